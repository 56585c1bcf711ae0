"""Explore: one live object driven by a slider per latent dimension, and the latent map.

The live object is a copy of one template training mesh. Each slider change re-meshes it
through the core's `LatentMesher` (vertices = offset + features(z) @ basis, the basis
computed once per model and template) and one bulk write of the position attribute, so a
drag costs a small matrix product and a `foreach_set`, for every model type.

Operators: Explore (create / reset the live object), Randomise, Reset, Snap to Nearest
Training Shape, Bake (the live object becomes an ordinary mesh), Latent Map (an image).
"""

from __future__ import annotations

import contextlib

import bpy
import numpy as np
from bpy.props import IntProperty, StringProperty

from ..core.errors import ShapeGenError
from . import store
from .convert import mesh_data_from_arrays
from .picture import latent_map_pixels

__all__ = ["CLASSES", "on_slider_changed", "update_live", "current_latent", "set_latent", "model_changed",
           "forget_cache", "LIVE_KEY", "LATENT_KEY"]

LIVE_KEY = "shapegen_live"  # object property: model id the live object belongs to
LATENT_KEY = "shapegen_latent"  # object property: latent vector (list of floats)
MODEL_KEY = "shapegen_model"  # object property: model name
MODEL_ID_KEY = "shapegen_model_id"  # object property: model id (store.MODEL_ID_KEY of the Text)
TEMPLATE_KEY = "shapegen_template"  # object property: name of the template training shape
TEMPLATE_INDEX_KEY = "shapegen_template_index"
LIVE_NAME = "ShapeGen Live"
MAP_NAME = "ShapeGen Latent Map"

# (model id, template index) -> LatentMesher; process memory, rebuilt lazily
_MESHERS: dict[tuple[str, int], object] = {}
_SUSPENDED = [0]


def forget_cache() -> None:
    _MESHERS.clear()


@contextlib.contextmanager
def _batch():
    """Set many sliders with one re-mesh at the end (instead of one per slider)."""
    _SUSPENDED[0] += 1
    try:
        yield
    finally:
        _SUSPENDED[0] -= 1


# ------------------------------------------------------------------------------ sliders
def _latent_statistics(model) -> tuple[np.ndarray, np.ndarray]:
    z = model.training_latents()
    centre = z.mean(axis=0)
    scale = z.std(axis=0)
    scale[~(scale > 1e-9)] = 1.0
    return centre, scale


def rebuild_sliders(scene: bpy.types.Scene, model) -> None:
    """One slider per latent dimension of `model`, all at the training mean."""
    settings = scene.shapegen
    centre, scale = _latent_statistics(model)
    with _batch():
        settings.latents.clear()
        for k in range(model.latent_dim):
            item = settings.latents.add()
            item.name = f"z{k + 1}"
            item.centre = float(centre[k])
            item.scale = float(scale[k])
            item.value = 0.0


def current_latent(scene: bpy.types.Scene) -> np.ndarray:
    """z from the sliders: centre + value × scale per dimension."""
    items = scene.shapegen.latents
    return np.array([item.centre + item.value * item.scale for item in items], dtype=np.float64)


def set_latent(scene: bpy.types.Scene, z: np.ndarray) -> None:
    """Move every slider so the sliders express `z`, then re-mesh once."""
    items = scene.shapegen.latents
    z = np.asarray(z, dtype=np.float64).ravel()
    if len(z) != len(items):
        raise ShapeGenError(f"latent vector has {len(z)} values, the sliders {len(items)}")
    with _batch():
        for item, value in zip(items, z):
            item.value = float((value - item.centre) / item.scale)
    update_live(scene)


def on_slider_changed(scene: bpy.types.Scene) -> None:
    """Update callback of every slider (properties.ShapeGenLatent.value)."""
    if _SUSPENDED[0] or not isinstance(scene, bpy.types.Scene):
        return
    try:
        update_live(scene)
    except ShapeGenError as exc:  # an update callback cannot report: keep the reason visible
        scene.shapegen.job_message = str(exc)


# ------------------------------------------------------------------------------ live object
def live_object(scene: bpy.types.Scene) -> bpy.types.Object | None:
    obj = scene.shapegen.live_object
    if obj is None or LIVE_KEY not in obj or obj.type != "MESH":
        return None
    return obj


def _mesher(scene: bpy.types.Scene, model, index: int):
    key = (store.model_id(scene), int(index))
    mesher = _MESHERS.get(key)
    if mesher is None:
        mesher = _MESHERS[key] = model.latent_mesher(int(index))
    return mesher


