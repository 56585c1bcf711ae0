"""Latent vectors in the scene: the sliders, the live object they drive, and the latent
tag of every object ShapeGen generates.

The live object is a copy of one template training shape's own mesh (template_mesh: its
polygons, UV maps and materials; a triangle mesh when the template's object is gone).
Each slider change re-meshes it through the core's `LatentMesher` (vertices = offset +
features(z) @ basis, the basis computed once per model and template) and one bulk write
of the position attribute (through the copy's vertex map when the core welded vertices),
so a drag costs a small matrix product and a `foreach_set`, for every model type.

The live shape is checked by the core's quality gate (core/generate/quality.py; 10-200 ms for
10-30k faces, most of it the self-intersection search): at once after an operator
(Explore, Randomise, Snap, Reset) and, while a slider is dragged, once the drag pauses
(FULL_CHECK_DELAY, a timer), so a drag stays a matrix product and a bulk write. The
reasons the current shape fails are kept on the object (keys.QUALITY_KEY, "" when it
passes) and shown in the Explore panel.

Generated objects (samples, in-between shapes, modes, the live object) carry their latent
vector, model and template (keys.LATENT_KEY, ...): written by `tag_object`, read by
`object_latent` and `tagged_latents`.
"""

from __future__ import annotations

import contextlib

import bpy
import numpy as np

from ..core.base.errors import ShapeGenError
from ..core.models.latent_units import LatentUnits
from ..core.generate.quality import QualitySettings
from ..core.generate.sampling import quality_gate
from . import store
from .keys import (LATENT_KEY, LIVE_KEY, MODEL_ID_KEY, MODEL_KEY, QUALITY_KEY, SEED_KEY, SOURCE_KEY,
                   TEMPLATE_INDEX_KEY, TEMPLATE_KEY, VERTEX_MAP_KEY)
from .placement import place_one, union_box, vertex_box
from .template_mesh import TemplateMeshes

__all__ = ["on_slider_changed", "sliders_batch", "update_live", "current_latent", "set_latent", "set_values",
           "slider_units", "reset_sliders",
           "live_object", "create_live", "model_changed", "write_positions", "tag_object", "object_latent",
           "tagged_latents", "forget_cache", "live_quality", "LIVE_NAME"]

LIVE_NAME = "ShapeGen Live"

# (model id, template index) -> LatentMesher; process memory, rebuilt lazily
_MESHERS: dict[tuple[str, int], object] = {}
# live mesh datablock name -> its vertex map (keys.VERTEX_MAP_KEY as an array); rebuilt lazily
_VERTEX_MAPS: dict[str, np.ndarray] = {}
_SUSPENDED = [0]
# updates of the live object so far; a pending gate check runs only if none came after it
_UPDATES = [0]
#: Seconds a slider drag must pause before the quality gate checks the live shape.
FULL_CHECK_DELAY = 0.3


def forget_cache() -> None:
    _MESHERS.clear()
    _VERTEX_MAPS.clear()


@contextlib.contextmanager
def sliders_batch():
    """Set many sliders with one re-mesh at the end (instead of one per slider)."""
    _SUSPENDED[0] += 1
    try:
        yield
    finally:
        _SUSPENDED[0] -= 1


# ------------------------------------------------------------------------------ sliders
def rebuild_sliders(scene: bpy.types.Scene, model) -> None:
    """One slider per latent dimension of `model`, all at the training mean, in training
    standard deviations (core.models.latent_units: ±3 covers every training shape), as the model
    file records them (nothing is encoded here)."""
    settings = scene.shapegen
    units = model.latent_units()
    with sliders_batch():
        settings.latents.clear()
        for k in range(model.latent_dim):
            item = settings.latents.add()
            item.name = f"z{k + 1}"
            item.centre = float(units.centre[k])
            item.scale = float(units.scale[k])
            item.value = 0.0


def slider_units(scene: bpy.types.Scene) -> LatentUnits:
    """The sliders' units: centre and scale per dimension."""
    items = scene.shapegen.latents
    return LatentUnits(np.array([item.centre for item in items], dtype=np.float64),
                       np.array([item.scale for item in items], dtype=np.float64))


def current_latent(scene: bpy.types.Scene) -> np.ndarray:
    """z from the sliders: centre + value × scale per dimension."""
    values = np.array([item.value for item in scene.shapegen.latents], dtype=np.float64)
    return slider_units(scene).to_latent(values)


def _sized(scene: bpy.types.Scene, vector) -> np.ndarray:
    vector = np.asarray(vector, dtype=np.float64).ravel()
    if len(vector) != len(scene.shapegen.latents):
        raise ShapeGenError(f"latent vector has {len(vector)} values, the sliders {len(scene.shapegen.latents)}")
    return vector


