"""Prepare keeps what it is given (issue 30) on a mug scene as an artist models it: solid
mugs (quad walls, n-gon caps at both ends, walls tapering inward on some and outward on
others, a handle as a second part: bench/blender_mugs.py `mug_data(closed=True)`), one
with a Subdivision modifier, one parented to a turned, scaled empty, one with an
unapplied rotation and one with an unapplied non-uniform scale, all upright in the world.
The real Prepare operator turns none of them; a mug laid on its side by hand is stood on
its axis and flagged (which end is up, nothing in a class of tapers both ways tells), and
Turn Flagged turns it as the flag suggests, in one undoable step; the artist's objects
are never changed."""

from __future__ import annotations

import importlib.util
import math

import bpy
import numpy as np
from conftest import ROOT, addon_module, vertices

KINDS = ("plain", "subdivided", "parented", "rotated", "scaled")


def _mug_builder():
    spec = importlib.util.spec_from_file_location("blender_mugs", ROOT / "bench" / "blender_mugs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _solid_mugs(count: int = 10) -> bpy.types.Collection:
    """The scene: `count` solid mugs upright in the world, the kinds of KINDS in turn."""
    builder = _mug_builder()
    rng = np.random.default_rng(11)
    material = bpy.data.materials.new("Ceramic")
    collection = bpy.data.collections.new("mugs")
    bpy.context.scene.collection.children.link(collection)
    for i in range(count):
        data = builder.mug_data(f"mug_{i}", rng, material, closed=True)
        obj = bpy.data.objects.new(f"mug_{i}", data)
        collection.objects.link(obj)
        kind = KINDS[i % len(KINDS)]
        if kind == "subdivided":
            modifier = obj.modifiers.new("Subdivision", "SUBSURF")
            modifier.levels = 1
        elif kind == "parented":
            holder = bpy.data.objects.new(f"holder_{i}", None)
            bpy.context.scene.collection.objects.link(holder)
            holder.rotation_euler, holder.scale = (0.0, 0.0, 0.7), (1.5, 1.5, 1.5)
            bpy.context.view_layer.update()
            obj.parent = holder
            obj.matrix_parent_inverse = holder.matrix_world.inverted()  # upright and facing +x in the world
        elif kind == "rotated":  # unapplied rotation, the data turned back: upright in the world
            obj.rotation_euler = (0.4, -0.3, 1.1)
            data.transform(obj.rotation_euler.to_matrix().to_4x4().inverted())
        elif kind == "scaled":  # unapplied non-uniform scale, the data scaled back
            obj.scale = (1.4, 0.8, 1.2)
            data.transform(np.diag([1 / 1.4, 1 / 0.8, 1 / 1.2, 1.0]).tolist())
        (obj.parent or obj).location = (4.0 * i, 0.0, 0.0)
    bpy.context.view_layer.update()
    settings = bpy.context.scene.shapegen
    settings.source_collection = collection
    settings.n_landmarks = 60
    return collection


def _snapshot(collection) -> dict:
    """What the artist made: world matrix, mesh, modifiers, materials, UVs, properties."""
    return {o.name: (np.array(o.matrix_world), vertices(o).copy(), [m.type for m in o.modifiers],
                     [m.name for m in o.data.materials], [u.name for u in o.data.uv_layers], set(o.keys()))
            for o in collection.objects}


def _assert_untouched(collection, before: dict) -> None:
    for name, (matrix, points, modifiers, materials, uvs, keys) in before.items():
        obj = bpy.data.objects[name]
        np.testing.assert_array_equal(np.array(obj.matrix_world), matrix)
        np.testing.assert_array_equal(vertices(obj), points)
        assert [m.type for m in obj.modifiers] == modifiers
        assert [m.name for m in obj.data.materials] == materials and [u.name for u in obj.data.uv_layers] == uvs
        assert set(obj.keys()) == keys


def _copies(extension) -> dict:
    keys = addon_module(extension, "shapegen_addon.keys")
    prepared = addon_module(extension, "shapegen_addon.prepared")
    return {o[keys.SOURCE_KEY]: o for o in prepared.prepared_objects(bpy.data.collections["mugs Prepared"])}


def _rotation(copy, keys) -> np.ndarray:
    transform = np.reshape(copy[keys.TRANSFORM_KEY], (4, 4))
    return transform[:3, :3] / np.cbrt(np.linalg.det(transform[:3, :3]))


def test_upright_solid_mugs_are_not_turned_and_stay_as_made(extension):
    keys = addon_module(extension, "shapegen_addon.keys")
    collection = _solid_mugs()
    before = _snapshot(collection)
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    message = bpy.context.scene.shapegen.job_message
    assert ", 0 turned" in message, (message, {n: c[keys.POSE_CHANGE_KEY] for n, c in _copies(extension).items()})
    for name, copy in _copies(extension).items():
        assert copy[keys.POSE_CHANGE_KEY] == "", (name, copy[keys.POSE_CHANGE_KEY])
        # world +Z is the prepared copy's up: no turn beyond the given up axis
        np.testing.assert_allclose(_rotation(copy, keys) @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-9)
    _assert_untouched(collection, before)


def test_a_mug_laid_on_its_side_is_stood_up_flagged_and_turned_on_request(extension):
    keys = addon_module(extension, "shapegen_addon.keys")
    collection = _solid_mugs()
    laid = bpy.data.objects["mug_5"]  # a plain object
    laid.rotation_euler = (math.pi / 2, 0.0, 0.0)  # laid on its side by hand: its own up along world -y
    bpy.context.view_layer.update()
    own_up = np.array(laid.matrix_world.to_3x3().normalized()) @ [0.0, 0.0, 1.0]
    before = _snapshot(collection)
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    copies = _copies(extension)
    copy = copies["mug_5"]
    assert "file-convention turn" in copy[keys.POSE_CHANGE_KEY], copy[keys.POSE_CHANGE_KEY]
    # its axis is up; which end, nothing in the collection tells: flagged with a turn to make
    assert abs((_rotation(copy, keys) @ own_up)[2]) > math.cos(math.radians(3.0))
    assert copy[keys.POSE_OUTLIER_KEY].startswith("may be upside down"), copy[keys.POSE_OUTLIER_KEY]
    assert keys.FLAG_TURN_KEY in copy
    for name, other in copies.items():
        if name != "mug_5":
            assert other[keys.POSE_CHANGE_KEY] == "" and keys.FLAG_TURN_KEY not in other, name
    landmarks = np.array(copy[keys.LANDMARKS_KEY], dtype=np.float64).reshape(-1, 3)
    markers = next(c for c in copy.children if c.type == "MESH")
    marker_centre = vertices(markers).mean(axis=0)

    assert bpy.ops.shapegen.turn_flagged() == {"FINISHED"}
    assert "SHAPEGEN_OT_turn_flagged" in dir(bpy.types) and "UNDO" in bpy.types.SHAPEGEN_OT_turn_flagged.bl_options
    copy = _copies(extension)["mug_5"]
    assert (_rotation(copy, keys) @ own_up)[2] > math.cos(math.radians(3.0))  # its own up is world +Z
    assert "at the user's request" in copy[keys.POSE_CHANGE_KEY] and copy[keys.POSE_OUTLIER_KEY] == ""
    assert keys.FLAG_TURN_KEY not in copy
    # mesh, landmarks and markers moved together: the copy still equals its source under its transform
    transform = np.reshape(copy[keys.TRANSFORM_KEY], (4, 4))
    source = vertices(laid, evaluated=True)
    world = source @ np.array(laid.matrix_world)[:3, :3].T + np.array(laid.matrix_world)[:3, 3]
    mapped = world @ transform[:3, :3].T + transform[:3, 3]
    np.testing.assert_allclose(np.sort(mapped, axis=0), np.sort(vertices(copy), axis=0), atol=1e-4)
    turned_landmarks = np.reshape(copy[keys.LANDMARKS_KEY], (-1, 3))
    assert not np.allclose(turned_landmarks, landmarks)
    assert np.linalg.norm(vertices(markers).mean(axis=0) - marker_centre) > 1e-3
    assert turned_landmarks[:, 2].min() >= -1e-6  # floored again
    assert not bpy.ops.shapegen.turn_flagged.poll()  # nothing left to turn
    _assert_untouched(collection, before)
