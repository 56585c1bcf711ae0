"""Registration tasks run in this process or in a pool of spawned worker processes, with
cooperative cancel and the one conversion of their ICP iterations into progress fractions.

A task carries ONE shape (its surface, or the proxy of a dense one, in the normalised
frame, as references to the collection's arrays: the frame change happens in the
worker), so neither this process nor a worker holds more per task as the collection
grows; at most `2 · jobs` tasks are handed to the pool at a time."""

from __future__ import annotations

import concurrent.futures as futures
import multiprocessing
import os
import queue as queue_module
import signal
import time
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..base.child_process import MEMORY_ADVICE, exit_with_parent, how_it_ended
from ..base.errors import WorkerDied
from ..geometry import TargetSurface
from ..base.progress import CancelCheck, Progress
from .registration import Registration, RegistrationProblem, register
from .settings import CorrespondenceSettings

__all__ = ["RegistrationRunner", "RegistrationTask", "dead_worker_task"]


@dataclass(frozen=True)
class RegistrationTask:
    """Everything one worker needs to register the template to one shape (picklable).
    The shape's surface and landmarks are in the normalised frame; p -> (p − centre) /
    scale takes them to the registration frame the template, its normals' frame and the
    result are in."""

    index: int  # position in the run's task list
    name: str
    vertices: np.ndarray  # normalised frame: the shape's surface (or its proxy, core/meshes/simplify.py)
    faces: np.ndarray
    landmarks: np.ndarray  # normalised frame
    landmark_normals: np.ndarray
    template: np.ndarray  # registration frame
    template_normals: np.ndarray
    edges: np.ndarray
    settings: CorrespondenceSettings
    centre: np.ndarray  # the registration frame
    scale: float
    template_between: np.ndarray | None = None  # positions between turning lines (features.py; None: not compared)
    plain_points: np.ndarray | None = None  # (L,) bool: compared by position and normal only (features.merged_regions)


# worker-process state set by _init_worker (spawned processes only)
_WORKER: dict[str, Any] = {}


def _init_worker(progress_queue, cancel_event) -> None:
    exit_with_parent()
    _WORKER["queue"] = progress_queue
    _WORKER["cancel"] = cancel_event


#: test hook: a worker given a task of this shape name kills itself with SIGKILL,
#: as the out-of-memory killer would
KILL_ON_SHAPE_VARIABLE = "SHAPEGEN_TEST_KILL_WORKER_ON"


def _started(run: int, index: int, name: str) -> None:
    """Tell the parent this worker took task `index` of `run` (so a worker that dies is
    known by its shape); the test hook `KILL_ON_SHAPE_VARIABLE` acts here."""
    _WORKER["queue"].put((run, index, ("started", os.getpid())))
    if name and os.environ.get(KILL_ON_SHAPE_VARIABLE) == name:
        import time

        time.sleep(0.5)  # let the queue's feeder thread deliver "started" first
        os.kill(os.getpid(), signal.SIGKILL)


def register_task(task: RegistrationTask, on_iteration=None, should_cancel=None) -> Registration:
    """Register the template to one shape (in this process or any worker)."""
    surface = TargetSurface((task.vertices - task.centre) / task.scale, task.faces)
    problem = RegistrationProblem(task.template, task.edges, surface, (task.landmarks - task.centre) / task.scale,
                                  task.settings, task.template_normals, task.landmark_normals,
                                  template_between=task.template_between, plain_points=task.plain_points)
    return register(problem, on_iteration, should_cancel)


def _run_in_worker(task: RegistrationTask, run: int) -> tuple[int, Registration]:
    """A pool worker's task: iterations go to the parent's queue as (run, index, iteration)."""
    progress_queue = _WORKER["queue"]
    _started(run, task.index, task.name)
    result = register_task(task, lambda iteration: progress_queue.put((run, task.index, iteration)),
                           _WORKER["cancel"])
    return task.index, result


def _call_in_worker(function: Callable, item, index: int, run: int):
    """A pool worker's call of `function(item)` (`RegistrationRunner.map`); skipped once
    cancel was asked."""
    CancelCheck(_WORKER["cancel"], "correspondence")()
    _started(run, index, _item_name(item, index))
    return index, function(item)