def set_values(scene: bpy.types.Scene, values: np.ndarray) -> None:
    """Set every slider (in its units), then re-mesh once."""
    with sliders_batch():
        for item, value in zip(scene.shapegen.latents, _sized(scene, values)):
            item.value = float(value)
    update_live(scene)


def set_latent(scene: bpy.types.Scene, z: np.ndarray) -> None:
    """Move every slider so the sliders express `z`, then re-mesh once."""
    set_values(scene, slider_units(scene).to_values(_sized(scene, z)))


def reset_sliders(scene: bpy.types.Scene) -> None:
    """Every slider back to the training mean, then re-mesh once."""
    with sliders_batch():
        for item in scene.shapegen.latents:
            item.value = 0.0
    update_live(scene)


def on_slider_changed(scene: bpy.types.Scene) -> None:
    """Update callback of every slider (properties.ShapeGenLatent.value)."""
    if _SUSPENDED[0] or not isinstance(scene, bpy.types.Scene):
        return
    try:
        if update_live(scene, full_check=False):
            _schedule_full_check(scene)
    except ShapeGenError as exc:  # an update callback cannot report: keep the reason visible
        scene.shapegen.job_message = str(exc)


def _schedule_full_check(scene: bpy.types.Scene) -> None:
    """The quality gate's check of the live shape once the drag pauses (FULL_CHECK_DELAY)."""
    token = _UPDATES[0]
    scene_name = scene.name

    def check():
        found = bpy.data.scenes.get(scene_name)
        if found is not None and _UPDATES[0] == token:
            try:
                live_quality(found)
            except ShapeGenError:
                pass
        return None

    bpy.app.timers.register(check, first_interval=FULL_CHECK_DELAY)


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


def update_live(scene: bpy.types.Scene, full_check: bool = True) -> bool:
    """Re-mesh the live object from the sliders and, with `full_check`, check it with the
    quality gate (a slider drag leaves that to `_schedule_full_check`). False when there is
    nothing to update."""
    obj = live_object(scene)
    if obj is None or not len(scene.shapegen.latents):
        return False
    model = store.require_model(scene)
    if obj[LIVE_KEY] != store.model_id(scene):
        raise ShapeGenError(f"'{obj.name}' belongs to another model: press Explore to rebuild it")
    mesher = _mesher(scene, model, int(obj[TEMPLATE_INDEX_KEY]))
    vertex_map = _vertex_map(obj)
    expected = mesher.n_vertices if vertex_map is None else len(vertex_map)
    if len(obj.data.vertices) != expected or (vertex_map is not None and vertex_map.max() >= mesher.n_vertices):
        raise ShapeGenError(f"'{obj.name}' has {len(obj.data.vertices)} vertices, its template "
                            f"'{mesher.template_name}' {mesher.n_vertices}: press Explore to rebuild it")
    z = current_latent(scene)
    flat = mesher.flat_vertices(z)
    write_positions(obj.data, flat if vertex_map is None else flat.reshape(-1, 3)[vertex_map].ravel())
    obj[LATENT_KEY] = z.tolist()
    _UPDATES[0] += 1
    if full_check:
        _gate_live(obj, model, mesher.template_index, flat)
    return True


def _gate_live(obj: bpy.types.Object, model, template_index: int, flat: np.ndarray):
    """The quality gate's verdict on the live shape (core vertices `flat`), its reasons kept
    on the object (keys.QUALITY_KEY)."""
    quality = quality_gate(model, QualitySettings()).check(np.asarray(flat, dtype=np.float64).reshape(-1, 3),
                                                           template_index)
    obj[QUALITY_KEY] = "; ".join(quality.reasons)
    return quality


def live_quality(scene: bpy.types.Scene):
    """The full quality gate (core/generate/quality.py `MeshQuality`) of the live object's current
    shape, its reasons kept on the object (keys.QUALITY_KEY, "" when it passes); None when
    there is no live object."""
    obj = live_object(scene)
    if obj is None or not len(scene.shapegen.latents):
        return None
    model = store.require_model(scene)
    mesher = _mesher(scene, model, int(obj[TEMPLATE_INDEX_KEY]))
    return _gate_live(obj, model, mesher.template_index, mesher.flat_vertices(current_latent(scene)))


def _vertex_map(obj: bpy.types.Object) -> np.ndarray | None:
    """The live object's vertex map (keys.VERTEX_MAP_KEY), None when it is the identity."""
    if VERTEX_MAP_KEY not in obj:
        return None
    found = _VERTEX_MAPS.get(obj.data.name)
    if found is None or len(found) != len(obj.data.vertices):
        found = _VERTEX_MAPS[obj.data.name] = np.asarray(obj[VERTEX_MAP_KEY], dtype=np.int64)
    return found


