"""Generate: sample new shapes, interpolate between two shapes, PPCA modes as shape keys.

Every generated object is an ordinary mesh object tagged with its latent vector, model
and template (latent.tag_object; a sample also with its seed), so later operators
(Interpolate, Latent Map) can find its latent vector again. Vertex positions come from the
core (`GenerativeShapeModel.sample`, `mesh_from_landmarks`, `LatentMesher`), the mesh
around them is a copy of the template's own (template_mesh.TemplateMeshes; a plain
triangle mesh, said in the report, when the template's object is gone); nothing here is
an algorithm. Samples pass the core's quality gate (core/generate/sampling.py: a failing mesh is
re-meshed on the next-nearest template, then stiffer, or redrawn with a new seed, within
the run's pooled draw budget); the report says how many were redrawn and why, and each
sample records the meshes refused on its way (keys.REJECTED_KEY) and the stiffness it was
meshed with when stiffer than the model's (keys.STIFFNESS_KEY). A sample still failing
when the budget is spent is not added (a broken mesh in the scene passes for a good one):
the report says how many passed and failed and the commonest reasons.
"""

from __future__ import annotations

import bpy
import numpy as np
from bpy.props import EnumProperty, IntProperty, StringProperty

from ...core.base.errors import ShapeGenError
from ...core.generate.quality import QualitySettings
from ...core.generate.sampling import draw_budget, gate_summary, gated_samples, shortfall
from ...core.models.ppca import MODE_RANGE
from .. import store
from ..keys import INTERPOLATION_KEY, REJECTED_KEY, STIFFNESS_KEY
from ..latent import object_latent, tag_object
from ..placement import grid_offsets, place, place_one, vertex_box
from ..preview import ensure_collection
from ..template_mesh import TemplateMeshes
from ..ui.properties import INTERPOLATION_ITEMS

__all__ = ["CLASSES", "SAMPLES_COLLECTION", "INTERPOLATION_COLLECTION", "MODES_COLLECTION"]

SAMPLES_COLLECTION = "ShapeGen Samples"
INTERPOLATION_COLLECTION = "ShapeGen Interpolation"
MODES_COLLECTION = "ShapeGen Modes"


def shape_size(model) -> float:
    """Largest bounding-box side over the training meshes (grid spacing unit)."""
    return max(float(np.ptp(m.vertices, axis=0).max()) for m in model.meshes)


class SHAPEGEN_OT_sample(store.NeedsModel, bpy.types.Operator):
    """Sample new shapes from the model into the "ShapeGen Samples" collection, on a grid
    beside the scene's objects"""

    bl_idname = "shapegen.sample"
    bl_label = "Sample"
    bl_options = {"REGISTER", "UNDO"}

    count: IntProperty(name="Count", default=0, min=0, max=1000,
                       description="Shapes to sample (0: the panel's Count)")
    seed: IntProperty(name="Seed", default=-1, min=-1,
                      description="First seed; shape i uses seed + i (-1: the panel's Seed)")

    def execute(self, context):
        scene = context.scene
        settings = scene.shapegen
        try:
            model = store.require_model(scene)
            count = self.count or settings.generate.sample_count
            first_seed = settings.prepare.seed if self.seed < 0 else self.seed
            # everything that can fail runs before the scene is touched; sample i is drawn
            # with seed first_seed + i (redraws: core.generate.sampling.redraw_seed)
            quality = QualitySettings()
            results = gated_samples(model, count, first_seed, template=settings.generate.sample_template,
                                    settings=quality)
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        name = store.model_name(scene)
        passed = [s for s in results if s.quality.ok]
        failure = shortfall(results, draw_budget(count, quality))
        if not passed:
            self.report({"ERROR"}, f"No shape sampled from '{name}': {failure}; none added. {gate_summary(results)}.")
            return {"CANCELLED"}
        spacing = settings.prepare.preview_spacing * shape_size(model)
        locations = place(scene, [vertex_box(s.mesh.vertices) for s in passed], grid_offsets(len(passed), spacing))
        collection = ensure_collection(scene, SAMPLES_COLLECTION)
        meshes = TemplateMeshes(scene, model)
        for sample, location in zip(passed, locations):
            obj = meshes.new_object(f"{name} sample {first_seed + sample.index}", sample.template_index,
                                    sample.mesh.vertices)
            obj.location = location
            tag_object(obj, scene, sample.latent, model.names[sample.template_index], seed=sample.seed)
            if sample.rejected:
                obj[REJECTED_KEY] = [r.describe() for r in sample.rejected]
            if sample.stiffer:
                obj[STIFFNESS_KEY] = float(sample.stiffness)
            collection.objects.link(obj)
        added = f"Sampled {len(passed)} shape(s) from '{name}' into '{collection.name}' " \
                f"(seeds {first_seed}-{first_seed + count - 1})"
        if failure:
            self.report({"WARNING"}, f"{added}; {failure}; the failing ones were not added. "
                        f"{gate_summary(results)}.{meshes.note}")
        else:
            self.report({"INFO"}, f"{added}; {gate_summary(results)}.{meshes.note}")
        return {"FINISHED"}


