"""Mugs modelled in Blender through bpy (headless, the bpy 5.0.1 module), read as the
add-on reads objects: set (d) of bench/orientation.py and the "mugs" class of
bench/samples.py.

    python bench/blender_mugs.py [--n 14] [--seed 0] [--blend mugs.blend] [--obj-dir DIR]

One mug's mesh data (`mug_data`), built with bmesh in its own frame (+Z up, handle at +x):
a body of quads revolved from a profile (outer wall, rim, inner wall) closed by two 32-gon
caps (outside and inside bottom), and a handle as a second part (a tube of quads swept
along a C, its ends capped by octagons and pushed into the wall). Both carry a "UVMap"
(cylindrical) and the material "Ceramic". Size, taper, wall and handle vary per mug.

Objects of a collection are one of `KINDS`; all stand on +Z and face +x in world
coordinates, however they got there:

* plain objects;
* mirrored objects (scale −1 on x, mesh data built mirrored, so the world shape is the
  same mug);
* objects with a turned, scaled parent (the child's data compensates the parent's turn);
* rotated objects (object rotation, data turned back by it);
* objects with an unapplied Subdivision modifier (the evaluated mesh is read).

`model_mugs` (orientation set d) cycles through the kinds; `perturbed` (the variant with
a known subset) gives the chosen mugs an extra world map (a turn, or a mirror) after
modelling. `mug_meshes` (samples bench) is plain mugs each turned about z by
its object rotation, mug 3 mirrored (a mirrored template once broke the samples).
Objects are read by the add-on's own `convert.object_to_mesh` (evaluated, world
coordinates, welded, wound outwards), imported from this source tree.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import math
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("plain", "mirrored", "parented", "rotated", "subdivided")
N_AROUND = 32
TUBE_AROUND = 8
TUBE_STEPS = 12
MIRRORED = 3
SPACING = 4.0


def addon_convert():
    """shapegen_addon.convert of this source tree, the tree loaded as package `shapegen_src`
    (so the add-on's relative `..core` imports resolve to ROOT/core as in the extension)."""
    if "shapegen_src" not in sys.modules:
        spec = importlib.util.spec_from_file_location("shapegen_src", ROOT / "__init__.py",
                                                      submodule_search_locations=[str(ROOT)])
        module = importlib.util.module_from_spec(spec)
        sys.modules["shapegen_src"] = module
        spec.loader.exec_module(module)
    return importlib.import_module("shapegen_src.shapegen_addon.convert")


def _ring(bm, radius: float, z: float) -> list:
    angles = 2 * np.pi * np.arange(N_AROUND) / N_AROUND
    return [bm.verts.new((radius * np.cos(a), radius * np.sin(a), z)) for a in angles]


def _bridge(bm, low: list, high: list) -> None:
    n = len(low)
    for k in range(n):
        bm.faces.new((low[k], low[(k + 1) % n], high[(k + 1) % n], high[k]))


def mug_data(name: str, rng: np.random.Generator, material, closed: bool = False):
    """Mesh data of one mug in its own frame (module docstring), with UVs and `material`;
    `closed`: a solid mug, its body a tube of quads closed by n-gon caps at both ends (as an
    artist often models one), the handle at 45-60 % of its height."""
    import bmesh
    import bpy

    radius, height = rng.uniform(0.8, 1.2), rng.uniform(1.4, 2.4)
    taper, wall = rng.uniform(-0.2, 0.25), rng.uniform(0.10, 0.14)
    bottom = rng.uniform(0.12, 0.2)

    def outer(z):
        return radius * (1.0 + taper * (z / height - 0.5))

    bm = bmesh.new()
    outside = [_ring(bm, outer(z), z) for z in np.linspace(0.0, height, 6)]
    inside = [] if closed else [_ring(bm, outer(z) - wall, z) for z in np.linspace(height, bottom, 6)]
    rings = outside + inside
    for low, high in zip(rings, rings[1:]):
        _bridge(bm, low, high)
    bm.faces.new(list(reversed(outside[0])))  # 32-gon under the mug, facing down
    # 32-gon inside facing up into the cup, or the lid of a closed mug
    bm.faces.new(list(outside[-1]) if closed else list(reversed(inside[-1])))

    tube = rng.uniform(0.05, 0.07)
    reach, centre = rng.uniform(0.22, 0.32) * height, rng.uniform(0.45, 0.55) * height
    across = np.array([0.0, 1.0, 0.0])
    phis = 2 * np.pi * np.arange(TUBE_AROUND) / TUBE_AROUND
    tube_rings = []
    for theta in np.linspace(-0.5 * np.pi, 0.5 * np.pi, TUBE_STEPS + 1):
        z = centre + reach * np.sin(theta)
        point = np.array([outer(z) - 0.4 * wall + 0.9 * reach * np.cos(theta), 0.0, z])
        normal = np.array([np.cos(theta), 0.0, np.sin(theta)])
        tube_rings.append([bm.verts.new(point + tube * (np.cos(p) * normal + np.sin(p) * across)) for p in phis])
    for low, high in zip(tube_rings, tube_rings[1:]):
        _bridge(bm, low, high)
    bm.faces.new(tube_rings[0])
    bm.faces.new(list(reversed(tube_rings[-1])))
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces[:])

    data = bpy.data.meshes.new(name)
    bm.to_mesh(data)
    bm.free()
    co = np.empty(3 * len(data.vertices))
    data.vertices.foreach_get("co", co)
    corner_vertex = np.empty(len(data.loops), dtype=np.int64)
    data.loops.foreach_get("vertex_index", corner_vertex)
    corner = co.reshape(-1, 3)[corner_vertex]
    uv = np.stack([(np.arctan2(corner[:, 1], corner[:, 0]) / (2 * np.pi)) % 1.0, corner[:, 2] / height], axis=1)
    data.uv_layers.new(name="UVMap").data.foreach_set("uv", uv.astype(np.float32).ravel())
    data.materials.append(material)
    data.polygons.foreach_set("use_smooth", np.ones(len(data.polygons), dtype=bool))
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


