"""Background jobs: long core work in a separate Python process, with progress and cancel.

The Blender layer (and tests, and anything else) starts a `BackgroundJob`, then polls it;
polling never blocks. The worker is a plain Python process running `core/app/worker.py` with
the core importable (it never imports bpy: a child of Blender cannot). It talks back over
its stdout, one JSON object per line (progress as in core/base/progress.py):

    {"event": "progress", "fraction": 0.42,
     "stage": "correspondence: registering vase_003 (round 1 of 2, iteration 7)"}
    {"event": "done", "output": "/tmp/.../model.npz"}
    {"event": "failed", "error": "vase_007: mesh has no faces"}
    {"event": "cancelled"}

and listens on its stdin for the line "cancel" (cooperative cancel, checked between
iterations). If it does not stop within `cancel_grace` seconds after a cancel it is
terminated. Results are files written atomically by the worker; a cancelled or failed job
leaves no output file behind. The worker's temporary folder (TMPDIR) is one the job makes
and removes once the worker has ended, so a killed worker leaves no temporary files.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path

from ..base.child_process import MEMORY_ADVICE, how_it_ended

__all__ = ["BackgroundJob", "JobStatus", "JOB_STATES"]

JOB_STATES = ("pending", "running", "done", "failed", "cancelled")
WORKER_SCRIPT = Path(__file__).resolve().parent / "worker.py"


@dataclass
class JobStatus:
    state: str = "pending"
    fraction: float = 0.0
    stage: str = ""
    error: str = ""
    output: str = ""
    log: list[str] = field(default_factory=list)

    @property
    def finished(self) -> bool:
        return self.state in ("done", "failed", "cancelled")


class BackgroundJob:
    """One task (`worker.TASKS`) run in a child Python process.

    task: task name, e.g. "fit". arguments: JSON-serialisable dict for the task.
    python: interpreter for the child (default: this one; inside Blender, Blender's own
    Python). The child's sys.path is this process's, so bundled wheels (scipy) are found.
    """

    def __init__(self, task: str, arguments: dict, python: str | None = None, cancel_grace: float = 10.0):
        self.task = task
        self.arguments = dict(arguments)
        self.python = python or _python_executable()
        self.cancel_grace = cancel_grace
        self._status = JobStatus()
        self._lock = threading.Lock()
        self._process: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None
        self._cancel_requested_at: float | None = None
        self._stderr_tail: list[str] = []
        self._remove_temporary = lambda: None  # set by `start`: removes the worker's temporary folder

    # ------------------------------------------------------------------ control
    def start(self) -> "BackgroundJob":
        if self._process is not None:
            raise RuntimeError("job already started")
        env = dict(os.environ)
        paths = [str(WORKER_SCRIPT.parent.parent.parent)] + [p for p in sys.path if p]
        env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
        env.setdefault("OPENBLAS_NUM_THREADS", "1")
        # the worker's temporary files (its spill store, core/meshes/spill.py) go into a folder this
        # process removes when the job ends, however the worker ended (a killed worker cannot)
        self.temporary_folder = tempfile.mkdtemp(prefix=f"shapegen-job-{self.task}-")
        self._remove_temporary = weakref.finalize(self, shutil.rmtree, self.temporary_folder, True)
        env.update(TMPDIR=self.temporary_folder, TEMP=self.temporary_folder, TMP=self.temporary_folder)
        self._process = subprocess.Popen(
            [self.python, "-u", str(WORKER_SCRIPT), self.task, json.dumps(self.arguments)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        )
        with self._lock:
            self._status.state = "running"
        self._reader = threading.Thread(target=self._read_stdout, daemon=True)
        self._reader.start()
        threading.Thread(target=self._read_stderr, daemon=True).start()
        return self

    def cancel(self) -> None:
        """Ask the worker to stop; it is terminated if it has not after `cancel_grace` s."""
        if self._process is None or self._process.poll() is not None:
            return
        if self._cancel_requested_at is None:
            self._cancel_requested_at = time.monotonic()
            try:
                self._process.stdin.write("cancel\n")
                self._process.stdin.flush()
            except (BrokenPipeError, OSError):
                pass

    def poll(self) -> JobStatus:
        """The current status (never blocks)."""
        process = self._process
        if process is not None and process.poll() is not None:
            # the process ended: wait for the reader to consume the last lines
            if self._reader is not None:
                self._reader.join(timeout=2.0)
            with self._lock:
                if not self._status.finished:
                    if self._cancel_requested_at is not None:
                        self._status.state = "cancelled"
                    else:
                        self._status.state = "failed"
                        self._status.error = self._ended_message(process.returncode)
        elif (process is not None and self._cancel_requested_at is not None
              and time.monotonic() - self._cancel_requested_at > self.cancel_grace):
            process.terminate()
        with self._lock:
            status = JobStatus(self._status.state, self._status.fraction, self._status.stage,
                               self._status.error, self._status.output, list(self._status.log))
        if status.finished and process is not None and process.poll() is not None:
            self._remove_temporary()
        return status

    def wait(self, timeout: float | None = None, interval: float = 0.05) -> JobStatus:
        """Poll until finished (for scripts and tests; the UI polls from a timer instead)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            status = self.poll()
            if status.finished:
                return status
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {self.task} still running after {timeout} s")
            time.sleep(interval)

    def kill(self) -> None:
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
            self._process.wait()
        self._remove_temporary()

    # ------------------------------------------------------------------ internals
    def _ended_message(self, returncode: int) -> str:
        """One line for a worker that ended without saying so: killed by a signal (the
        out-of-memory killer sends SIGKILL), with the stage it was in; else its exit code
        and the last lines it wrote on stderr."""
        if returncode < 0:
            stage = f" during '{self._status.stage}'" if self._status.stage else ""
            return f"the {self.task} worker {how_it_ended(returncode)}{stage}, {MEMORY_ADVICE}"
        tail = " | ".join(self._stderr_tail[-3:])
        return f"worker exited with code {returncode}" + (f": {tail}" if tail else "")

    def _read_stdout(self) -> None:
        for line in self._process.stdout:
            line = line.strip()
            if not line:
                continue
            try:
                message = json.loads(line)
            except json.JSONDecodeError:
                with self._lock:
                    self._status.log.append(line)
                continue
            with self._lock:
                event = message.get("event")
                if event == "progress":
                    self._status.fraction = float(message.get("fraction", 0.0))
                    self._status.stage = str(message.get("stage", ""))
                elif event == "done":
                    self._status.state = "done"
                    self._status.fraction = 1.0
                    self._status.output = str(message.get("output", ""))
                elif event == "failed":
                    self._status.state = "failed"
                    self._status.error = str(message.get("error", "unknown error"))
                elif event == "cancelled":
                    self._status.state = "cancelled"

    def _read_stderr(self) -> None:
        for line in self._process.stderr:
            line = line.rstrip()
            if line:
                self._stderr_tail.append(line)
                del self._stderr_tail[:-20]


def _python_executable() -> str:
    """A Python interpreter for the worker: sys.executable, unless that is a Blender binary
    (older Blenders), in which case Blender's bundled python next to it."""
    exe = Path(sys.executable)
    if "python" in exe.name.lower():
        return str(exe)
    candidates = sorted(Path(sys.prefix).glob("bin/python3*")) + sorted(Path(sys.prefix).glob("bin/python*.exe"))
    if candidates:
        return str(candidates[0])
    return str(exe)
