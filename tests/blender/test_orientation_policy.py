"""Prepare keeps what it is given on a mug scene as an artist models it: solid
mugs (quad walls, n-gon caps at both ends, walls tapering inward on some and outward on
others, a handle as a second part: bench/blender_mugs.py `mug_data(closed=True)`), one
with a Subdivision modifier, one parented to a turned, scaled empty, one with an
unapplied rotation and one with an unapplied non-uniform scale, all upright in the world.
The real Prepare operator turns none of them; a mug laid on its side on the floor by hand
is flagged and left as given (it rests where its author put it), and Turn Flagged stands
it on its axis; with open mugs, one turned over by hand and kept is flagged (its hollow opens
downwards) and Turn Flagged stands it up in one undoable step; the artist's objects are
never changed."""

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


def _solid_mugs(count: int = 10, closed: bool = True) -> bpy.types.Collection:
    """The scene: `count` mugs upright in the world (solid, or open at the top), the kinds
    of KINDS in turn."""
    builder = _mug_builder()
    rng = np.random.default_rng(11)
    material = bpy.data.materials.new("Ceramic")
    collection = bpy.data.collections.new("mugs")
    bpy.context.scene.collection.children.link(collection)
    for i in range(count):
        data = builder.mug_data(f"mug_{i}", rng, material, closed=closed)
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
    settings.prepare.n_landmarks = 60
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


def test_a_mug_laid_on_its_side_on_the_floor_is_flagged_and_turn_flagged_stands_it(extension):
    """Laid on its side on the ground plane by hand, where the other mugs stand: the
    costs ask to stand it, but it rests on the floor the collection shares, where its
    author put it, so it is flagged and left as given; Turn Flagged stands it on its
    axis in one step. The other mugs are neither turned nor flagged."""
    keys = addon_module(extension, "shapegen_addon.keys")
    collection = _solid_mugs()
    laid = bpy.data.objects["mug_5"]  # a plain object
    laid.rotation_euler = (math.pi / 2, 0.0, 0.0)  # its own up now along world -y
    bpy.context.view_layer.update()
    world = vertices(laid) @ np.array(laid.matrix_world)[:3, :3].T + np.array(laid.matrix_world)[:3, 3]
    laid.location.z -= world[:, 2].min()  # lying on the floor
    bpy.context.view_layer.update()
    own_up = np.array(laid.matrix_world.to_3x3().normalized()) @ [0.0, 0.0, 1.0]
    before = _snapshot(collection)
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    copies = _copies(extension)
    copy = copies["mug_5"]
    assert copy[keys.POSE_CHANGE_KEY] == "", copy[keys.POSE_CHANGE_KEY]
    assert copy[keys.POSE_OUTLIER_KEY].startswith("may be on its side") and "where its author put it" in \
        copy[keys.POSE_OUTLIER_KEY], copy[keys.POSE_OUTLIER_KEY]
    assert abs((_rotation(copy, keys) @ own_up)[2]) < 1e-6  # left lying
    for name, other in copies.items():
        if name != "mug_5":
            assert other[keys.POSE_CHANGE_KEY] == "" and other.get(keys.POSE_OUTLIER_KEY, "") == "", name
    assert bpy.ops.shapegen.turn_flagged() == {"FINISHED"}
    copy = _copies(extension)["mug_5"]
    assert abs((_rotation(copy, keys) @ own_up)[2]) > math.cos(math.radians(3.0))  # its axis is up
    assert "at the user's request" in copy[keys.POSE_CHANGE_KEY] and copy[keys.POSE_OUTLIER_KEY] == ""
    _assert_untouched(collection, before)


def test_a_mug_turned_over_by_hand_is_flagged_and_turn_flagged_stands_it_up(extension):
    """Open mugs: a mug turned over by hand and kept (Keep Pose) is flagged, its hollow
    opening downwards; Turn Flagged stands it up in one undoable step, its prepared copy,
    landmarks and markers moving together, the artist's objects unchanged."""
    keys = addon_module(extension, "shapegen_addon.keys")
    collection = _solid_mugs(closed=False)
    turned = bpy.data.objects["mug_5"]
    turned.rotation_euler = (math.pi, 0.0, 0.0)
    turned[keys.KEEP_POSE_KEY] = True
    bpy.context.view_layer.update()
    own_up = np.array(turned.matrix_world.to_3x3().normalized()) @ [0.0, 0.0, 1.0]
    before = _snapshot(collection)
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    copy = _copies(extension)["mug_5"]
    assert copy[keys.POSE_CHANGE_KEY] == ""
    assert copy[keys.POSE_OUTLIER_KEY].startswith("may be upside down: its hollow opens downwards"), \
        copy[keys.POSE_OUTLIER_KEY]
    assert (_rotation(copy, keys) @ own_up)[2] < -math.cos(math.radians(1.0))
    landmarks = np.array(copy[keys.LANDMARKS_KEY], dtype=np.float64).reshape(-1, 3)
    markers = next(c for c in copy.children if c.type == "MESH")
    marker_centre = vertices(markers).mean(axis=0)

    assert "UNDO" in bpy.types.SHAPEGEN_OT_turn_flagged.bl_options
    assert bpy.ops.shapegen.turn_flagged() == {"FINISHED"}
    copy = _copies(extension)["mug_5"]
    assert (_rotation(copy, keys) @ own_up)[2] > math.cos(math.radians(3.0))  # its own up is world +Z
    assert "at the user's request" in copy[keys.POSE_CHANGE_KEY] and copy[keys.POSE_OUTLIER_KEY] == ""
    assert keys.FLAG_TURN_KEY not in copy
    # mesh and landmarks moved together: the copy still equals its source under its transform
    transform = np.reshape(copy[keys.TRANSFORM_KEY], (4, 4))
    world = vertices(turned, evaluated=True) @ np.array(turned.matrix_world)[:3, :3].T \
        + np.array(turned.matrix_world)[:3, 3]
    mapped = world @ transform[:3, :3].T + transform[:3, 3]
    np.testing.assert_allclose(np.sort(mapped, axis=0), np.sort(vertices(copy), axis=0), atol=1e-4)
    turned_landmarks = np.array(copy[keys.LANDMARKS_KEY], dtype=np.float64).reshape(-1, 3)
    assert not np.allclose(turned_landmarks, landmarks) and turned_landmarks[:, 2].min() >= -1e-6
    assert np.linalg.norm(vertices(markers).mean(axis=0) - marker_centre) > 1e-3  # the markers came along
    assert not bpy.ops.shapegen.turn_flagged.poll()  # nothing left to turn
    _assert_untouched(collection, before)
