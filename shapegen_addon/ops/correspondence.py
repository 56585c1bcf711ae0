"""Correspondence section: "Find Correspondences" on a prepared collection (thesis §4.2).

The prepared shapes (from Prepare) are written to a temporary `.npz` and corresponded in
a background worker (core task "correspond", the same job runtime as Prepare and Fit: one
job at a time, progress in the panel, Cancel). The result is applied on the main thread
(prepared.apply_correspondence): every prepared object gets its corresponded landmarks
and a child marker object whose colours encode the landmark index the same way on every
shape, so the same colour should sit on the same part of every shape.
"""

from __future__ import annotations

from pathlib import Path

import bpy

from ...core.app.jobs import BackgroundJob, JobStatus
from ..exclusion import without_excluded
from ..jobs import MANAGER, JobOperator, job_settings, report_outcome
from ..prepared import (apply_correspondence, prepared_collection_for, prepared_objects, recorded_prepare_settings,
                        to_prepared_collection)

__all__ = ["CLASSES"]


def _load(status: JobStatus):
    if status.state != "done":
        return None
    from ...core.correspond import Correspondence

    return Correspondence.load(status.output)


def _finish(status: JobStatus, result) -> None:
    settings = job_settings(status, f"finding correspondences in '{MANAGER.payload.get('collection')}'")
    if settings is None:
        return
    collection = bpy.data.collections.get(MANAGER.payload.get("collection", ""))
    if status.state != "done" or isinstance(result, Exception) or collection is None:
        reason = (str(result) if isinstance(result, Exception) else status.error
                  or ("the prepared collection is gone" if collection is None else status.state))
        report_outcome(settings, "CANCELLED" if status.state == "cancelled" else "FAILED",
                       f"Find Correspondences {status.state}: {reason}; nothing was changed")
        return
    apply_correspondence(collection, result)
    outliers = [n for n, o in zip(result.names, result.outliers) if o]
    report_outcome(settings, "DONE", f"Corresponded {len(result.names)} shapes x {result.n_landmarks} landmarks "
                   f"(template {result.template_name}); "
                   + (f"outliers: {', '.join(outliers)}" if outliers else "no outliers")
                   + (f"; {result.pose_summary()} (each shape's line says how)" if result.pose_summary() else ""),
                   "corresponded")


def _check_correspondence_settings(options: dict) -> None:
    from ...core.correspond import CorrespondenceSettings

    CorrespondenceSettings.from_dict(options)


class SHAPEGEN_OT_find_correspondences(JobOperator, bpy.types.Operator):
    """Place every prepared shape's landmarks on the same parts of every shape, in the background
    (optional: Fit does it too); coloured markers show the result"""

    bl_idname = "shapegen.find_correspondences"
    bl_label = "Find Correspondences"
    bl_options = {"REGISTER"}
    job_name = "correspondence"

    @classmethod
    def poll(cls, context):
        if not super().poll(context):
            return False
        if prepared_collection_for(context.scene.shapegen.source_collection) is None:
            cls.poll_message_set("Prepare the chosen collection first (Data panel)")
            return False
        return True

    def execute(self, context):
        chosen = self.chosen_collection(context)
        if chosen is None:
            return {"CANCELLED"}
        collection = prepared_collection_for(chosen)
        if collection is None:
            self.report({"ERROR"}, f"'{chosen.name}' has no prepared collection: Prepare it first (Data panel)")
            return {"CANCELLED"}
        objects = without_excluded(collection, prepared_objects(collection))
        if len(objects) < 2:
            self.report({"ERROR"}, f"'{collection.name}' has {len(objects)} prepared shape(s); need at least 2")
            return {"CANCELLED"}
        checked = self.job_options(context.scene.shapegen.correspondence_options(), _check_correspondence_settings)
        if checked is None:
            return {"CANCELLED"}
        options, run = checked

        def start(folder: Path) -> None:
            prepared = to_prepared_collection(objects)
            prepared.settings = recorded_prepare_settings(collection)  # the correspondence records them
            prepared.save(folder / "prepared.npz")
            job = BackgroundJob("correspond", {"prepared": str(folder / "prepared.npz"), "settings": options, **run,
                                               "output": str(folder / "correspondence.npz")})
            MANAGER.start(job, _finish, label=f"correspond '{collection.name}'", folder=folder,
                          payload={"scene": context.scene.name, "collection": collection.name}, prepare=_load)

        return self.run_job(context, start,
                            started=f"Finding correspondences across {len(objects)} shapes in the background")


CLASSES = (SHAPEGEN_OT_find_correspondences,)
