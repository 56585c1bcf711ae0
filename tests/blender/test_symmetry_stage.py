"""The symmetry stage of Prepare on Blender-made mugs (issue 12): eight mugs modelled with
bmesh (quads, 32-gon caps, a handle as a second part: bench/blender_mugs.py `mug_data`),
one laid on its side by its object rotation and one by its mesh data. The real Prepare
operator stands both up (their axes are the collection's up by symmetry), the prepared
copies say so and carry the rotation, nobody else is turned, and the artist's objects are
untouched."""

from __future__ import annotations

import importlib.util
import math

import bpy
import numpy as np
from conftest import ROOT, addon_module, vertices
from mathutils import Matrix


def _mug_builder():
    spec = importlib.util.spec_from_file_location("blender_mugs", ROOT / "bench" / "blender_mugs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _mugs(count: int = 8) -> bpy.types.Collection:
    builder = _mug_builder()
    rng = np.random.default_rng(3)
    material = bpy.data.materials.new("Ceramic")
    collection = bpy.data.collections.new("mugs")
    bpy.context.scene.collection.children.link(collection)
    for i in range(count):
        obj = bpy.data.objects.new(f"mug_{i}", builder.mug_data(f"mug_{i}", rng, material))
        obj.location = (4.0 * i, 0.0, 0.0)
        collection.objects.link(obj)
    settings = bpy.context.scene.shapegen
    settings.source_collection = collection
    settings.n_landmarks = 60
    return collection


def test_mugs_on_their_side_are_stood_up_and_the_originals_untouched(extension):
    keys = addon_module(extension, "shapegen_addon.keys")
    prepared_objects = addon_module(extension, "shapegen_addon.prepared").prepared_objects
    collection = _mugs()
    by_object = bpy.data.objects["mug_2"]
    by_object.rotation_euler = (math.pi / 2, 0.0, 0.0)  # its axis along -y
    by_data = bpy.data.objects["mug_5"]
    by_data.data.transform(Matrix.Rotation(math.pi / 2, 4, "Y"))  # its axis along +x
    bpy.context.view_layer.update()
    axes = {"mug_2": np.array(by_object.matrix_world)[:3, :3] @ [0.0, 0.0, 1.0], "mug_5": np.array([1.0, 0.0, 0.0])}
    before = {o.name: (np.array(o.matrix_world), vertices(o).copy(), set(o.keys())) for o in collection.objects}

    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    message = bpy.context.scene.shapegen.job_message
    assert "2 turned (mug_2, mug_5)" in message, message

    copies = {o[keys.SOURCE_KEY]: o for o in prepared_objects(bpy.data.collections["mugs Prepared"])}
    assert set(copies) == {f"mug_{i}" for i in range(8)}
    for name, copy in copies.items():
        transform = np.reshape(copy[keys.TRANSFORM_KEY], (4, 4))
        rotation = transform[:3, :3] / np.cbrt(np.linalg.det(transform[:3, :3]))
        if name in axes:
            change = copy[keys.POSE_CHANGE_KEY]
            assert change.startswith("turned ") and "file-convention turn" in change, (change, copy[keys.POSE_OUTLIER_KEY])
            # the mug's own axis (bottom to top) is up in the prepared copy
            assert (rotation @ axes[name])[2] > np.cos(np.radians(3.0)), (name, rotation @ axes[name],
                                                                          copy[keys.POSE_OUTLIER_KEY])
            turn = np.reshape(copy[keys.POSE_ROTATION_KEY], (3, 3))
            np.testing.assert_allclose(turn @ turn.T, np.eye(3), atol=1e-6)
            assert np.degrees(np.arccos(np.clip((np.trace(turn) - 1) / 2, -1, 1))) > 80.0
        else:
            assert copy[keys.POSE_OUTLIER_KEY] == ""
            assert copy[keys.POSE_CHANGE_KEY] == "", (name, copy[keys.POSE_CHANGE_KEY])
            np.testing.assert_array_equal(copy[keys.POSE_ROTATION_KEY], np.eye(3).ravel())
            np.testing.assert_allclose(rotation, np.eye(3), atol=1e-9)

    for obj in collection.objects:  # the artist's objects: same place, same mesh, no new properties
        matrix, points, props = before[obj.name]
        np.testing.assert_array_equal(np.array(obj.matrix_world), matrix)
        np.testing.assert_array_equal(vertices(obj), points)
        assert set(obj.keys()) == props