def submit_bounded(calls: list[tuple], submit: Callable, wait_some: Callable, limit: int, check: Callable,
                   finished: Callable, stop: Callable) -> None:
    """Submit `calls` with at most `limit` pending; `wait_some(pending)` returns finished
    futures (after a short wait), `check()` raises to cancel, each future's result is
    (index, value) for `finished`; on any exception `stop(pending)` before re-raising."""
    waiting = list(reversed(calls))
    pending: set = set()
    try:
        while waiting or pending:
            while waiting and len(pending) < limit:
                pending.add(submit(waiting.pop()))
            done = wait_some(pending)
            check()
            for future in done:
                pending.discard(future)
                finished(*future.result())
    except BaseException:
        stop(pending)
        raise


def collector(count: int, progress: Progress, message: Callable[[int], str]) -> tuple[list, Callable]:
    """(results, finished): `finished(index, result)` stores a result of a map over `count`
    items and reports the share done with `message(index)`."""
    results: list = [None] * count
    done = [0]

    def finished(index: int, result) -> None:
        results[index] = result
        done[0] += 1
        progress(done[0] / count, message(index))

    return results, finished


class _RunProgress:
    """Progress of one run of registration tasks, its own 0..1: every task has an equal
    share, filled by its ICP iterations up to its cap (settings.iterations.max_iterations) and
    completely once it has finished. Late iteration events of a finished task change
    nothing, so the fraction never decreases and is 1.0 when all tasks have finished."""

    def __init__(self, tasks: Sequence[RegistrationTask], progress: Progress, label: str):
        self.tasks, self.progress, self.label = tasks, progress, label
        self.shares = [0.0] * len(tasks)

    def iteration(self, index: int, iteration: int) -> None:
        task = self.tasks[index]
        self.shares[index] = max(self.shares[index], min(iteration / task.settings.iterations.max_iterations, 1.0))
        self._report(f"registering {task.name} ({self.label}, iteration {iteration})")

    def finished(self, index: int, iterations: int) -> None:
        self.shares[index] = 1.0
        self._report(f"registered {self.tasks[index].name} ({self.label}, {iterations} iterations)")

    def _report(self, message: str) -> None:
        self.progress(sum(self.shares) / len(self.shares), message)


def _item_name(item, index: int) -> str:
    """The shape a task or mapped item is about (its `name`, or its place)."""
    return str(getattr(item, "name", None) or f"item {index + 1}")


def worker_death_message(name: str, exitcode: int | None, jobs: int) -> str:
    """One line: which shape a dead worker was working on, how it ended, the likely cause
    and what to try."""
    return f"{name}: the worker process working on it {how_it_ended(exitcode)}, {MEMORY_ADVICE}; this run used {jobs}"


