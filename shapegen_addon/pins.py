"""Pins on the live object: Empties the artist moves; the live object takes the most probable
shape of the model given all of them (the core's `GenerativeShapeModel.complete_from_pins`,
thesis §5.5.3 made soft) and the sliders follow.

A pin is an Empty in the "<model> Pins" collection tagged with the landmark it pins
(keys.PIN_KEY). `on_depsgraph_update` (a depsgraph_update_post handler) compares the pins'
positions in the live object's frame with those it last applied and, when a pin moved, was
added or deleted, asks the core for the posterior given every pin, searched from the live
object's latent (so a drag moves the shape continuously), and sets the sliders to it (one
re-mesh through latent.py's `LatentMesher`). Each pin records how far the shape stays from
it (keys.PIN_DISTANCE_KEY); with Show Uncertainty the live object gets a colour attribute
of the posterior standard deviation per vertex (keys.STD_ATTRIBUTE), from the core's
`vertex_std`.
"""

from __future__ import annotations

import bpy
import numpy as np
from bpy.app.handlers import persistent
from mathutils import Vector

from ..core.base.errors import ShapeGenError
from . import latent, store
from .keys import (MODEL_ID_KEY, PIN_DISTANCE_KEY, PIN_KEY, PINS_START_KEY, STD_ATTRIBUTE,
                   TEMPLATE_INDEX_KEY, VERTEX_MAP_KEY)

__all__ = ["add_pin", "clear_pins", "pins_of", "apply_pins", "on_depsgraph_update", "pin_objects",
           "collection_name", "register_pin_handler", "unregister_pin_handler"]

# scene name -> the pins last applied ((landmark, x, y, z) rounded), so the handler's own
# re-mesh, or an update that moved no pin, costs nothing
_APPLIED: dict[str, tuple] = {}
_BUSY = [False]


def collection_name(scene: bpy.types.Scene) -> str:
    return f"{store.model_name(scene)} Pins"