def write_positions(mesh: bpy.types.Mesh, flat: np.ndarray) -> None:
    """Bulk vertex write through the position attribute (the fast path, ~0.2 ms per 100k)."""
    mesh.attributes["position"].data.foreach_set("vector", np.ascontiguousarray(flat, dtype=np.float32))
    mesh.update()


def update_live(scene: bpy.types.Scene) -> bool:
    """Re-mesh the live object from the sliders. False when there is nothing to update."""
    obj = live_object(scene)
    if obj is None or not len(scene.shapegen.latents):
        return False
    model = store.require_model(scene)
    if obj[LIVE_KEY] != store.model_id(scene):
        raise ShapeGenError(f"'{obj.name}' belongs to another model: press Explore to rebuild it")
    mesher = _mesher(scene, model, int(obj[TEMPLATE_INDEX_KEY]))
    if len(obj.data.vertices) != mesher.n_vertices:
        raise ShapeGenError(f"'{obj.name}' has {len(obj.data.vertices)} vertices, its template "
                            f"'{mesher.template_name}' {mesher.n_vertices}: press Explore to rebuild it")
    z = current_latent(scene)
    write_positions(obj.data, mesher.flat_vertices(z))
    obj[LATENT_KEY] = z.tolist()
    return True


def create_live(scene: bpy.types.Scene, model, template: str = "") -> bpy.types.Object:
    """Create (or rebuild) the live object on the template nearest the mean shape."""
    index = model.shape_index(template) if template else model.mean_template()
    source = model.meshes[index]
    name = store.model_name(scene)
    data = mesh_data_from_arrays(f"{LIVE_NAME} mesh", source.vertices, source.faces)
    obj = live_object(scene)
    if obj is None:
        obj = bpy.data.objects.new(LIVE_NAME, data)
        scene.collection.objects.link(obj)
        scene.shapegen.live_object = obj
    else:
        old = obj.data
        obj.data = data
        if old.users == 0:
            bpy.data.meshes.remove(old)
        if obj.name not in scene.objects:  # deleted from the scene but still referenced
            scene.collection.objects.link(obj)
    obj[LIVE_KEY] = store.model_id(scene)
    obj[MODEL_KEY] = name
    obj[MODEL_ID_KEY] = store.model_id(scene)
    obj[TEMPLATE_KEY] = model.names[index]
    obj[TEMPLATE_INDEX_KEY] = index
    if len(scene.shapegen.latents) != model.latent_dim:
        rebuild_sliders(scene, model)
    update_live(scene)
    return obj


def model_changed(scene: bpy.types.Scene, model) -> None:
    """A new model became the scene's: new sliders; an existing live object follows it."""
    rebuild_sliders(scene, model)
    if live_object(scene) is not None:
        create_live(scene, model)


def tag_object(obj: bpy.types.Object, scene: bpy.types.Scene, z, template: str, seed: int | None = None) -> None:
    """Custom properties that tie a generated object to its model and latent vector."""
    obj[LATENT_KEY] = [float(v) for v in np.ravel(z)]
    obj[MODEL_KEY] = store.model_name(scene)
    obj[MODEL_ID_KEY] = store.model_id(scene)
    obj[TEMPLATE_KEY] = template
    if seed is not None:
        obj["shapegen_seed"] = int(seed)


# ------------------------------------------------------------------------------ operators
class _NeedsLive(store.NeedsModel):
    """Operator mixin: a model and its live object (Explore) must exist."""

    @classmethod
    def poll(cls, context):
        if not super().poll(context):
            return False
        if live_object(context.scene) is None:
            cls.poll_message_set("No live object: press Explore first")
            return False
        return True


def _run(operator, function) -> set[str]:
    try:
        message = function()
    except ShapeGenError as exc:
        operator.report({"ERROR"}, str(exc))
        return {"CANCELLED"}
    if message:
        operator.report({"INFO"}, message)
    return {"FINISHED"}


class SHAPEGEN_OT_explore(store.NeedsModel, bpy.types.Operator):
    """Create the live object (a template mesh driven by the latent sliders), or rebuild it"""

    bl_idname = "shapegen.explore"
    bl_label = "Explore"
    bl_options = {"REGISTER", "UNDO"}

    template: StringProperty(name="Template", default="",
                             description="Training shape to deform (empty: the one nearest the mean shape)")

    def execute(self, context):
        def work():
            model = store.require_model(context.scene)
            obj = create_live(context.scene, model, self.template)
            return f"'{obj.name}': {model.latent_dim} sliders on template '{obj[TEMPLATE_KEY]}'"

        return _run(self, work)