class RegistrationRunner:
    """Runs registration tasks in-process (jobs = 1) or in a pool of spawned processes,
    with progress per ICP iteration and cooperative cancel (`should_cancel`: None, a
    callable or an Event-like object; see core/base/progress.py).

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
        self._started: dict[int, int] = {}  # task index -> pid of the worker that took it (this run), in order
        self._finished: set[int] = set()  # task indices of this run with a result
        self._workers: dict = {}  # pid -> the pool's worker processes seen (their exit codes tell how they ended)
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
                result = register_task(task, lambda iteration: tracker.iteration(task.index, iteration), self.cancel)
                results[task.index] = result
                tracker.finished(task.index, result.iterations)
            return results

        def finished(index: int, result: Registration) -> None:
            results[index] = result
            tracker.finished(index, result.iterations)

        self._submit_bounded([(_run_in_worker, task, self._runs) for task in tasks], finished, tracker,
                             [task.name for task in tasks])
        return results

    def map(self, function: Callable, items: Sequence, progress: Progress, message: Callable[[int], str]) -> list:
        """[function(item) for item in items], in the workers when there are any (`function`
        must then be a module-level function and the items picklable), in order; progress
        after each item with `message(index)`, cancel checked between items."""
        results, finished = collector(len(items), progress, message)
        if self.pool is None:
            for index, item in enumerate(items):
                self.cancel()
                finished(index, function(item))
            return results
        self._runs += 1
        self._submit_bounded([(_call_in_worker, function, item, index, self._runs) for index, item in enumerate(items)],
                             finished, None, [_item_name(item, index) for index, item in enumerate(items)])
        return results

    def _submit_bounded(self, calls: list[tuple], finished: Callable, tracker: "_RunProgress | None",
                        names: list[str]) -> None:
        """Run the calls (function, *arguments; each returns (index, result)) in the pool
        with at most 2 · jobs submitted at a time (a submitted call holds its pickled shape
        in the pool's queue), passing progress events to `tracker` and results to
        `finished(index, result)`; cancel stops the workers at their next check. A worker
        that dies (BrokenProcessPool) ends the run with `WorkerDied` naming the shape it
        had started (`names[index]`) and its signal."""
        self._started, self._finished = {}, set()

        def wait_some(pending):
            self._workers.update(getattr(self.pool, "_processes", None) or {})
            done, _ = futures.wait(pending, timeout=0.1, return_when=futures.FIRST_COMPLETED)
            self._drain(tracker)
            return done

        def stop(pending):
            self.cancel_event.set()
            for future in pending:
                future.cancel()

        def finished_here(index: int, result) -> None:
            self._finished.add(index)
            finished(index, result)

        def submit(call):
            future = self.pool.submit(*call)
            # the pool starts its workers on a submit: known at once, so a worker killed before
            # the first wait is still named with its signal
            self._workers.update(getattr(self.pool, "_processes", None) or {})
            return future

        try:
            submit_bounded(calls, submit, wait_some, 2 * self.jobs, self.cancel, finished_here, stop)
        except BrokenProcessPool:
            raise self._death(names) from None

    def _death(self, names: list[str]) -> WorkerDied:
        """The error of a broken pool: the shape a dead worker was working on (the last task
        it started and did not finish; a worker ended by a signal first) and how it ended."""
        self._drain(None)
        ended = {}
        for pid, process in self._workers.items():
            process.join(timeout=1.0)
            # the pool's own thread may be reaping it at the same moment: ask again briefly
            for _ in range(40):
                if process.exitcode is not None:
                    break
                time.sleep(0.05)
            ended[pid] = process.exitcode
        unfinished = [(index, pid) for index, pid in self._started.items() if index not in self._finished]
        if not unfinished:
            return WorkerDied(f"a worker process ended without a result, {MEMORY_ADVICE}; this run used {self.jobs}")
        index, pid = dead_worker_task(unfinished, ended)
        return WorkerDied(worker_death_message(names[index], ended.get(pid), self.jobs))

    def _drain(self, tracker: _RunProgress | None) -> None:
        """Pass the queued iteration events of the current run to `tracker` (None: drop them)."""
        while True:
            try:
                run, index, iteration = self.queue.get_nowait()
            except queue_module.Empty:
                return
            if run != self._runs:
                continue
            if isinstance(iteration, tuple):  # ("started", pid): a worker took the task
                self._started[index] = iteration[1]
            elif tracker is not None:
                tracker.iteration(index, iteration)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self._drain(None)
            self.queue.close()
        if self._set_blas_threads:
            os.environ.pop("OPENBLAS_NUM_THREADS", None)


def dead_worker_task(unfinished: list[tuple[int, int]], ended: dict[int, int | None]) -> tuple[int, int]:
    """(task index, worker pid) of the task whose worker's death broke the pool, from the
    started, unfinished tasks (in start order) and the workers' exit codes: a worker ended by
    a signal other than SIGTERM first (the pool itself ends the surviving workers of a broken
    pool with SIGTERM, so those are its siblings), then any ended by a signal, then any. A
    worker runs its tasks one after another: its last started one is the one it was on."""
    by_signal = [(index, pid) for index, pid in unfinished if (ended.get(pid) or 0) < 0]
    not_by_pool = [(index, pid) for index, pid in by_signal if ended.get(pid) != -signal.SIGTERM]
    return (not_by_pool or by_signal or unfinished)[-1]

