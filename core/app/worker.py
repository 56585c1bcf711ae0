"""Worker process entry for `jobs.BackgroundJob`: `python worker.py TASK JSON_ARGUMENTS`.

Runs one task from `TASKS`, reporting progress as JSON lines on stdout and honouring a
"cancel" line on stdin (see jobs.py for the protocol). Never imports bpy.
"""

from __future__ import annotations

import _thread
import json
import sys
import threading
import traceback
from pathlib import Path

if __name__ == "__main__" and not __package__:
    # started as a script: import the core's folder (this file's grandparent) as a package
    # so relative imports work
    _core = Path(__file__).resolve().parent.parent
    sys.path.insert(0, str(_core.parent))
    import importlib

    _module = importlib.import_module(f"{_core.name}.{Path(__file__).resolve().parent.name}.worker")
    sys.exit(_module.main(sys.argv[1:]))

# Note: nothing below imports the core at module level. Process pools started by a task
# (correspondence runs shapes in parallel, spawn context) re-run this file by path as
# "__mp_main__", without a package; it must then only define functions.


def _emit(**message) -> None:
    sys.stdout.write(json.dumps(message) + "\n")
    sys.stdout.flush()


#: seconds a task has to stop by itself (its own cancel checks) after a cancel before the
#: worker interrupts it
CANCEL_GRACE = 0.5


class _CancelOnStdin:
    """Cancel from the parent: `event` (the tasks' `should_cancel`) is set when the parent
    writes "cancel" on stdin, or closes it (the parent is gone). A task that has not
    stopped by itself `CANCEL_GRACE` s later (a step with no cancel check, e.g. a long
    loop in a library) is interrupted: `_thread.interrupt_main` raises KeyboardInterrupt
    in the main thread at its next Python instruction, which `main` reports as cancelled.
    So a cancel takes effect within about `CANCEL_GRACE` s in every stage."""

    def __init__(self, grace: float = CANCEL_GRACE):
        self.event = threading.Event()
        self.grace = grace
        self._ended = threading.Event()
        self._lock = threading.Lock()
        threading.Thread(target=self._listen, daemon=True).start()

    def _listen(self) -> None:
        for line in sys.stdin:
            if line.strip() == "cancel":
                break
        self.event.set()
        if self._ended.wait(self.grace):
            return
        with self._lock:
            if not self._ended.is_set():
                _thread.interrupt_main()

    def task_ended(self) -> None:
        """The task returned or raised: nothing may interrupt the main thread any more."""
        with self._lock:
            self._ended.set()


def task_fit(arguments: dict, progress, should_cancel) -> str:
    """Fit a GenerativeShapeModel from raw meshes (`meshes`: core.meshes.meshset .npz, prepared
    here first with `keep_pose`, one bool per mesh, as in task_prepare), from an
    already prepared collection (`prepared`: PreparedCollection .npz; no second Prepare) or
    from the meshes and correspondence of an earlier model (`correspondence_of`: a model
    file; only the shape model is fitted); `settings` are FitSettings as plain data
    (FitSettings.from_dict); `jobs` and `scheduler`, where the registrations run
    (`RunOptions`), are arguments of their own, as in task_correspond."""
    from ..preprocess.collection import PreparedCollection, prepare_meshes
    from ..meshes.meshset import load_mesh_set
    from .fit_settings import FitSettings, RunOptions
    from .shape_model import GenerativeShapeModel
    from .pipeline import fit_meshes, fit_shape_model
    from ..base.progress import sub_range
    from ..meshes.spill import SpillStore

    settings = FitSettings.from_dict(arguments.get("settings", {}))
    run = RunOptions(jobs=arguments.get("jobs"), scheduler=arguments.get("scheduler"))
    if "correspondence_of" in arguments:
        earlier = GenerativeShapeModel.load(arguments["correspondence_of"])
        model = fit_shape_model(earlier.meshes, earlier.correspondence, settings, progress=progress,
                                should_cancel=should_cancel)
        return _save_result(model, arguments, should_cancel, "fit")
    with SpillStore() as spill:  # dense meshes on disk until the model is written (core/meshes/spill.py)
        if "prepared" in arguments:
            source = PreparedCollection.load(arguments["prepared"])
        else:  # prepared here, as fit_meshes would (progress 0-0.15), so the kept poses count
            source = prepare_meshes(_kept(load_mesh_set(arguments["meshes"]), spill), settings.prepare,
                                    progress=sub_range(progress, 0.0, 0.15, "prepare: "), should_cancel=should_cancel,
                                    keep_pose=arguments.get("keep_pose"))
        model = fit_meshes(source, settings, progress=progress, should_cancel=should_cancel, jobs=run.jobs,
                           scheduler=run.scheduler)
        return _save_result(model, arguments, should_cancel, "fit")


def _kept(meshes: list, spill) -> list:
    """The meshes with the dense ones moved into the run's spill store (core/meshes/spill.py), so
    the stages after loading hold one at a time."""
    for index, mesh in enumerate(meshes):
        meshes[index] = spill.keep(mesh)
    return meshes


def _save_result(result, arguments: dict, should_cancel, task: str) -> str:
    """The shared end of a task: nothing is written once cancelled; else `result.save` to
    arguments["output"], whose path is the task's output."""
    from ..base.progress import CancelCheck

    CancelCheck(should_cancel, task)()
    output = Path(arguments["output"])
    result.save(output)
    return str(output)