class SHAPEGEN_OT_interpolate(store.NeedsModel, bpy.types.Operator):
    """In-between shapes of two objects (training shapes or samples): new objects in a row, or
    one object with a shape-key animation; all on one mesh"""

    bl_idname = "shapegen.interpolate"
    bl_label = "Interpolate"
    bl_options = {"REGISTER", "UNDO"}

    object_a: StringProperty(name="From", default="", description="First object (empty: the panel's From)")
    object_b: StringProperty(name="To", default="", description="Second object (empty: the panel's To)")
    steps: IntProperty(name="Steps", default=0, min=0, max=500, description="In-between shapes (0: the panel's)")
    mode: EnumProperty(name="Output", items=[("PANEL", "Panel", "The panel's choice")] + INTERPOLATION_ITEMS,
                       default="PANEL")

    def _objects(self, context):
        settings = context.scene.shapegen
        found = []
        for name, pointer, label in ((self.object_a, settings.generate.interpolate_a, "From"),
                                     (self.object_b, settings.generate.interpolate_b, "To")):
            obj = bpy.data.objects.get(name) if name else pointer
            if obj is None:
                raise ShapeGenError(f"No object named '{name}'" if name else f"Choose the '{label}' object first")
            found.append(obj)
        if found[0] == found[1]:
            raise ShapeGenError(f"'From' and 'To' are the same object ('{found[0].name}')")
        return found

    def execute(self, context):
        scene = context.scene
        settings = scene.shapegen
        steps = self.steps or settings.generate.interpolate_steps
        mode = settings.generate.interpolate_mode if self.mode == "PANEL" else self.mode
        try:
            model = store.require_model(scene)
            first, second = self._objects(context)
            z_a, z_b = object_latent(model, scene, first), object_latent(model, scene, second)
            index = model.path_template(z_a, z_b, settings.generate.sample_template)  # one mesh along the path
            mesher = model.latent_mesher(index, dtype=np.float64)
            ts, path = model.latent_path(z_a, z_b, steps + 2)  # the two objects and `steps` between
            shapes = [mesher.vertices(z) for z in path]
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        meshes = TemplateMeshes(scene, model)
        collection = ensure_collection(scene, INTERPOLATION_COLLECTION)
        base = f"{first.name} to {second.name}"
        spacing = settings.prepare.preview_spacing * shape_size(model)
        if mode == "OBJECTS":
            locations = place(scene, [vertex_box(shape) for shape in shapes[1:-1]],
                              grid_offsets(steps, spacing, columns=steps))
            for k, location in enumerate(locations, start=1):
                obj = meshes.new_object(f"{base} {k}", index, shapes[k])
                obj.location = location
                tag_object(obj, scene, path[k], model.names[index])
                obj[INTERPOLATION_KEY] = float(ts[k])
                collection.objects.link(obj)
            self.report({"INFO"}, f"{steps} in-between shape(s) of '{first.name}' and '{second.name}' in "
                        f"'{collection.name}'.{meshes.note}")
            return {"FINISHED"}

        obj = meshes.new_object(f"{base} morph", index, shapes[0])
        obj.location = place_one(scene, vertex_box(np.concatenate(shapes)))
        collection.objects.link(obj)
        tag_object(obj, scene, z_a, model.names[index])
        obj.shape_key_add(name="Basis", from_mix=False)
        frames = settings.generate.interpolate_frames
        start = scene.frame_start
        for k in range(1, len(shapes)):
            key = obj.shape_key_add(name=f"t={ts[k]:.3f}", from_mix=False)
            key.data.foreach_set("co", meshes.positions(index, shapes[k]))
            # crossfade: key k rises from 0 at step k-1 to 1 at step k and falls to 0 at step k+1
            for frame, value in ((start + (k - 1) * frames, 0.0), (start + k * frames, 1.0),
                                 (start + (k + 1) * frames, 0.0)):
                if value == 0.0 and k == len(shapes) - 1 and frame > start + k * frames:
                    continue  # the last shape holds
                key.value = value
                key.keyframe_insert("value", frame=frame)
        for fcurve in _fcurves(obj.data.shape_keys):
            for point in fcurve.keyframe_points:
                point.interpolation = "LINEAR"
        for key in obj.data.shape_keys.key_blocks[1:]:
            key.value = 0.0
        scene.frame_end = max(scene.frame_end, start + (len(shapes) - 1) * frames)
        self.report({"INFO"}, f"'{obj.name}': {len(shapes) - 1} shape keys animated over frames "
                    f"{start}-{start + (len(shapes) - 1) * frames}.{meshes.note}")
        return {"FINISHED"}


