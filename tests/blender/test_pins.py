"""Pins on the live object (Explore): the live object takes the model's most
probable shape given the pins, the sliders follow, clearing restores, and both operators are
undo steps (headless Blender cannot run undo itself)."""

from __future__ import annotations

import bpy
import numpy as np
import pytest
from conftest import addon_module, load_model, vertices


def _pins(extension):
    return addon_module(extension, "shapegen_addon.pins")


def _move(pin, world) -> None:
    pin.location = tuple(float(v) for v in world)
    bpy.context.view_layer.update()  # the depsgraph handler re-solves here


@pytest.mark.parametrize("kind", ["ppca", "bgplvm"])
def test_pins_at_a_training_shape_bring_the_live_object_to_it(extension, model_files, kind):
    load_model(kind, model_files)
    scene = bpy.context.scene
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    model = addon_module(extension, "shapegen_addon.store").get_model(scene)
    live = scene.shapegen.live_object
    matrix = np.array(live.matrix_world)
    target = model.correspondence.points[3]
    chosen = list(range(0, model.n_landmarks, 5))
    for i in chosen:
        assert bpy.ops.shapegen.pin_add(landmark=i) == {"FINISHED"}
    pins = _pins(extension).pin_objects(scene)
    assert [int(p["shapegen_pin"]) for p in pins] == chosen
    assert all(p.users_collection[0].name.endswith(" Pins") for p in pins)
    before = np.array([item.value for item in scene.shapegen.latents])
    for pin, i in zip(pins, chosen):
        pin.location = tuple((matrix[:3, :3] @ target[i] + matrix[:3, 3]).tolist())
    bpy.context.view_layer.update()
    after = np.array([item.value for item in scene.shapegen.latents])
    assert np.abs(after - before).max() > 1e-3                                   # the sliders followed
    shown = model.decode(addon_module(extension, "shapegen_addon.latent").current_latent(scene))[0]
    reconstruction = model.decode(model.encode(target[None]))[0]
    error = np.sqrt(np.mean(np.sum((shown - target) ** 2, 1)))
    assert error <= 1.5 * np.sqrt(np.mean(np.sum((reconstruction - target) ** 2, 1))) + 1e-4
    # the live mesh is the re-meshed shape, and each pin says how far the shape stays from it
    mesher = model.latent_mesher(int(live["shapegen_template_index"]))
    z = addon_module(extension, "shapegen_addon.latent").current_latent(scene)
    np.testing.assert_allclose(vertices(live), mesher.vertices(z), atol=1e-5)
    distances = [float(p["shapegen_pin_distance"]) for p in pins]
    assert max(distances) > 0 and max(distances) < 0.1 * np.ptp(target, axis=0).max()


def test_moving_one_pin_moves_the_sliders_and_clearing_restores(extension, model_files):
    load_model("ppca", model_files)
    scene = bpy.context.scene
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    live = scene.shapegen.live_object
    start = vertices(live).copy()
    model = addon_module(extension, "shapegen_addon.store").get_model(scene)
    # the landmark that varies most over the class (a vase's floor point does not move at all)
    varying = int(np.argmax(np.linalg.norm(model.model.components_.reshape(model.n_landmarks, -1), axis=1)))
    shown = model.decode(addon_module(extension, "shapegen_addon.latent").current_latent(scene))[0]
    scene.cursor.location = tuple(live.matrix_world @ __import__("mathutils").Vector(shown[varying].tolist()))
    assert bpy.ops.shapegen.pin_add() == {"FINISHED"}                          # nearest the cursor
    pin = _pins(extension).pin_objects(scene)[0]
    assert int(pin["shapegen_pin"]) == varying
    values = np.array([item.value for item in scene.shapegen.latents])
    _move(pin, np.array(pin.location) + np.array([0.0, 0.0, 0.3]))
    moved = np.array([item.value for item in scene.shapegen.latents])
    assert np.abs(moved - values).max() > 1e-3
    assert np.abs(vertices(live) - start).max() > 1e-3
    assert bpy.ops.shapegen.pins_clear() == {"FINISHED"}
    assert not _pins(extension).pin_objects(scene)
    assert bpy.data.collections.get(_pins(extension).collection_name(scene)) is None
    np.testing.assert_allclose(vertices(live), start, atol=1e-5)
    np.testing.assert_allclose([item.value for item in scene.shapegen.latents], values, atol=1e-6)


def test_show_uncertainty_colours_the_live_object(extension, model_files):
    load_model("ppca", model_files)
    scene = bpy.context.scene
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    scene.shapegen.explore.show_uncertainty = True
    assert bpy.ops.shapegen.pin_add(landmark=0) == {"FINISHED"}
    pin = _pins(extension).pin_objects(scene)[0]
    _move(pin, np.array(pin.location) + np.array([0.05, 0.0, 0.0]))
    live = scene.shapegen.live_object
    attribute = live.data.color_attributes.get("shapegen_std")
    assert attribute is not None and len(attribute.data) == len(live.data.vertices)
    colours = np.empty(len(attribute.data) * 4, dtype=np.float32)
    attribute.data.foreach_get("color", colours)
    grey = colours.reshape(-1, 4)[:, 0]
    assert grey.max() == pytest.approx(1.0) and grey.min() == pytest.approx(0.0)


def test_pin_operators_are_undo_steps(extension):
    for name in ("pin_add", "pins_clear"):
        operator = getattr(bpy.types, f"SHAPEGEN_OT_{name}")
        assert {"REGISTER", "UNDO"} <= set(operator.bl_options)
