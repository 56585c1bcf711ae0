"""Worker processes never outlive the process that started them.

A pool worker blocks on its task queue, and the queue's pipe stays open in the worker
itself, so when its parent is terminated (Blender's Cancel after the grace period, a
killed `shapegen` run) nothing tells it: it would finish its registration and then wait
forever. `exit_with_parent` watches the parent's sentinel (a pipe on POSIX, the process
handle on Windows) from a daemon thread and ends the worker as soon as the parent is gone.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading

__all__ = ["exit_with_parent", "how_it_ended", "MEMORY_ADVICE"]

#: what a worker that died of a signal most likely met, and what to try
MEMORY_ADVICE = ("most likely because the machine ran out of memory; try fewer parallel jobs (--jobs, or \"jobs\" "
                 "in Extra Settings)")

#: exit status of a worker ended because its parent went away
ORPHAN_EXIT_CODE = 70


def exit_with_parent() -> None:
    """In a process started by `multiprocessing`: exit at once when the parent exits.
    A no-op in a process that multiprocessing did not start."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        parent.join()  # returns when the parent's sentinel closes, i.e. the parent has exited
        os._exit(ORPHAN_EXIT_CODE)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def how_it_ended(exitcode: int | None) -> str:
    """How a process with this exit code ended, for a message: "was killed by signal 9
    (SIGKILL)" for a negative code (POSIX: the signal), else its exit status."""
    if exitcode is not None and exitcode < 0:
        try:
            return f"was killed by signal {-exitcode} ({signal.Signals(-exitcode).name})"
        except ValueError:
            return f"was killed by signal {-exitcode}"
    return "ended without a result" + ("" if exitcode is None else f" (exit status {exitcode})")
