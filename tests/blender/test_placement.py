"""New objects go beside the work already in the scene, never on top of it."""

from __future__ import annotations

import bpy
import numpy as np
from conftest import add_vase_collection, load_model


def world_box(obj) -> np.ndarray:
    """(2, 3) world-space box of the evaluated object (modifiers applied)."""
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    corners = np.array([corner[:] for corner in evaluated.bound_box])
    matrix = np.array(evaluated.matrix_world)
    points = corners @ matrix[:3, :3].T + matrix[:3, 3]
    return np.stack([points.min(axis=0), points.max(axis=0)])


def overlap(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(a[0] < b[1]) and np.all(b[0] < a[1]))


def add_box(name: str, centre, size: float, grown: bool = False) -> bpy.types.Object:
    """A cube mesh object of side `size` at `centre` (a Displace modifier grows it when asked)."""
    half = 0.5 * size
    corners = [(x, y, z) for x in (-half, half) for y in (-half, half) for z in (-half, half)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(corners, [], faces)
    obj = bpy.data.objects.new(name, mesh)
    obj.location = centre
    if grown:  # the evaluated box is larger than the mesh's own
        obj.modifiers.new("grow", "DISPLACE").strength = half
    bpy.context.scene.collection.objects.link(obj)
    return obj


class Scene:
    """The scene's objects before an operator, to check that what it adds is clear of them."""

    def __init__(self):
        self.boxes = {}
        self.snapshot()

    def snapshot(self) -> None:
        self.boxes = {o.name: world_box(o) for o in bpy.context.scene.objects if o.type == "MESH"}

    def new_objects(self) -> list:
        return [o for o in bpy.context.scene.objects if o.name not in self.boxes and o.type == "MESH"]

    def assert_clear(self, operator: str) -> list:
        """Every object added since the snapshot is clear of every object that was there."""
        made = self.new_objects()
        assert made, operator
        for obj in made:
            box = world_box(obj)
            hits = [name for name, other in self.boxes.items() if overlap(box, other)]
            assert not hits, f"{operator}: '{obj.name}' overlaps {hits}"
        self.snapshot()
        return made


def test_every_operator_puts_its_objects_beside_the_existing_ones(extension, model_files):
    scene = bpy.context.scene
    scene.cursor.location = (1.5, 0.5, 0.0)
    add_box("at origin", (0.0, 0.0, 0.0), 3.0)
    add_box("at cursor", (1.5, 0.5, 0.5), 1.0, grown=True)
    add_vase_collection(extension)                       # the training vases, also near the origin
    state = Scene()
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    state.assert_clear("prepare")

    load_model("ppca", model_files)
    assert bpy.ops.shapegen.sample(count=4) == {"FINISHED"}
    first = state.assert_clear("sample")
    assert bpy.ops.shapegen.sample(count=3, seed=50) == {"FINISHED"}
    second = state.assert_clear("second sample")          # clear of the first batch too
    assert len(first) == 4 and len(second) == 3

    settings = scene.shapegen
    settings.generate.interpolate_a = bpy.data.objects["vase_000"]
    settings.generate.interpolate_b = bpy.data.objects["vase_004"]
    assert bpy.ops.shapegen.interpolate(steps=3, mode="OBJECTS") == {"FINISHED"}
    state.assert_clear("interpolate (objects)")
    assert bpy.ops.shapegen.interpolate(steps=3, mode="SHAPE_KEYS") == {"FINISHED"}
    state.assert_clear("interpolate (morph)")
    assert bpy.ops.shapegen.modes_to_shape_keys() == {"FINISHED"}
    state.assert_clear("modes to shape keys")

    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    before_explore = dict(state.boxes)
    state.assert_clear("explore")
    assert bpy.ops.shapegen.explore_randomise() == {"FINISHED"}
    assert bpy.ops.shapegen.explore_bake() == {"FINISHED"}
    state.boxes = before_explore                        # the baked object is the former live one
    baked = state.assert_clear("bake")
    assert [o.name for o in baked] == ["vases_ppca baked"]
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    state.assert_clear("explore after bake")


def test_new_objects_start_at_the_cursor_when_it_is_free(extension, model_files):
    scene = bpy.context.scene
    scene.cursor.location = (40.0, -7.0, 2.0)
    add_box("elsewhere", (0.0, 0.0, 0.0), 2.0)
    load_model("gplvm", model_files)
    assert bpy.ops.shapegen.sample(count=3, seed=4) == {"FINISHED"}
    samples = sorted(bpy.data.collections["ShapeGen Samples"].objects, key=lambda o: o["shapegen_seed"])
    np.testing.assert_allclose(samples[0].location[:], (40.0, -7.0, 2.0), atol=1e-6)
    hidden = add_box("hidden", (40.0, -7.0, 2.0), 50.0)
    hidden.hide_set(True)                               # hidden objects take no room
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    np.testing.assert_allclose(scene.shapegen.live_object.location[1:], (-7.0, 2.0), atol=1e-6)
    assert not overlap(world_box(scene.shapegen.live_object), world_box(samples[-1]))
