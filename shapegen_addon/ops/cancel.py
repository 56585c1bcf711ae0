"""Cancel: stops whichever background job runs (Prepare, Find Correspondences or Fit).

Its id keeps the name it had when Fit was the only job (`shapegen.fit_cancel`), so
scripts and keymaps that call it keep working.
"""

from __future__ import annotations

import bpy

from ..jobs import MANAGER, job_scene

__all__ = ["CLASSES"]


class SHAPEGEN_OT_fit_cancel(bpy.types.Operator):
    """Stop the running background job (Prepare, Find Correspondences or Fit); the scene and
    any earlier model stay as they are"""

    bl_idname = "shapegen.fit_cancel"
    bl_label = "Cancel"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        if not MANAGER.running:
            cls.poll_message_set("No background job is running")
            return False
        return True

    def execute(self, context):
        MANAGER.cancel()
        scene = job_scene()
        if scene is not None:
            scene.shapegen.job_stage = "cancelling"
        self.report({"INFO"}, f"Cancelling {MANAGER.label}")
        return {"FINISHED"}


CLASSES = (SHAPEGEN_OT_fit_cancel,)
