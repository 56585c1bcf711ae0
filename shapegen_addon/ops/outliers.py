"""Outliers section: leave the shapes the correspondence flags out of training and fit
again, or take them back (exclusion.py records the list on the user's collection; the
objects themselves are never changed or hidden)."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty

from ..exclusion import exclude, excluded_names, include_all, outliers, training_collection
from ..jobs import JobOperator, no_job_running

__all__ = ["CLASSES"]


class SHAPEGEN_OT_exclude_outliers(JobOperator, bpy.types.Operator):
    """Leave the outliers listed in the Correspondence panel out of training and fit again
    (recorded on the collection; your objects are not changed)"""

    bl_idname = "shapegen.exclude_outliers"
    bl_label = "Exclude Outliers and Refit"
    bl_options = {"REGISTER", "UNDO"}
    job_name = "fit"

    refit: BoolProperty(name="Refit", default=True, description="Fit the collection again without them")

    def execute(self, context):
        chosen = self.chosen_collection(context)
        collection = training_collection(chosen)
        if collection is None:
            if chosen is not None:
                self.report({"ERROR"}, f"The source collection of '{chosen.name}' is gone")
            return {"CANCELLED"}
        added = exclude(collection, [name for name, _ in outliers(context.scene, collection)])
        if not added:
            self.report({"WARNING"}, f"'{collection.name}' has no outliers to exclude")
            return {"CANCELLED"}
        message = (f"Excluded {', '.join(added)} from '{collection.name}' (Include Excluded takes "
                   f"{'it' if len(added) == 1 else 'them'} back)")
        if not self.refit:
            self.report({"INFO"}, f"{message}; Prepare or Fit again to use the rest")
            return {"FINISHED"}
        self.report({"INFO"}, f"{message}; fitting again")
        bpy.ops.shapegen.fit(collection_name=collection.name, extra_settings=self.extra_settings, wait=self.wait)
        return {"FINISHED"}


class SHAPEGEN_OT_include_excluded(bpy.types.Operator):
    """Take the objects left out of training back in (Prepare or Fit again to use them)"""

    bl_idname = "shapegen.include_excluded"
    bl_label = "Include Excluded"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not no_job_running(cls):
            return False
        if not excluded_names(training_collection(context.scene.shapegen.source_collection)):
            cls.poll_message_set("The chosen collection leaves no objects out")
            return False
        return True

    def execute(self, context):
        collection = training_collection(context.scene.shapegen.source_collection)
        names = include_all(collection)
        self.report({"INFO"}, f"Included {', '.join(names)} in '{collection.name}' again; Prepare or Fit again "
                              "to use them")
        return {"FINISHED"}


CLASSES = (SHAPEGEN_OT_exclude_outliers, SHAPEGEN_OT_include_excluded)
