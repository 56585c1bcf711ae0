"""Where registrations run: the local process pool (pool.py) or, given a scheduler, a
Dask distributed cluster. Both take the same tasks (one shape each, picklable)
and give the same results; `make_runner` chooses. Dask is imported only when a scheduler
is given (core/base/cluster.py), so the core runs without it."""

from __future__ import annotations

import time
import uuid
from contextlib import ExitStack
from typing import Callable, Sequence

from ..base.progress import CancelCheck, Progress
from .pool import RegistrationRunner, RegistrationTask, _RunProgress, collector, register_task, submit_bounded
from .registration import Registration

__all__ = ["DaskRunner", "make_runner"]


def make_runner(jobs: int, scheduler: str | None = None, should_cancel=None):
    """The local RegistrationRunner (`jobs` processes; 1: in this process), or a
    DaskRunner on `scheduler` (tcp://host:port or local:N, core/base/cluster.py)."""
    if scheduler is None:
        return RegistrationRunner(jobs, should_cancel)
    return DaskRunner(scheduler, should_cancel)


class _PolledEvent:
    """The cluster-wide cancel Event `name`, asked at most every `interval` seconds (each
    ask is a round trip to the scheduler; ICP iterations come every few milliseconds)."""

    def __init__(self, name: str, interval: float = 0.5):
        from distributed import Event

        self.event, self.interval, self.asked, self.answer = Event(name), interval, float("-inf"), False

    def is_set(self) -> bool:
        now = time.monotonic()
        if now - self.asked >= self.interval:
            self.asked, self.answer = now, bool(self.event.is_set())
        return self.answer


def _cancel_event(name: str) -> _PolledEvent:
    return _PolledEvent(name)


def _register_on_worker(task: RegistrationTask, cancel_name: str) -> tuple[int, Registration]:
    """A Dask worker's registration; cancel is the cluster-wide Event `cancel_name`,
    checked between ICP iterations (at most twice a second)."""
    return task.index, register_task(task, None, _cancel_event(cancel_name))


def _call_on_worker(function: Callable, item, index: int, cancel_name: str):
    CancelCheck(_cancel_event(cancel_name), "correspondence")()
    return index, function(item)


class DaskRunner:
    """RegistrationRunner's interface (`run`, `map`, `close`) on a Dask cluster: each
    task is one shape, at most 2 per worker thread are submitted at a time, progress
    advances as shapes finish, cancel sets a cluster-wide Event the workers check
    between ICP iterations and cancels what is queued."""

    def __init__(self, scheduler: str, should_cancel=None):
        from distributed import Event

        from ..base.cluster import connect

        self._stack = ExitStack()
        self.client = self._stack.enter_context(connect(scheduler))
        self.cancel = CancelCheck(should_cancel, "correspondence")
        self.cancel_name = f"shapegen-cancel-{uuid.uuid4().hex}"
        self.cancel_event = Event(self.cancel_name, client=self.client)
        self.jobs = max(1, sum(self.client.nthreads().values()))

    def run(self, tasks: Sequence[RegistrationTask], progress: Progress, label: str) -> list[Registration]:
        tracker = _RunProgress(tasks, progress, label)
        results: list = [None] * len(tasks)

        def finished(index: int, result: Registration) -> None:
            results[index] = result
            tracker.finished(index, result.iterations)

        self._submit_bounded([(_register_on_worker, task, self.cancel_name) for task in tasks], finished)
        return results

    def map(self, function: Callable, items: Sequence, progress: Progress, message: Callable[[int], str]) -> list:
        results, finished = collector(len(items), progress, message)
        self._submit_bounded([(_call_on_worker, function, item, index, self.cancel_name)
                              for index, item in enumerate(items)], finished)
        return results

    def _submit_bounded(self, calls: list[tuple], finished: Callable) -> None:
        from distributed import wait

        def wait_some(pending):
            try:
                return wait(list(pending), timeout=0.1, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                return ()

        def stop(pending):
            self.cancel_event.set()
            self.client.cancel(list(pending))

        submit_bounded(calls, lambda call: self.client.submit(*call, pure=False), wait_some, 2 * self.jobs,
                       self.cancel, finished, stop)

    def close(self) -> None:
        self._stack.close()