class SHAPEGEN_OT_explore_randomise(_NeedsLive, bpy.types.Operator):
    """Draw a latent vector from the model's latent distribution and show it"""

    bl_idname = "shapegen.explore_randomise"
    bl_label = "Randomise"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            scene = context.scene
            model = store.require_model(scene)
            seed = scene.shapegen.explore_seed
            z = model.model.sample_latents(1, np.random.default_rng(seed))[0]
            set_latent(scene, z)
            scene.shapegen.explore_seed = seed + 1
            return f"Random shape (seed {seed})"

        return _run(self, work)


class SHAPEGEN_OT_explore_reset(_NeedsLive, bpy.types.Operator):
    """Move every slider back to the training mean"""

    bl_idname = "shapegen.explore_reset"
    bl_label = "Reset"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            scene = context.scene
            with _batch():
                for item in scene.shapegen.latents:
                    item.value = 0.0
            update_live(scene)
            return ""

        return _run(self, work)


class SHAPEGEN_OT_explore_snap(_NeedsLive, bpy.types.Operator):
    """Move the sliders to the nearest training shape's latent vector"""

    bl_idname = "shapegen.explore_snap"
    bl_label = "Snap to Nearest Training Shape"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            scene = context.scene
            model = store.require_model(scene)
            items = scene.shapegen.latents
            scale = np.array([item.scale for item in items])
            training = model.training_latents()
            distances = (((training - current_latent(scene)) / scale) ** 2).sum(axis=1)
            index = int(np.argmin(distances))
            set_latent(scene, training[index])
            return f"Snapped to '{model.names[index]}'"

        return _run(self, work)


class SHAPEGEN_OT_explore_bake(_NeedsLive, bpy.types.Operator):
    """Turn the live object into an ordinary mesh (no longer driven by the sliders)"""

    bl_idname = "shapegen.explore_bake"
    bl_label = "Bake"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        def work():
            scene = context.scene
            obj = live_object(scene)
            del obj[LIVE_KEY]
            del obj[TEMPLATE_INDEX_KEY]
            obj.name = f"{store.model_name(scene)} baked"
            obj.data.name = obj.name
            scene.shapegen.live_object = None
            return f"Baked '{obj.name}'"

        return _run(self, work)


class SHAPEGEN_OT_latent_map(store.NeedsModel, bpy.types.Operator):
    """Draw the training shapes' latent vectors as a 2-D map (image "ShapeGen Latent Map"):
    training shapes blue, outliers red, ShapeGen samples green, the live object white"""

    bl_idname = "shapegen.latent_map"
    bl_label = "Latent Map"
    bl_options = {"REGISTER"}

    size: IntProperty(name="Size", default=0, min=0, max=4096, description="Pixels (0: the panel's Map Size)")

    def execute(self, context):
        def work():
            scene = context.scene
            model = store.require_model(scene)
            size = self.size or scene.shapegen.map_size
            key = store.model_id(scene)
            extra = [np.asarray(o[LATENT_KEY], dtype=np.float64) for o in scene.objects
                     if o.get(MODEL_ID_KEY) == key and LATENT_KEY in o and LIVE_KEY not in o
                     and len(o[LATENT_KEY]) == model.latent_dim]
            live = live_object(scene)
            picture = latent_map_pixels(
                model.training_latents(), model.correspondence.outliers, size,
                samples=np.array(extra).reshape(-1, model.latent_dim),
                live=current_latent(scene) if live is not None else None)
            image = bpy.data.images.get(MAP_NAME)
            if image is not None and tuple(image.size) != (size, size):
                bpy.data.images.remove(image)
                image = None
            if image is None:
                image = bpy.data.images.new(MAP_NAME, size, size, alpha=True)
            image.pixels.foreach_set(picture.pixels.ravel())
            image.update()
            try:
                image.pack()  # keep the pixels with the .blend
            except RuntimeError:
                pass
            image["shapegen_dims"] = list(picture.dims)
            image["shapegen_bounds"] = list(picture.bounds)
            image["shapegen_model_id"] = key
            n_out = int(np.sum(model.correspondence.outliers))
            axes = ", ".join(f"z{d + 1}" for d in picture.dims if d >= 0)
            return (f"Latent map of {len(model.names)} shapes ({n_out} outlier(s)) on {axes}: "
                    f"image '{image.name}'")

        return _run(self, work)


CLASSES = (SHAPEGEN_OT_explore, SHAPEGEN_OT_explore_randomise, SHAPEGEN_OT_explore_reset,
           SHAPEGEN_OT_explore_snap, SHAPEGEN_OT_explore_bake, SHAPEGEN_OT_latent_map)