def pin_objects(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    """The scene's pins of its model, by landmark."""
    key = store.model_id(scene)
    found = [o for o in scene.objects if PIN_KEY in o and o.get(MODEL_ID_KEY) == key]
    return sorted(found, key=lambda o: int(o[PIN_KEY]))


def _live_matrix(obj: bpy.types.Object) -> np.ndarray:
    return np.array(obj.matrix_world, dtype=np.float64)


def pins_of(scene: bpy.types.Scene) -> dict[int, np.ndarray]:
    """{landmark: position in the live object's frame (the model frame)}."""
    obj = latent.live_object(scene)
    if obj is None:
        return {}
    inverse = np.linalg.inv(_live_matrix(obj))
    pins = {}
    for pin in pin_objects(scene):
        world = np.append(np.array(pin.matrix_world.translation, dtype=np.float64), 1.0)
        pins[int(pin[PIN_KEY])] = (inverse @ world)[:3]
    return pins


def _signature(pins: dict[int, np.ndarray]) -> tuple:
    return tuple((i, *np.round(p, 7).tolist()) for i, p in sorted(pins.items()))


def _live_landmarks(scene: bpy.types.Scene, model) -> np.ndarray:
    return model.decode(latent.current_latent(scene))[0]


def add_pin(scene: bpy.types.Scene, landmark: int = -1) -> bpy.types.Object:
    """An Empty at the live object's landmark `landmark` (-1: the one nearest the 3D cursor)."""
    obj = latent.live_object(scene)
    if obj is None:
        raise ShapeGenError("no live object: press Explore first")
    model = store.require_model(scene)
    landmarks = _live_landmarks(scene, model)
    matrix = _live_matrix(obj)
    world = landmarks @ matrix[:3, :3].T + matrix[:3, 3]
    if landmark < 0:
        landmark = int(np.argmin(np.sum((world - np.array(scene.cursor.location)) ** 2, axis=1)))
    elif landmark >= model.n_landmarks:
        raise ShapeGenError(f"landmark {landmark} does not exist: the model has {model.n_landmarks} (0 to "
                            f"{model.n_landmarks - 1})")
    if any(int(p[PIN_KEY]) == landmark for p in pin_objects(scene)):
        raise ShapeGenError(f"landmark {landmark} is pinned already: move its pin")
    if not pin_objects(scene):
        obj[PINS_START_KEY] = latent.current_latent(scene).tolist()
    name = collection_name(scene)
    collection = bpy.data.collections.get(name)
    if collection is None:
        collection = bpy.data.collections.new(name)
    if collection.name not in scene.collection.children:
        scene.collection.children.link(collection)
    pin = bpy.data.objects.new(f"Pin {landmark}", None)
    pin.empty_display_type = "SPHERE"
    pin.empty_display_size = 0.02 * float(np.ptp(world, axis=0).max())
    pin.location = Vector(world[landmark].tolist())
    pin[PIN_KEY] = landmark
    pin[MODEL_ID_KEY] = store.model_id(scene)
    pin[PIN_DISTANCE_KEY] = 0.0
    collection.objects.link(pin)
    _APPLIED[scene.name] = _signature(pins_of(scene))  # pinned where the shape is: nothing to re-solve
    return pin


def clear_pins(scene: bpy.types.Scene) -> int:
    """Remove every pin; the live object goes back to the shape it had before the first."""
    pins = pin_objects(scene)
    for pin in pins:
        bpy.data.objects.remove(pin)
    collection = bpy.data.collections.get(collection_name(scene))
    if collection is not None and not collection.all_objects:
        bpy.data.collections.remove(collection)
    _APPLIED.pop(scene.name, None)
    obj = latent.live_object(scene)
    if obj is not None and PINS_START_KEY in obj:
        start = np.array(list(obj[PINS_START_KEY]), dtype=np.float64)  # a copy: the property's memory goes next
        del obj[PINS_START_KEY]
        if start.shape == (len(scene.shapegen.latents),):
            latent.set_latent(scene, start)
    return len(pins)


def apply_pins(scene: bpy.types.Scene, force: bool = False) -> bool:
    """The live object takes the most probable shape given its pins (module docstring);
    False when there was nothing to do (no live object, no pins, no pin moved)."""
    obj = latent.live_object(scene)
    if obj is None or not len(scene.shapegen.latents):
        return False
    pins = pins_of(scene)
    signature = _signature(pins)
    if not pins or (not force and _APPLIED.get(scene.name) == signature):
        _APPLIED[scene.name] = signature
        return False
    model = store.require_model(scene)
    done = model.complete_from_pins(pins, start=latent.current_latent(scene))
    _APPLIED[scene.name] = signature
    # as a slider drag: the sliders, one re-mesh, and the quality gate only once the drag pauses
    values = latent.slider_units(scene).to_values(done.latent)
    with latent.sliders_batch():
        for item, value in zip(scene.shapegen.latents, values):
            item.value = float(value)
    if latent.update_live(scene, full_check=False):
        latent._schedule_full_check(scene)
    distances = done.distances(pins)
    for pin in pin_objects(scene):
        pin[PIN_DISTANCE_KEY] = distances.get(int(pin[PIN_KEY]), 0.0)
    if scene.shapegen.explore.show_uncertainty:
        write_uncertainty(obj, model, done.std)
    return True


def write_uncertainty(obj: bpy.types.Object, model, landmark_std: np.ndarray) -> None:
    """The live object's colour attribute STD_ATTRIBUTE: posterior std per vertex, as grey
    levels from the smallest (black: surest, at the pins) to the largest (white: least sure)."""
    std = model.vertex_std(landmark_std, int(obj[TEMPLATE_INDEX_KEY]))
    if VERTEX_MAP_KEY in obj:
        std = std[np.asarray(obj[VERTEX_MAP_KEY], dtype=np.int64)]
    level = (std - std.min()) / max(float(np.ptp(std)), 1e-12)
    mesh = obj.data
    attribute = mesh.color_attributes.get(STD_ATTRIBUTE)
    if attribute is None or attribute.domain != "POINT" or attribute.data_type != "FLOAT_COLOR":
        if attribute is not None:
            mesh.color_attributes.remove(attribute)
        attribute = mesh.color_attributes.new(STD_ATTRIBUTE, "FLOAT_COLOR", "POINT")
    colours = np.ones((len(level), 4), dtype=np.float32)
    colours[:, :3] = level[:, None]
    attribute.data.foreach_set("color", colours.ravel())
    mesh.update()


@persistent
def on_depsgraph_update(scene, depsgraph=None):
    """depsgraph_update_post: re-solve when a pin moved, was added or deleted."""
    if _BUSY[0] or not isinstance(scene, bpy.types.Scene) or scene.shapegen.live_object is None:
        return
    _BUSY[0] = True
    try:
        apply_pins(scene)
    except ShapeGenError as exc:  # a handler cannot report: keep the reason visible
        scene.shapegen.job_message = str(exc)
    finally:
        _BUSY[0] = False


def register_pin_handler() -> None:
    if on_depsgraph_update not in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.append(on_depsgraph_update)


def unregister_pin_handler() -> None:
    while on_depsgraph_update in bpy.app.handlers.depsgraph_update_post:
        bpy.app.handlers.depsgraph_update_post.remove(on_depsgraph_update)
    _APPLIED.clear()