def task_prepare(arguments: dict, progress, should_cancel) -> str:
    """Align, scale and landmark meshes from an .npz (core.meshes.meshset) into a prepared
    collection .npz (PreparedCollection.save); `settings` are PrepareSettings as plain data,
    `keep_pose` one bool per mesh (keep its pose) or absent. Cancel is checked at every
    progress step (after each shape's stage)."""
    from ..preprocess.collection import PrepareSettings, prepare_meshes
    from ..meshes.meshset import load_mesh_set
    from ..meshes.spill import SpillStore

    settings = PrepareSettings.from_dict(arguments.get("settings", {}))
    with SpillStore() as spill:
        meshes = _kept(load_mesh_set(arguments["meshes"]), spill)
        prepared = prepare_meshes(meshes, settings, progress=progress, should_cancel=should_cancel,
                                  keep_pose=arguments.get("keep_pose"))
        return _save_result(prepared, arguments, should_cancel, "prepare")


def task_correspond(arguments: dict, progress, should_cancel) -> str:
    """Dense correspondence of a prepared collection (.npz written by PreparedCollection.save);
    `settings` are CorrespondenceSettings as plain data, `jobs` and `scheduler` where the
    registrations run (`RunOptions`)."""
    from ..preprocess.collection import PreparedCollection
    from ..correspond import CorrespondenceSettings, correspond
    from .fit_settings import RunOptions

    prepared = PreparedCollection.load(arguments["prepared"])
    settings = CorrespondenceSettings.from_dict(arguments.get("settings", {}))
    run = RunOptions(jobs=arguments.get("jobs"), scheduler=arguments.get("scheduler"))
    result = correspond(prepared, settings, template=arguments.get("template") or None, jobs=run.jobs,
                        scheduler=run.scheduler, progress=progress, should_cancel=should_cancel)
    return _save_result(result, arguments, should_cancel, "correspondence")


def task_selftest(arguments: dict, progress, should_cancel) -> str:
    """A tiny task for tests of the job machinery: counts, sleeps, can fail, crash, be
    killed (`kill_at`: SIGKILL) or run a step that never checks cancel (`busy_at`, for
    `busy` seconds; `import_at`: one that turns the cancel's interrupt into an ImportError)."""
    from ..base.progress import CancelCheck
    from ..meshes.spill import SpillStore

    cancel = CancelCheck(should_cancel, "selftest")
    steps = int(arguments.get("steps", 10))
    with SpillStore():  # a temporary folder for the task's duration, as the real tasks have
        _selftest_steps(arguments, steps, progress, cancel)
    output = Path(arguments["output"])
    output.write_text("ok")
    return str(output)


def _busy(seconds: float) -> None:
    """Spin for `seconds` without a cancel check."""
    import time

    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


def _selftest_steps(arguments: dict, steps: int, progress, cancel) -> None:
    import time

    from ..base.errors import ShapeGenError

    for i in range(steps):
        if arguments.get("busy_at") == i:  # a long step that never checks cancel
            _busy(float(arguments.get("busy", 30.0)))
        if arguments.get("import_at") == i:  # ... whose library turns the cancel's interrupt into its own
            try:                             # error, as an import interrupted midway does
                _busy(float(arguments.get("busy", 30.0)))
            except KeyboardInterrupt:
                raise ImportError("numpy.core.multiarray failed to import") from None
        cancel()
        progress((i + 1) / steps, f"step {i + 1} of {steps}")
        time.sleep(float(arguments.get("sleep", 0.01)))
        if arguments.get("fail_at") == i:
            raise ShapeGenError(f"selftest failed on purpose at step {i}")
        if arguments.get("crash_at") == i:
            import os

            os._exit(3)  # a hard crash: no message, non-zero exit
        if arguments.get("kill_at") == i:  # killed as the out-of-memory killer would
            import os
            import signal

            os.kill(os.getpid(), signal.SIGKILL)


TASKS = {"prepare": task_prepare, "fit": task_fit, "correspond": task_correspond, "selftest": task_selftest}


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] not in TASKS:
        _emit(event="failed", error=f"usage: worker.py TASK JSON (tasks: {', '.join(TASKS)})")
        return 2
    from ..base.errors import Cancelled, ShapeGenError

    task, arguments = TASKS[argv[0]], json.loads(argv[1])
    cancel = _CancelOnStdin()
    try:
        try:
            output = task(arguments, lambda f, stage: _emit(event="progress", fraction=f, stage=stage),
                          cancel.event)
        finally:
            cancel.task_ended()
    except (Cancelled, KeyboardInterrupt):
        _emit(event="cancelled")
        return 0
    except Exception as exc:
        if cancel.event.is_set():  # the cancel's interrupt broke a step midway (e.g. an import): not a fault
            _emit(event="cancelled")
            return 0
        if isinstance(exc, ShapeGenError):
            _emit(event="failed", error=str(exc))
            return 1
        traceback.print_exc()  # an unexpected bug: report it with its type, keep the trace on stderr
        _emit(event="failed", error=f"{type(exc).__name__}: {exc}")
        return 1
    _emit(event="done", output=output)
    return 0