def _fcurves(id_data) -> list:
    """The F-curves animating `id_data` (slotted actions of Blender 4.4+, or legacy ones)."""
    animation = getattr(id_data, "animation_data", None)
    if animation is None or animation.action is None:
        return []
    action = animation.action
    try:
        from bpy_extras.anim_utils import action_get_channelbag_for_slot

        bag = action_get_channelbag_for_slot(action, animation.action_slot)
        if bag is not None:
            return list(bag.fcurves)
    except (ImportError, AttributeError):
        pass
    return list(getattr(action, "fcurves", []))


class SHAPEGEN_OT_modes_to_shape_keys(store.NeedsModel, bpy.types.Operator):
    """The average shape with one shape key per way the shapes vary (PPCA models; range ±3):
    plain Blender data that keeps working without the extension"""

    bl_idname = "shapegen.modes_to_shape_keys"
    bl_label = "Modes to Shape Keys"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        scene = context.scene
        try:
            model = store.require_model(scene)
            if model.model_type != "ppca":
                raise ShapeGenError(f"Modes as shape keys need a PPCA model (this one is {model.model_type}: "
                                    "its decode is not linear in the latents); use Explore instead")
            index = model.mean_template()
            mesher = model.latent_mesher(index, dtype=np.float64)
            mean = mesher.offset.reshape(-1, 3)
            modes = mesher.basis.reshape(model.latent_dim, -1, 3)  # PPCA: basis row k = W_k on the mesh
        except ShapeGenError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        meshes = TemplateMeshes(scene, model)
        obj = meshes.new_object(f"{store.model_name(scene)} modes", index, mean)
        # room for every mode key at either end of its range
        obj.location = place_one(scene, vertex_box(np.concatenate([mean[None], mean + MODE_RANGE * modes,
                                                                    mean - MODE_RANGE * modes])))
        ensure_collection(scene, MODES_COLLECTION).objects.link(obj)
        tag_object(obj, scene, np.zeros(model.latent_dim), model.names[index])
        obj.shape_key_add(name="Mean", from_mix=False)
        for k, mode in enumerate(modes):
            key = obj.shape_key_add(name=f"Mode {k + 1}", from_mix=False)
            key.data.foreach_set("co", meshes.positions(index, mean + mode))
            key.slider_min, key.slider_max = -MODE_RANGE, MODE_RANGE
            key.value = 0.0
        self.report({"INFO"}, f"'{obj.name}': {model.latent_dim} mode shape keys (range ±{MODE_RANGE:g})."
                              f"{meshes.note}")
        return {"FINISHED"}


CLASSES = (SHAPEGEN_OT_sample, SHAPEGEN_OT_interpolate, SHAPEGEN_OT_modes_to_shape_keys)
