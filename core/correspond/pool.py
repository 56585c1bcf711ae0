"""Registration tasks run in this process or in a pool of spawned worker processes, with
cooperative cancel and the one conversion of their ICP iterations into progress fractions."""

from __future__ import annotations

import concurrent.futures as futures
import multiprocessing
import os
import queue as queue_module
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from ..child_process import exit_with_parent
from ..geometry import TargetSurface
from ..progress import CancelCheck, Progress
from .registration import Registration, register
from .settings import CorrespondenceSettings

__all__ = ["RegistrationRunner", "RegistrationTask"]


@dataclass(frozen=True)
class RegistrationTask:
    """Everything one worker needs to register the template to one shape (picklable)."""

    index: int  # position in the run's task list
    name: str
    vertices: np.ndarray  # registration frame
    faces: np.ndarray
    landmarks: np.ndarray  # registration frame
    landmark_normals: np.ndarray
    template: np.ndarray  # registration frame
    template_normals: np.ndarray
    edges: np.ndarray
    settings: CorrespondenceSettings


# worker-process state set by _init_worker (spawned processes only)
_WORKER: dict[str, Any] = {}


def _init_worker(progress_queue, cancel_event) -> None:
    exit_with_parent()
    _WORKER["queue"] = progress_queue
    _WORKER["cancel"] = cancel_event


def _register(task: RegistrationTask, on_iteration, should_cancel) -> Registration:
    """Register the template to one shape (in this process or a worker)."""
    surface = TargetSurface(task.vertices, task.faces)
    return register(task.template, task.edges, surface, task.landmarks, task.settings, task.template_normals,
                    task.landmark_normals, on_iteration, should_cancel)


def _run_in_worker(task: RegistrationTask, run: int) -> tuple[int, Registration]:
    """A pool worker's task: iterations go to the parent's queue as (run, index, iteration)."""
    progress_queue = _WORKER["queue"]
    result = _register(task, lambda iteration: progress_queue.put((run, task.index, iteration)), _WORKER["cancel"])
    return task.index, result


class _RunProgress:
    """Progress of one run of registration tasks, its own 0..1: every task has an equal
    share, filled by its ICP iterations up to its cap (settings.max_iterations) and
    completely once it has finished. Late iteration events of a finished task change
    nothing, so the fraction never decreases and is 1.0 when all tasks have finished."""

    def __init__(self, tasks: Sequence[RegistrationTask], progress: Progress, label: str):
        self.tasks, self.progress, self.label = tasks, progress, label
        self.shares = [0.0] * len(tasks)

    def iteration(self, index: int, iteration: int) -> None:
        task = self.tasks[index]
        self.shares[index] = max(self.shares[index], min(iteration / task.settings.max_iterations, 1.0))
        self._report(f"registering {task.name} ({self.label}, iteration {iteration})")

    def finished(self, index: int, iterations: int) -> None:
        self.shares[index] = 1.0
        self._report(f"registered {self.tasks[index].name} ({self.label}, {iterations} iterations)")

    def _report(self, message: str) -> None:
        self.progress(sum(self.shares) / len(self.shares), message)


class RegistrationRunner:
    """Runs registration tasks in-process (jobs = 1) or in a pool of spawned processes,
    with progress per ICP iteration and cooperative cancel (`should_cancel`: None, a
    callable or an Event-like object; see core/progress.py).

    A spawned worker loads numpy, and with it OpenBLAS, before any code of ours runs in it,
    and OpenBLAS reads OPENBLAS_NUM_THREADS only then. So while the pool is open this
    process's environment holds OPENBLAS_NUM_THREADS=1 (unless the caller set it), which
    the workers inherit when they start; this process's BLAS, loaded already, keeps its
    threads, and `close` takes the variable out again."""

    def __init__(self, jobs: int, should_cancel=None):
        self.jobs = jobs
        self.cancel = CancelCheck(should_cancel, "correspondence")
        self.pool = None
        self._runs = 0
        self._set_blas_threads = False
        if jobs > 1:
            self._set_blas_threads = "OPENBLAS_NUM_THREADS" not in os.environ
            if self._set_blas_threads:
                os.environ["OPENBLAS_NUM_THREADS"] = "1"
            context = multiprocessing.get_context("spawn")
            self.queue = context.Queue()
            self.cancel_event = context.Event()
            self.pool = futures.ProcessPoolExecutor(
                max_workers=jobs, mp_context=context, initializer=_init_worker,
                initargs=(self.queue, self.cancel_event))

    def run(self, tasks: Sequence[RegistrationTask], progress: Progress, label: str) -> list[Registration]:
        """Register every task; `progress` gets this run's own fraction (see `_RunProgress`),
        its messages name the shape and `label` (e.g. "round 1 of 2")."""
        self._runs += 1
        tracker = _RunProgress(tasks, progress, label)
        results: list[Registration | None] = [None] * len(tasks)
        if self.pool is None:
            for task in tasks:
                result = _register(task, lambda iteration: tracker.iteration(task.index, iteration), self.cancel)
                results[task.index] = result
                tracker.finished(task.index, result.iterations)
            return results
        pending = {self.pool.submit(_run_in_worker, task, self._runs): task for task in tasks}
        try:
            while pending:
                done, _ = futures.wait(pending, timeout=0.1, return_when=futures.FIRST_COMPLETED)
                self._drain(tracker)
                self.cancel()
                for future in done:
                    pending.pop(future)
                    index, result = future.result()
                    results[index] = result
                    tracker.finished(index, result.iterations)
        except BaseException:
            self.cancel_event.set()
            for future in pending:
                future.cancel()
            raise
        return results

    def _drain(self, tracker: _RunProgress | None) -> None:
        """Pass the queued iteration events of the current run to `tracker` (None: drop them)."""
        while True:
            try:
                run, index, iteration = self.queue.get_nowait()
            except queue_module.Empty:
                return
            if tracker is not None and run == self._runs:
                tracker.iteration(index, iteration)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self._drain(None)
            self.queue.close()
        if self._set_blas_threads:
            os.environ.pop("OPENBLAS_NUM_THREADS", None)