def _local(obj, world_map: np.ndarray) -> np.ndarray:
    """The map of an object's data that acts as `world_map` after its world matrix's
    linear part L (about its origin): L⁻¹ W L."""
    import bpy

    bpy.context.view_layer.update()
    linear = np.array(obj.matrix_world)[:3, :3]
    return np.linalg.solve(linear, world_map @ linear)


def build_mugs(kinds, seed: int, perturbed: dict[int, np.ndarray] | None = None, turn_about_up: bool = False):
    """One mug object per entry of `kinds` (module docstring) in a new collection "Mugs" of
    an empty scene, on a grid. `perturbed`: index -> extra world linear map applied after
    modelling; `turn_about_up`: each object also turned about z by a random object rotation."""
    import bpy
    from mathutils import Matrix

    bpy.ops.wm.read_factory_settings(use_empty=True)
    rng = np.random.default_rng(seed)
    collection = bpy.data.collections.new("Mugs")
    bpy.context.scene.collection.children.link(collection)
    material = bpy.data.materials.new("Ceramic")
    objects = []
    for i, kind in enumerate(kinds):
        data = mug_data(f"mug_{i:02d}", rng, material)
        obj = bpy.data.objects.new(f"mug_{i:02d}", data)
        collection.objects.link(obj)
        place = np.array([SPACING * (i % 5), SPACING * (i // 5), rng.uniform(-0.5, 0.5)])
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
            obj.rotation_euler = tuple(rng.uniform(-math.pi, math.pi, 3))
            _turned(data, np.array(obj.rotation_euler.to_matrix()).T)
        elif kind == "subdivided":
            modifier = obj.modifiers.new("Subdivision", "SUBSURF")
            modifier.levels = modifier.render_levels = 1
        elif kind != "plain":
            raise ValueError(f"unknown mug kind {kind!r} (one of {KINDS})")
        if turn_about_up:
            (obj.parent or obj).rotation_euler.z += rng.uniform(0.0, 2 * math.pi)
        if perturbed and i in perturbed:
            _turned(data, _local(obj, perturbed[i]))
        (obj.parent or obj).location = tuple(place)
        objects.append(obj)
    bpy.context.view_layer.update()
    return objects


def read_mugs(objects) -> list:
    """The objects as the add-on reads them (core Mesh, world coordinates)."""
    import bpy

    convert = addon_convert()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    return [convert.object_to_mesh(obj, depsgraph=depsgraph) for obj in objects]


def model_mugs(n: int, seed: int, perturbed: dict[int, np.ndarray] | None = None):
    """Orientation set (d): (meshes as the add-on reads them, kind of each object), the
    kinds cycling through `KINDS`. `perturbed`: index -> extra world linear map."""
    kinds = [KINDS[i % len(KINDS)] for i in range(n)]
    return read_mugs(build_mugs(kinds, 5000 + seed, perturbed)), kinds


def mug_meshes(n: int = 14, seed: int = 0) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Samples bench: plain mugs turned about z, mug 3 mirrored, read as Blender's Prepare
    reads them: [(name, vertices, triangles)]."""
    kinds = ["mirrored" if i == MIRRORED else "plain" for i in range(n)]
    meshes = read_mugs(build_mugs(kinds, seed, turn_about_up=True))
    return [(mesh.name, np.array(mesh.vertices), np.array(mesh.faces)) for mesh in meshes]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=14)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--blend", type=Path, default=None, help="save the scene as this .blend")
    parser.add_argument("--obj-dir", type=Path, default=None, help="write what the core reads as OBJ files here")
    args = parser.parse_args()
    meshes = mug_meshes(args.n, args.seed)
    for name, vertices, faces in meshes:
        print(f"{name}: {len(vertices)} vertices, {len(faces)} triangles")
    if args.blend:
        import bpy

        bpy.ops.wm.save_as_mainfile(filepath=str(args.blend.resolve()))
    if args.obj_dir:
        from shapegen_core.meshes.writing import write_mesh
        from shapegen_core.meshes.mesh import Mesh

        args.obj_dir.mkdir(parents=True, exist_ok=True)
        for name, vertices, faces in meshes:
            write_mesh(Mesh(vertices, faces, name=name), args.obj_dir / f"{name}.obj")
    return 0


if __name__ == "__main__":
    sys.exit(main())
