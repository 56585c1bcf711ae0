"""Set (d) of bench/orientation.py: a collection of mugs modelled in Blender through bpy
(headless, the bpy 5.0.1 module), read as the add-on reads objects.

Every mug is a body of quads (a cylinder of 10-20 segments, radius and height varied,
its top inset and pushed down into a cavity, so the cavity floor and the bottom are
n-gons) and a handle as a second part of the same mesh (a half ring of quads at +x). All
stand on +Z and face +x in world coordinates, however they got there:

* plain objects;
* mirrored objects (scale −1 on x, mesh data built mirrored, so the world shape is the
  same mug);
* objects with a turned, scaled parent (the child's data compensates the parent's turn);
* rotated objects (object rotation, data turned back by it);
* objects with an unapplied Subdivision modifier (the evaluated mesh is read).

`perturbed` (the variant with a known subset): the chosen mugs get an extra world turn
(upside down, on their side, a quarter or three-eighths turn about up) or a mirror across
the yz plane after modelling; the turns are returned so the benchmark knows each mug's
true pose. Objects are read by the add-on's own `convert.object_to_mesh` (evaluated,
world coordinates, welded, wound outwards), imported from the source tree.
"""

from __future__ import annotations

import importlib
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("plain", "mirrored", "parented", "rotated", "subdivided")


def _addon_convert():
    """shapegen_addon.convert from the source tree (a package holding links to core/ and
    shapegen_addon/, so its relative imports of the core resolve as in the extension)."""
    if "sgbench.shapegen_addon.convert" in sys.modules:
        return sys.modules["sgbench.shapegen_addon.convert"]
    folder = Path(tempfile.mkdtemp(prefix="shapegen_bench_")) / "sgbench"
    folder.mkdir()
    (folder / "__init__.py").write_text("")
    (folder / "core").symlink_to(ROOT / "core")
    (folder / "shapegen_addon").symlink_to(ROOT / "shapegen_addon")
    sys.path.insert(0, str(folder.parent))
    return importlib.import_module("sgbench.shapegen_addon.convert")


def _mug_data(name: str, rng: np.random.Generator):
    """Mesh data of one mug in its own frame (+Z up, handle at +x), built with bmesh."""
    import bmesh
    import bpy

    segments = int(rng.integers(10, 21)) // 2 * 2
    radius, height = rng.uniform(0.35, 0.55), rng.uniform(0.8, 1.3)
    wall, floor = rng.uniform(0.04, 0.08), rng.uniform(0.06, 0.12)
    bm = bmesh.new()
    bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=segments, radius1=radius, radius2=radius,
                          depth=height)
    bmesh.ops.translate(bm, verts=bm.verts, vec=(0.0, 0.0, height / 2))
    bm.faces.ensure_lookup_table()
    top = max(bm.faces, key=lambda f: f.calc_center_median().z)
    inset = bmesh.ops.inset_individual(bm, faces=[top], thickness=wall)
    bmesh.ops.translate(bm, verts=top.verts, vec=(0.0, 0.0, -(height - floor)))
    del inset
    # handle: a half ring of quads (tube of `sides` around a semicircle) at +x
    ring, sides = rng.uniform(0.22, 0.35) * height, 6
    tube = rng.uniform(0.035, 0.06)
    centre = np.array([radius - 0.02, 0.0, height * rng.uniform(0.45, 0.6)])
    steps = 9
    rows = []
    for s in range(steps):
        angle = -math.pi / 2 + math.pi * s / (steps - 1)
        axis_point = centre + ring * np.array([math.cos(angle), 0.0, math.sin(angle)])
        radial = np.array([math.cos(angle), 0.0, math.sin(angle)])
        circle = [axis_point + tube * (math.cos(t) * radial + math.sin(t) * np.array([0.0, 1.0, 0.0]))
                  for t in np.linspace(0, 2 * math.pi, sides, endpoint=False)]
        rows.append([bm.verts.new(tuple(point)) for point in circle])
    for a, b in zip(rows[:-1], rows[1:]):
        for k in range(sides):
            bm.faces.new((a[k], a[(k + 1) % sides], b[(k + 1) % sides], b[k]))
    for end in (rows[0], rows[-1][::-1]):
        bm.faces.new(end[::-1])  # n-gon ends close the tube
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces)
    data = bpy.data.meshes.new(name)
    bm.to_mesh(data)
    bm.free()
    return data


