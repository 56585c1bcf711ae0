"""Model section: Fit in the background (collection → worker process → model packed into
the .blend), Load Model, Export Model.

Flow of Fit:
1. `SHAPEGEN_OT_fit` (main thread) asks core/app/stages.py which stages run
   (fitting.plan_fit: is Prepare's result for the objects current, was the scene's model
   corresponded on exactly those with the same settings?) and reads what the worker starts
   from (fitting.fit_inputs): the collection's mesh objects' triangles
   (convert.object_triangles, world coordinates), the prepared shapes, or that model's
   correspondence; a helper thread writes them
   into a temporary folder, then the core's "fit" task starts in a worker process
   (core/app/worker.py, which never imports bpy) through `jobs.MANAGER`. Nothing in the scene
   changes yet.
2. The job runtime (jobs.poll_job, from the UI timer or a script's loop) mirrors the
   progress into `scene.shapegen`.
3. When the job ends, `fitting.finish` runs on the main thread: on success the model file is
   loaded, packed into the .blend and becomes the scene's model (`fitting.install_model`); on
   failure or cancel only the job's state and message change, so the scene and any
   earlier model stay as they were, and the message says why.
"""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.props import StringProperty

from ...core.base.errors import ShapeGenError
from ...core.app.jobs import BackgroundJob
from .. import fitting, store
from ..exclusion import training_objects
from ..jobs import MANAGER, JobOperator, no_job_running

__all__ = ["CLASSES"]


class SHAPEGEN_OT_fit(JobOperator, bpy.types.Operator):
    """Fit a generative shape model to the chosen collection in a background process
    (Blender stays usable; progress and Cancel in the Model panel)"""

    bl_idname = "shapegen.fit"
    bl_label = "Fit"
    bl_options = {"REGISTER"}
    job_name = "fit"

    def execute(self, context):
        scene = context.scene
        settings = scene.shapegen
        collection = self.chosen_collection(context)
        if collection is None:
            return {"CANCELLED"}
        objects = [o for o in training_objects(collection) if o.type == "MESH"]
        if len(objects) < 2:
            self.report({"ERROR"}, f"Collection '{collection.name}' has {len(objects)} mesh object(s); "
                        "a shape model needs at least 2")
            return {"CANCELLED"}
        checked = self.job_options(settings.fit_options(), fitting.check_fit_settings)
        if checked is None:
            return {"CANCELLED"}
        options, run = checked
        evaluated = not settings.prepare.use_base_mesh
        try:
            plan = fitting.plan_fit(scene, collection, objects, options, evaluated)
        except ShapeGenError as exc:  # the scene's model could not be read
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        print(f"ShapeGen: fit '{collection.name}': {plan.reason}")

        def start(folder: Path) -> None:
            inputs, setup = fitting.fit_inputs(plan, settings, objects, evaluated, folder)
            job = BackgroundJob("fit", {**inputs, **run, "settings": options, "output": str(folder / "model.npz")})
            MANAGER.start(job, fitting.finish, label=f"fit '{collection.name}'", folder=folder,
                          payload={"scene": scene.name, "name": collection.name, "reused": plan.reused_labels},
                          prepare=fitting.load_result, setup=setup)

        return self.run_job(context, start, started=f"Fitting {len(objects)} shapes of '{collection.name}' in the "
                                                    f"background: {plan.reason}")


class SHAPEGEN_OT_load_model(bpy.types.Operator):
    """Load a fitted model file (.npz from `shapegen fit` or Export Model) into this scene;
    it is packed into the .blend"""

    bl_idname = "shapegen.load_model"
    bl_label = "Load Model"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(name="File", subtype="FILE_PATH")
    filter_glob: StringProperty(default="*.npz", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return no_job_running(cls)

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        path = Path(bpy.path.abspath(self.filepath))
        if not path.is_file():
            self.report({"ERROR"}, f"{path}: no such model file")
            return {"CANCELLED"}
        try:
            model = fitting.install_model(context.scene, path, path.stem)
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"Loaded {model.model_type} model '{path.stem}': {len(model.names)} shapes, "
                    f"{model.latent_dim} latent dimensions")
        return {"FINISHED"}


class SHAPEGEN_OT_export_model(store.NeedsModel, bpy.types.Operator):
    """Write the scene's packed model to a .npz file (for the `shapegen` command line)"""

    bl_idname = "shapegen.export_model"
    bl_label = "Export Model"
    bl_options = {"REGISTER"}

    filepath: StringProperty(name="File", subtype="FILE_PATH")
    filter_glob: StringProperty(default="*.npz", options={"HIDDEN"})

    def invoke(self, context, event):
        if not self.filepath:
            self.filepath = f"{bpy.path.clean_name(store.model_name(context.scene))}.npz"
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        if not self.filepath:
            self.report({"ERROR"}, "No file path given")
            return {"CANCELLED"}
        path = Path(bpy.path.abspath(self.filepath))
        try:
            path.write_bytes(store.model_bytes(context.scene.shapegen.model_text))
        except (OSError, ShapeGenError) as exc:
            self.report({"ERROR"}, f"{path}: {exc}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Wrote {path}")
        return {"FINISHED"}


CLASSES = (SHAPEGEN_OT_fit, SHAPEGEN_OT_load_model, SHAPEGEN_OT_export_model)
