"""Correspondence section: "Find Correspondences" on a prepared collection (thesis §4.2).

The prepared shapes (from Prepare) are written to a temporary `.npz` and corresponded in
a background worker (core task "correspond", the same job manager as Fit: one job at a
time, progress in the panel, Cancel). The result is applied on the main thread: every
prepared object gets its corresponded landmarks (`shapegen_correspondence`, object-local
= normalised frame) and a child marker object whose colours encode the LANDMARK INDEX the
same way on every shape (colour of landmark i = position of template landmark i in the
template's bounding box, as RGB), so a user can judge correspondence by eye (thesis
Fig. 4.2–4.4): the same colour should sit on the same part of every shape.
"""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import BoolProperty, StringProperty

from ..core.jobs import BackgroundJob, JobStatus
from .fitting import job_settings, no_job_running, parse_extra_settings, run_worker_job
from .jobs import MANAGER
from .prepared import apply_correspondence, prepared_collection_for, prepared_objects, to_prepared_collection

__all__ = ["CLASSES"]


# ------------------------------------------------------------------------------ job
def _load(status: JobStatus):
    if status.state != "done":
        return None
    from ..core.correspond import Correspondence

    return Correspondence.load(status.output)


def _finish(status: JobStatus, result) -> None:
    settings = job_settings(status, f"finding correspondences in '{MANAGER.payload.get('collection')}'")
    if settings is None:
        return
    collection = bpy.data.collections.get(MANAGER.payload.get("collection", ""))
    if status.state != "done" or isinstance(result, Exception) or collection is None:
        settings.job_state = "CANCELLED" if status.state == "cancelled" else "FAILED"
        reason = (str(result) if isinstance(result, Exception) else status.error
                  or ("the prepared collection is gone" if collection is None else status.state))
        settings.job_message = f"Find Correspondences {status.state}: {reason}; nothing was changed"
        print(f"ShapeGen: {settings.job_message}")
        return
    apply_correspondence(collection, result)
    outliers = [n for n, o in zip(result.names, result.outliers) if o]
    settings.job_state = "DONE"
    settings.job_fraction = 1.0
    settings.job_stage = "corresponded"
    settings.job_message = (f"Corresponded {len(result.names)} shapes x {result.n_landmarks} landmarks "
                            f"(template {result.template_name}); "
                            + (f"outliers: {', '.join(outliers)}" if outliers else "no outliers"))
    print(f"ShapeGen: {settings.job_message}")


class SHAPEGEN_OT_find_correspondences(bpy.types.Operator):
    """Find dense corresponding landmarks across the prepared collection (non-rigid ICP, in the background)"""

    bl_idname = "shapegen.find_correspondences"
    bl_label = "Find Correspondences"
    bl_options = {"REGISTER"}

    wait: BoolProperty(name="Wait", default=False, options={"SKIP_SAVE"},
                       description="Block until the job ends (scripts and background mode)")
    extra_settings: StringProperty(
        name="Extra Settings", default="",
        description='More CorrespondenceSettings fields as JSON, e.g. {"groupwise_rounds": 0}',
    )

    @classmethod
    def poll(cls, context):
        if not no_job_running(cls):
            return False
        if prepared_collection_for(context.scene.shapegen.source_collection) is None:
            cls.poll_message_set("Prepare the chosen collection first (Data panel)")
            return False
        return True

    def execute(self, context):
        collection = prepared_collection_for(context.scene.shapegen.source_collection)
        objects = prepared_objects(collection)
        if len(objects) < 2:
            self.report({"ERROR"}, f"'{collection.name}' has {len(objects)} prepared shape(s); need at least 2")
            return {"CANCELLED"}
        settings = context.scene.shapegen
        options = {"alpha_end": settings.stiffness, "alpha_start": max(100.0, settings.stiffness)}
        try:
            options.update(parse_extra_settings(self.extra_settings))
            from ..core.correspond import CorrespondenceSettings

            CorrespondenceSettings(**options)  # a bad setting is reported before a worker starts
        except (TypeError, ValueError) as exc:
            self.report({"ERROR"}, f"Invalid correspondence settings: {exc}")
            return {"CANCELLED"}
        def start(folder: Path) -> None:
            to_prepared_collection(objects).save(folder / "prepared.npz")
            job = BackgroundJob("correspond", {"prepared": str(folder / "prepared.npz"), "settings": options,
                                               "output": str(folder / "correspondence.npz")})
            MANAGER.start(job, _finish, label=f"correspond '{collection.name}'", folder=folder,
                          payload={"scene": context.scene.name, "collection": collection.name}, prepare=_load)

        return run_worker_job(self, settings, "shapegen-correspond-", start, wait=self.wait,
                              started=f"Finding correspondences across {len(objects)} shapes in the background")


CLASSES = (SHAPEGEN_OT_find_correspondences,)