def _turned(data, matrix: np.ndarray) -> None:
    """Apply a 3×3 linear map to mesh data in place (flipping polygons if it mirrors)."""
    import bmesh
    from mathutils import Matrix

    bm = bmesh.new()
    bm.from_mesh(data)
    full = np.eye(4)
    full[:3, :3] = matrix
    bmesh.ops.transform(bm, matrix=Matrix(full.tolist()), verts=bm.verts)
    if np.linalg.det(matrix) < 0:
        bmesh.ops.reverse_faces(bm, faces=bm.faces)
    bm.to_mesh(data)
    bm.free()


def model_mugs(n: int, seed: int, perturbed: dict[int, np.ndarray] | None = None):
    """(meshes as the add-on reads them, kind of each object). `perturbed`: index ->
    extra world linear map (a turn, or a mirror) applied after modelling."""
    import bpy
    from mathutils import Matrix

    bpy.ops.wm.read_factory_settings(use_empty=True)
    convert = _addon_convert()
    rng = np.random.default_rng(5000 + seed)
    collection = bpy.data.collections.new("mugs")
    bpy.context.scene.collection.children.link(collection)
    objects, kinds = [], []
    for i in range(n):
        kind = KINDS[i % len(KINDS)]
        data = _mug_data(f"mug_{i:02d}", rng)
        obj = bpy.data.objects.new(f"mug_{i:02d}", data)
        collection.objects.link(obj)
        place = np.array([3.0 * (i % 5), 3.0 * (i // 5), rng.uniform(-0.5, 0.5)])
        if kind == "mirrored":
            _turned(data, np.diag([-1.0, 1.0, 1.0]))
            obj.scale = (-1.0, 1.0, 1.0)
        elif kind == "parented":
            parent = bpy.data.objects.new(f"holder_{i:02d}", None)
            bpy.context.scene.collection.objects.link(parent)
            turn = rng.uniform(-math.pi, math.pi)
            parent.rotation_euler, parent.scale = (0.0, 0.0, turn), (1.5, 1.5, 1.5)
            obj.parent = parent
            _turned(data, np.array(Matrix.Rotation(turn, 3, "Z")).T)  # data turned back by the parent's turn
        elif kind == "rotated":
            euler = rng.uniform(-math.pi, math.pi, 3)
            obj.rotation_euler = tuple(euler)
            _turned(data, np.array(obj.rotation_euler.to_matrix()).T)
        elif kind == "subdivided":
            modifier = obj.modifiers.new("Subdivision", "SUBSURF")
            modifier.levels = modifier.render_levels = 1
        if perturbed and i in perturbed:
            _turned(data, _local(obj, perturbed[i]))
        obj.location = tuple(place) if obj.parent is None else (0.0, 0.0, 0.0)
        if obj.parent is not None:
            obj.parent.location = tuple(place)
        objects.append(obj)
        kinds.append(kind)
    bpy.context.view_layer.update()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    return [convert.object_to_mesh(obj, depsgraph=depsgraph) for obj in objects], kinds


def _local(obj, world_map: np.ndarray) -> np.ndarray:
    """The map of an object's data that acts as `world_map` after its world matrix's
    linear part L (about its origin): L⁻¹ W L."""
    import bpy

    bpy.context.view_layer.update()
    linear = np.array(obj.matrix_world)[:3, :3]
    return np.linalg.solve(linear, world_map @ linear)
