"""The job runtime in Blender, shared by Prepare, Find Correspondences and Fit.

* `poll_job()` polls `MANAGER` once (never blocks on the worker) and mirrors the progress
  into the job's scene (`scene.shapegen.job_fraction` / `job_stage`). With a window a
  `bpy.app.timers` function calls it every 0.1 s and redraws the sidebar; headless
  (timers never fire) the caller loops over `poll_job()` itself, or runs the operator with
  `wait=True`.
* `run_worker_job` is the shared tail of the three operators: start the job, then wait
  for it or leave it to the timer.
* `report_outcome` is how every job's end reaches the user: the scene's job state and
  message, a console line and, with a window, a popup.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import bpy

from ...core.base.errors import ShapeGenError
from ...core.app.jobs import JobStatus
from .manager import MANAGER

__all__ = ["poll_job", "job_scene", "job_settings", "report_outcome", "run_worker_job", "no_job_running",
           "start_polling", "unregister_timer", "POLL_INTERVAL"]

POLL_INTERVAL = 0.1


def job_scene() -> bpy.types.Scene | None:
    """The scene the running (or last) job of `MANAGER` belongs to, if it still exists."""
    return bpy.data.scenes.get(MANAGER.payload.get("scene", ""))


def job_settings(status: JobStatus, job: str):
    """The ShapeGen settings of the ended job's scene, or None (and a console line naming
    `job`) when the user deleted that scene meanwhile."""
    scene = job_scene()
    if scene is None:
        print(f"ShapeGen: {job} ended ({status.state}) but its scene is gone")
        return None
    return scene.shapegen


def poll_job() -> JobStatus | None:
    """Poll the running job once (main thread; never blocks on the worker). Mirrors the
    progress into the scene; the job's own callback applies the result when it has ended.
    Returns the status (None when no job ever ran in this process)."""
    if not MANAGER.running:
        return MANAGER.last_status
    scene = job_scene()
    status = MANAGER.poll()
    if status is not None and not status.finished and scene is not None:
        settings = scene.shapegen
        settings.job_fraction = min(max(status.fraction, 0.0), 1.0)
        settings.job_stage = status.stage
    return status


def report_outcome(settings, state: str, message: str, stage: str = "") -> None:
    """The end of a job, told the same way for every job: `state` ("DONE", "FAILED" or
    "CANCELLED") and `message` into the scene's settings (on DONE also a full progress bar
    and the final `stage`), a console line, and a popup when Blender has a window."""
    settings.job_state = state
    if state == "DONE":
        settings.job_fraction = 1.0
        settings.job_stage = stage
    settings.job_message = message
    print(f"ShapeGen: {message}")
    _notify(message, {"DONE": "INFO", "FAILED": "ERROR"}.get(state, "CANCEL"))


def _notify(message: str, icon: str) -> None:
    """A popup in the UI (a timer has no operator to report through)."""
    if bpy.app.background:
        return
    try:
        wm = bpy.context.window_manager
        wm.popup_menu(lambda menu, _ctx: menu.layout.label(text=message), title="ShapeGen", icon=icon)
    except Exception as exc:  # no window to show it in: the panel still shows job_message
        print(f"ShapeGen: could not show a popup ({exc})")


def _redraw() -> None:
    wm = bpy.context.window_manager
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _timer() -> float | None:
    try:
        poll_job()
    except Exception as exc:  # never let the timer die silently with a job still running
        print(f"ShapeGen: polling the job failed: {exc}")
    _redraw()
    return POLL_INTERVAL if MANAGER.running else None


def start_polling() -> None:
    """Poll `MANAGER` from a timer while a job runs (UI only: timers never fire in
    background mode, where callers loop over `poll_job()` themselves)."""
    if not bpy.app.background and not bpy.app.timers.is_registered(_timer):
        bpy.app.timers.register(_timer, first_interval=POLL_INTERVAL)


def unregister_timer() -> None:
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)


def no_job_running(operator_class) -> bool:
    """Operator poll part: one background job at a time; says which one runs and how far
    it is."""
    if not MANAGER.running:
        return True
    status = MANAGER.last_status
    percent = int(100 * status.fraction) if status else 0
    operator_class.poll_message_set(f"A job is already running ({MANAGER.label}, {percent} %): "
                                    "wait for it or cancel it")
    return False


def run_worker_job(operator, settings, prefix: str, start, *, wait: bool, started: str) -> set[str]:
    """The shared tail of the operators that run core work in a worker: `start(folder)`
    writes the job's inputs into a fresh temporary folder and starts it on `MANAGER`; if
    that fails the folder is removed and the error reported. Then the job state is
    mirrored into `settings`, and the operator either blocks until the job has ended
    (`wait`: scripts and background mode, where timers never fire) or leaves it to the UI
    timer."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        start(folder)
    except (ShapeGenError, OSError) as exc:
        shutil.rmtree(folder, ignore_errors=True)
        operator.report({"ERROR"}, str(exc))
        return {"CANCELLED"}
    settings.job_state = "RUNNING"
    settings.job_fraction = 0.0
    settings.job_stage = "starting"
    settings.job_message = ""
    if wait:
        status = MANAGER.last_status
        while MANAGER.running:
            status = poll_job()
            time.sleep(0.05)
        if status is None or status.state != "done" or settings.job_state != "DONE":
            operator.report({"ERROR"}, settings.job_message)
            return {"CANCELLED"}
        operator.report({"INFO"}, settings.job_message)
        return {"FINISHED"}
    start_polling()
    operator.report({"INFO"}, started)
    return {"FINISHED"}
