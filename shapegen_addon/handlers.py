"""What happens when a .blend is closed or opened (bpy.app.handlers load_pre / load_post).

Closing: a running job belongs to the file being closed, so it is stopped. Opening: the
process caches (decoded models, latent meshers) belong to the old file and are dropped,
every scene's packed model is decoded again, pins are re-applied only once they move
(depsgraph_update_post, pins.py), a job state left at RUNNING when the file
was saved (its worker is gone) is reset, and panel settings saved before they were grouped
by section are moved into their groups (compat.regroup_flat_settings).
"""

from __future__ import annotations

import bpy
from bpy.app.handlers import persistent

from ..core.base.errors import ShapeGenError
from . import latent, pins, store
from .compat import regroup_flat_settings
from .jobs import MANAGER

__all__ = ["register_handlers", "unregister_handlers"]


@persistent
def _load_pre(*_args):
    if MANAGER.running:  # the job belongs to the file being closed
        print(f"ShapeGen: a new file is loading; stopping the running job ({MANAGER.label})")
        MANAGER.kill("a new file was loaded")


@persistent
def _load_post(*_args):
    """Restore every scene's model after a file is opened (and reset stale job states)."""
    store.forget_cache()
    latent.forget_cache()
    for scene in bpy.data.scenes:
        settings = scene.shapegen
        moved = regroup_flat_settings(settings)
        if moved:
            print(f"ShapeGen: scene '{scene.name}': panel settings saved by an earlier version moved into their "
                  f"sections: {', '.join(moved)}")
        if settings.job_state == "RUNNING":
            settings.job_state = "IDLE"
            settings.job_stage = ""
        if settings.model_text is None:
            continue
        try:
            store.get_model(scene)
        except ShapeGenError as exc:
            settings.job_message = f"Could not restore the model: {exc}"
            print(f"ShapeGen: scene '{scene.name}': could not restore the model: {exc}")


def register_handlers() -> None:
    pins.register_pin_handler()
    if _load_post not in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.append(_load_post)
    if _load_pre not in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.append(_load_pre)


def unregister_handlers() -> None:
    pins.unregister_pin_handler()
    for handlers, function in ((bpy.app.handlers.load_post, _load_post), (bpy.app.handlers.load_pre, _load_pre)):
        while function in handlers:
            handlers.remove(function)
    store.forget_cache()