def create_live(scene: bpy.types.Scene, model, template: str = "") -> tuple[bpy.types.Object, str]:
    """Create (or rebuild) the live object on the template nearest the mean shape, a copy of
    the template's own mesh (template_mesh); a new one goes beside the scene's objects
    (placement.place_one), a rebuilt one stays where it is. Returns (object, note: empty,
    or why it is a plain triangle mesh)."""
    index = model.shape_index(template) if template else model.mean_template()
    meshes = TemplateMeshes(scene, model)
    data = meshes.mesh(f"{LIVE_NAME} mesh", index, model.meshes[index].vertices)
    found = meshes.template(index)
    obj = live_object(scene)
    if obj is None:
        obj = bpy.data.objects.new(LIVE_NAME, data)
        # room for any shape of the class, as the sliders change it
        obj.location = place_one(scene, union_box([vertex_box(mesh.vertices) for mesh in model.meshes]))
        scene.collection.objects.link(obj)
        scene.shapegen.live_object = obj
    else:
        old = obj.data
        obj.data = data
        if old.users == 0:
            bpy.data.meshes.remove(old)
        if obj.name not in scene.objects:  # deleted from the scene but still referenced
            scene.collection.objects.link(obj)
    _VERTEX_MAPS.pop(data.name, None)
    if found is not None and found.vertex_map is not None:
        obj[VERTEX_MAP_KEY] = found.vertex_map.tolist()
    elif VERTEX_MAP_KEY in obj:
        del obj[VERTEX_MAP_KEY]
    obj[LIVE_KEY] = store.model_id(scene)
    obj[MODEL_KEY] = store.model_name(scene)
    obj[MODEL_ID_KEY] = store.model_id(scene)
    obj[TEMPLATE_KEY] = model.names[index]
    obj[TEMPLATE_INDEX_KEY] = index
    if len(scene.shapegen.latents) != model.latent_dim:
        rebuild_sliders(scene, model)
    update_live(scene)
    return obj, meshes.note


def bake_live(scene: bpy.types.Scene) -> bpy.types.Object:
    """The live object becomes an ordinary (still tagged) mesh, no longer driven by the sliders."""
    obj = live_object(scene)
    del obj[LIVE_KEY]
    del obj[TEMPLATE_INDEX_KEY]
    if QUALITY_KEY in obj and not obj[QUALITY_KEY]:
        del obj[QUALITY_KEY]
    if VERTEX_MAP_KEY in obj:
        del obj[VERTEX_MAP_KEY]
    obj.name = f"{store.model_name(scene)} baked"
    obj.data.name = obj.name
    scene.shapegen.live_object = None
    return obj


def model_changed(scene: bpy.types.Scene, model) -> None:
    """A new model became the scene's: new sliders; an existing live object follows it."""
    rebuild_sliders(scene, model)
    if live_object(scene) is not None:
        create_live(scene, model)


# ------------------------------------------------------------------------------ latent tags
def tag_object(obj: bpy.types.Object, scene: bpy.types.Scene, z, template: str, seed: int | None = None) -> None:
    """Custom properties that tie a generated object to its model and latent vector."""
    obj[LATENT_KEY] = [float(v) for v in np.ravel(z)]
    obj[MODEL_KEY] = store.model_name(scene)
    obj[MODEL_ID_KEY] = store.model_id(scene)
    obj[TEMPLATE_KEY] = template
    if seed is not None:
        obj[SEED_KEY] = int(seed)


def object_latent(model, scene: bpy.types.Scene, obj: bpy.types.Object) -> np.ndarray:
    """The latent vector of `obj` under `model`: its latent tag (a sample, baked or live
    object of this model), else the encoded landmarks of the training shape it is (by
    name, or by the source tag of a prepared copy)."""
    if LATENT_KEY in obj and obj.get(MODEL_ID_KEY) == store.model_id(scene):
        z = np.asarray(obj[LATENT_KEY], dtype=np.float64)
        if z.shape == (model.latent_dim,):
            return z
    for name in (obj.name, obj.get(SOURCE_KEY)):
        if isinstance(name, str) and name in model.names:
            return model.training_latents()[model.names.index(name)]
    raise ShapeGenError(f"'{obj.name}' has no latent vector in model '{store.model_name(scene)}': pick a "
                        "training shape (named like one of the model's shapes) or a ShapeGen sample of this model")


def tagged_latents(scene: bpy.types.Scene, model) -> np.ndarray:
    """(K, latent_dim) latent vectors of the scene's objects tagged by the scene's model,
    the live object excepted (samples, in-between shapes, baked objects)."""
    key = store.model_id(scene)
    found = [np.asarray(o[LATENT_KEY], dtype=np.float64) for o in scene.objects
             if o.get(MODEL_ID_KEY) == key and LATENT_KEY in o and LIVE_KEY not in o
             and len(o[LATENT_KEY]) == model.latent_dim]
    return np.array(found).reshape(-1, model.latent_dim)
