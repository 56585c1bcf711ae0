"""A Blender-made mug collection (issue 14): 14 mugs modelled as an artist would, read the
way Blender's Prepare reads them.

    python bench/mugs.py [--n 14] [--seed 0] [--blend mugs.blend] [--obj-dir DIR]

Each mug is built with bmesh in the bpy module of `.venv`: a body of quads revolved from a
profile (outer wall, rim, inner wall) closed by two 32-gon caps (outside and inside
bottom), and a handle as a second part (a tube of quads swept along a C, its ends capped by
octagons and pushed into the wall). Both carry a "UVMap" (cylindrical on the body, tube
coordinates on the handle) and the material "Ceramic". Sizes, taper, wall and handle vary
per mug; each object is turned about z and placed on a row; mug 3 is mirrored (scale x −1),
as the mirrored template of the issue's report was.

`mug_meshes()` builds them in the current scene and returns what the core sees of them
(vertices, triangles) through the add-on's own reader (shapegen_addon/convert.read_object,
imported from this source tree), as plain numpy arrays with the objects' names.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
N_AROUND = 32
TUBE_AROUND = 8
TUBE_STEPS = 12
MIRRORED = 3


def _source_addon():
    """The extension package of this source tree under the name `shapegen_src` (so its
    relative `..core` imports resolve to ROOT/core)."""
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


def build_mug(name: str, rng, collection, material):
    """One mug object (module docstring) linked to `collection`."""
    import bmesh
    import bpy

    radius, height = rng.uniform(0.8, 1.2), rng.uniform(1.4, 2.4)
    taper, wall = rng.uniform(-0.2, 0.25), rng.uniform(0.10, 0.14)
    bottom = rng.uniform(0.12, 0.2)

    def outer(z):
        return radius * (1.0 + taper * (z / height - 0.5))

    bm = bmesh.new()
    heights = np.linspace(0.0, height, 6)
    outside = [_ring(bm, outer(z), z) for z in heights]
    inside = [_ring(bm, outer(z) - wall, z) for z in np.linspace(height, bottom, 6)]
    rings = outside + inside
    for low, high in zip(rings, rings[1:]):
        _bridge(bm, low, high)
    bm.faces.new(list(reversed(outside[0])))  # 32-gon under the mug, facing down
    bm.faces.new(list(reversed(inside[-1])))  # 32-gon inside, facing up into the cup

    tube = rng.uniform(0.05, 0.07)
    reach, centre = rng.uniform(0.22, 0.32) * height, rng.uniform(0.45, 0.55) * height
    sweep = np.linspace(-0.5 * np.pi, 0.5 * np.pi, TUBE_STEPS + 1)
    tube_rings = []
    for theta in sweep:
        z = centre + reach * np.sin(theta)
        base = outer(z) - 0.4 * wall
        point = np.array([base + 0.9 * reach * np.cos(theta), 0.0, z])
        normal = np.array([np.cos(theta), 0.0, np.sin(theta)])
        phis = 2 * np.pi * np.arange(TUBE_AROUND) / TUBE_AROUND
        tube_rings.append([bm.verts.new(point + tube * (np.cos(p) * normal + np.sin(p) * np.array([0.0, 1.0, 0.0])))
                           for p in phis])
    for low, high in zip(tube_rings, tube_rings[1:]):
        _bridge(bm, low, high)
    bm.faces.new(tube_rings[0])
    bm.faces.new(list(reversed(tube_rings[-1])))
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces[:])

    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    co = np.empty(3 * len(mesh.vertices))
    mesh.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    corner_vertex = np.empty(len(mesh.loops), dtype=np.int64)
    mesh.loops.foreach_get("vertex_index", corner_vertex)
    corner = co[corner_vertex]
    uv = np.stack([(np.arctan2(corner[:, 1], corner[:, 0]) / (2 * np.pi)) % 1.0, corner[:, 2] / height], axis=1)
    mesh.uv_layers.new(name="UVMap").data.foreach_set("uv", uv.astype(np.float32).ravel())
    mesh.materials.append(material)
    mesh.polygons.foreach_set("use_smooth", np.ones(len(mesh.polygons), dtype=bool))
    obj = bpy.data.objects.new(name, mesh)
    obj.rotation_euler = (0.0, 0.0, rng.uniform(0.0, 2 * np.pi))
    collection.objects.link(obj)
    return obj


def build_mugs(n: int = 14, seed: int = 0, name: str = "Mugs"):
    """`n` mug objects in a new collection `name` of the current scene, on a row along x."""
    import bpy

    collection = bpy.data.collections.new(name)
    bpy.context.scene.collection.children.link(collection)
    material = bpy.data.materials.get("Ceramic") or bpy.data.materials.new("Ceramic")
    rng = np.random.default_rng(seed)
    objects = []
    for i in range(n):
        obj = build_mug(f"mug_{i:02d}", rng, collection, material)
        obj.location = (3.0 * i, 0.0, 0.0)
        if i == MIRRORED:
            obj.scale = (-1.0, 1.0, 1.0)
        objects.append(obj)
    bpy.context.view_layer.update()
    return objects


def mug_meshes(n: int = 14, seed: int = 0) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Build the mugs and read them as Blender's Prepare does: [(name, vertices, triangles)]."""
    import bpy

    convert = _source_addon()
    objects = build_mugs(n, seed)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    read = [convert.read_object(obj, world=True, evaluated=True, depsgraph=depsgraph).mesh for obj in objects]
    return [(mesh.name, np.array(mesh.vertices), np.array(mesh.faces)) for mesh in read]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=14)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--blend", type=Path, default=None, help="save the scene as this .blend")
    parser.add_argument("--obj-dir", type=Path, default=None, help="write what the core reads as OBJ files here")
    args = parser.parse_args()
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    meshes = mug_meshes(args.n, args.seed)
    for name, vertices, faces in meshes:
        print(f"{name}: {len(vertices)} vertices, {len(faces)} triangles")
    if args.blend:
        bpy.ops.wm.save_as_mainfile(filepath=str(args.blend.resolve()))
    if args.obj_dir:
        from shapegen_core.io import write_mesh
        from shapegen_core.mesh import Mesh

        args.obj_dir.mkdir(parents=True, exist_ok=True)
        for name, vertices, faces in meshes:
            write_mesh(Mesh(vertices, faces, name=name), args.obj_dir / f"{name}.obj")
    return 0


if __name__ == "__main__":
    sys.exit(main())
