"""The background-job manager: one core `BackgroundJob` at a time, polled without blocking.

This module never imports bpy. It owns the running worker process (core/app/jobs.py), its
temporary folder and the callback that applies the result. Whoever drives the UI calls
`MANAGER.poll()` regularly on the main thread:

* in Blender with a window, a `bpy.app.timers` function does (runtime.py);
* in background mode / tests (timers never fire there) the caller loops over
  `jobs.poll_job()` or `MANAGER.poll()` itself.

An optional `setup()` (bpy-free, e.g. writing the input file) runs on a helper thread
before the worker starts; the job counts as running meanwhile. When the worker has
ended, an optional `prepare(status)` runs on a helper thread (bpy-free
work such as loading and validating the result file, so the main thread never waits for
it); meanwhile `poll()` still reports the job as running ("loading the result"). Then
`poll()` calls `on_finish(status, prepared)` exactly once, on the polling (= main) thread,
with prepare's return value (or the exception it raised), and forgets the job and removes
its temporary folder. So a result is only ever applied to Blender data on the main thread,
and a cancelled or failed job never touches the scene.
"""

from __future__ import annotations

import shutil
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from ...core.app.jobs import BackgroundJob, JobStatus

__all__ = ["JobManager", "MANAGER"]


class JobManager:
    """Holds at most one running job (Prepare, Find Correspondences or Fit). Not
    thread-safe: call from the main thread."""

    def __init__(self):
        self.job: BackgroundJob | None = None
        self.label = ""
        self.payload: dict = {}
        self.last_status: JobStatus | None = None
        self.started_at = 0.0
        self._on_finish: Callable[[JobStatus, Any], None] | None = None
        self._prepare: Callable[[JobStatus], Any] | None = None
        self._prepared: list = []  # [status, result or exception] once prepare has run
        self._thread: threading.Thread | None = None
        self._setup_thread: threading.Thread | None = None
        self._setup_box: list = []
        self._cancel_pending = False
        self._folder: Path | None = None

    @property
    def running(self) -> bool:
        return self.job is not None

    @property
    def task(self) -> str:
        """The running job's core task ("prepare", "correspond", "fit", ...), or ""."""
        return self.job.task if self.job is not None else ""

    @property
    def elapsed(self) -> float:
        return time.monotonic() - self.started_at if self.running else 0.0

    def start(self, job: BackgroundJob, on_finish: Callable[[JobStatus, Any], None], *, label: str = "",
              folder: Path | None = None, payload: dict | None = None,
              prepare: Callable[[JobStatus], Any] | None = None,
              setup: Callable[[], None] | None = None) -> None:
        """Start `job` (not yet started). `folder` is deleted when the job has finished.
        `setup` (helper thread, before the worker starts) and `prepare` (helper thread,
        after it ended) must not touch bpy."""
        if self.running:
            raise RuntimeError(f"a job is already running ({self.label})")
        self.label = label
        self.payload = dict(payload or {})
        self._on_finish = on_finish
        self._prepare = prepare
        self._prepared = []
        self._thread = None
        self._cancel_pending = False
        self._folder = folder
        self.last_status = JobStatus(state="running", stage="starting")
        self.started_at = time.monotonic()
        if setup is not None:
            self._setup_box = []
            self._setup_thread = threading.Thread(target=self._run_setup, args=(setup, job, self._setup_box),
                                                  daemon=True)
            self.job = job
            self._setup_thread.start()
            return
        try:
            job.start()
        except Exception:
            self._clear()
            raise
        self.job = job

    @staticmethod
    def _run_setup(setup, job: BackgroundJob, box: list) -> None:
        try:
            setup()
            job.start()
        except Exception as exc:  # reported as a failed job by poll()
            box.append(exc)
            return
        box.append(None)

    def poll(self) -> JobStatus | None:
        """The current status (None when nothing ever ran). Never blocks on the worker.

        On the poll that sees the job (and its `prepare` step) finished, calls
        `on_finish(status, prepared)` and clears the job.
        """
        if self.job is None:
            return self.last_status
        if self._setup_thread is not None:  # setup runs on its thread; the worker has not started
            if self._setup_thread.is_alive():
                return self.last_status
            self._setup_thread = None
            error = self._setup_box[0] if self._setup_box else RuntimeError("setup ended without a result")
            if error is not None:
                return self._finish(JobStatus(state="failed", error=f"{type(error).__name__}: {error}"), None)
            if self._cancel_pending:
                self.job.cancel()
        if self._thread is not None:  # the worker has ended; prepare runs on its thread
            if self._thread.is_alive():
                return self.last_status
            status, prepared = self._prepared
            return self._finish(status, prepared)
        status = self.job.poll()
        if not status.finished:
            self.last_status = status
            return status
        if self._prepare is None:
            return self._finish(status, None)
        self._prepared = []  # this job's own box: a killed job's late thread cannot fill another's
        self._thread = threading.Thread(target=self._run_prepare, args=(self._prepare, status, self._prepared),
                                        daemon=True)
        self._thread.start()
        self.last_status = replace(status, state="running", stage="loading the result")
        return self.last_status

    @staticmethod
    def _run_prepare(prepare, status: JobStatus, box: list) -> None:
        try:
            result = prepare(status)
        except Exception as exc:  # handed to on_finish, which reports it
            result = exc
        box[:] = [status, result]

    def _finish(self, status: JobStatus, prepared) -> JobStatus:
        self.last_status = status
        callback = self._on_finish
        try:
            if callback is not None:
                callback(status, prepared)
        finally:
            self._clear()
        return status

    def cancel(self) -> bool:
        """Ask the running job to stop (cooperative; terminated after its grace time)."""
        if self.job is None:
            return False
        if self._setup_thread is not None:
            self._cancel_pending = True  # the worker is not started yet: cancel it once it is
        self.job.cancel()
        return True

    def kill(self, reason: str = "the job was stopped") -> None:
        """Stop the worker now and forget the job without calling back (unregister, file
        load). The status says so: state "cancelled", stage "cancelled: <reason>" (error:
        `reason`), so a script polling the job sees it end."""
        if self._setup_thread is not None:
            self._setup_thread.join()  # let it finish starting the worker, then stop that
        if self.job is not None:
            self.job.kill()
            fraction = self.last_status.fraction if self.last_status is not None else 0.0
            self.last_status = JobStatus(state="cancelled", fraction=fraction, stage=f"cancelled: {reason}",
                                         error=reason)
        self._clear()

    def _clear(self) -> None:
        self.job = None
        self._on_finish = None
        self._prepare = None
        self._thread = None
        self._setup_thread = None
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None


#: the add-on's one job slot
MANAGER = JobManager()
