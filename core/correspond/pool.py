"""Registration tasks run in this process or in a pool of spawned worker processes, with
per-iteration progress forwarded to the caller and cooperative cancel."""

from __future__ import annotations

import concurrent.futures as futures
import multiprocessing
import os
import queue as queue_module
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import Cancelled
from ..geometry import TargetSurface
from .registration import Registration, register
from .settings import CorrespondenceSettings

__all__ = ["ProgressCallback", "RegistrationRunner", "RegistrationTask"]

#: progress(shape_name, stage, iteration). Stages, in order of a run:
#: "template" (template chosen; shape = its name, iteration 0),
#: "register" (one ICP iteration done on `shape`; iteration counts from 1),
#: "registered" (`shape` finished; iteration = iterations used),
#: "mean template" (groupwise re-estimation; iteration = round number, from 1).
ProgressCallback = Callable[[str, str, int], None]


@dataclass(frozen=True)
class RegistrationTask:
    """Everything one worker needs to register the template to one shape (picklable)."""

    index: int
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
    _WORKER["queue"] = progress_queue
    _WORKER["cancel"] = cancel_event


def _run_task(task: RegistrationTask, report=None, should_cancel=None) -> tuple[int, Registration]:
    """Register one shape (in this process or a worker)."""
    if report is None and "queue" in _WORKER:
        progress_queue = _WORKER["queue"]
        report = lambda name, stage, it: progress_queue.put((name, stage, it))  # noqa: E731
        should_cancel = _WORKER["cancel"].is_set
    surface = TargetSurface(task.vertices, task.faces)
    on_iteration = None if report is None else (lambda it: report(task.name, "register", it))
    result = register(task.template, task.edges, surface, task.landmarks, task.settings,
                      task.template_normals, task.landmark_normals, on_iteration, should_cancel)
    return task.index, result


class RegistrationRunner:
    """Runs registration tasks in-process (jobs = 1) or in a pool of spawned processes,
    forwarding per-iteration progress and cooperative cancel.

    A spawned worker loads numpy, and with it OpenBLAS, before any code of ours runs in it,
    and OpenBLAS reads OPENBLAS_NUM_THREADS only then. So while the pool is open this
    process's environment holds OPENBLAS_NUM_THREADS=1 (unless the caller set it), which
    the workers inherit when they start; this process's BLAS, loaded already, keeps its
    threads, and `close` takes the variable out again."""

    def __init__(self, jobs: int, report: ProgressCallback, should_cancel: Callable[[], bool]):
        self.jobs = jobs
        self.report = report
        self.should_cancel = should_cancel
        self.pool = None
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

    def run(self, tasks: Sequence[RegistrationTask]) -> list[Registration]:
        results: list[Registration | None] = [None] * len(tasks)
        if self.pool is None:
            for task in tasks:
                index, result = _run_task(task, self.report, self.should_cancel)
                results[index] = result
                self.report(task.name, "registered", result.iterations)
            return results
        pending = {self.pool.submit(_run_task, task): task for task in tasks}
        try:
            while pending:
                done, _ = futures.wait(pending, timeout=0.1, return_when=futures.FIRST_COMPLETED)
                self._drain()
                if self.should_cancel():
                    self.cancel_event.set()
                    raise Cancelled("correspondence cancelled")
                for future in done:
                    task = pending.pop(future)
                    index, result = future.result()
                    results[index] = result
                    self.report(task.name, "registered", result.iterations)
        except BaseException:
            self.cancel_event.set()
            for future in pending:
                future.cancel()
            raise
        return results

    def _drain(self) -> None:
        while True:
            try:
                name, stage, iteration = self.queue.get_nowait()
            except queue_module.Empty:
                return
            self.report(name, stage, iteration)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self._drain()
            self.queue.close()
        if self._set_blas_threads:
            os.environ.pop("OPENBLAS_NUM_THREADS", None)
