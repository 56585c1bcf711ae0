"""Blender data <-> core data. No algorithm lives here: only conversion.

* `object_to_mesh`: a mesh object's triangles in world coordinates as a core `Mesh`
  (vertex order kept, `foreach_get`, Blender's own loop triangulation);
  `object_triangles`: the same as raw arrays, without the core's validation.
* `mesh_data_from_arrays`: a new bpy mesh from vertex / face arrays (`foreach_set`).
* `import_mesh_file`: a file through Blender's own importer (OBJ, PLY, STL, glTF); OFF,
  which Blender cannot read, through the core reader (trimesh, bundled).
"""

from __future__ import annotations

from pathlib import Path

import bpy
import numpy as np

from ..core.errors import MeshError, MeshFileError
from ..core.mesh import Mesh, MeshReport

__all__ = ["object_to_mesh", "object_triangles", "mesh_data_from_arrays", "import_mesh_file", "BLENDER_IMPORTERS"]


def object_triangles(obj: bpy.types.Object, world: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw arrays of a mesh object: vertices (V, 3) float64 (world coordinates unless
    world=False), triangles (F, 3) int64 and the polygons' corner counts (P,).

    Bulk reads only: the position attribute and, for all-triangle meshes, the corner
    vertex attribute (well under 1 ms per 100k vertices); other meshes go through
    Blender's loop triangulation (handles concave n-gons). No validation beyond "has
    vertices and faces" (the core's Mesh does that).
    """
    if obj.type != "MESH":
        raise MeshError(f"{obj.name}: is a {obj.type.lower()} object, not a mesh")
    data = obj.data
    n_vertices = len(data.vertices)
    if n_vertices == 0:
        raise MeshError(f"{obj.name}: mesh is empty (no vertices)")
    coords = np.empty(n_vertices * 3, dtype=np.float32)
    data.attributes["position"].data.foreach_get("vector", coords)
    coords = coords.reshape(-1, 3).astype(np.float64)
    if world:
        matrix = np.array(obj.matrix_world, dtype=np.float64)
        coords = coords @ matrix[:3, :3].T + matrix[:3, 3]
    n_polygons, n_loops = len(data.polygons), len(data.loops)
    if n_polygons == 0:
        raise MeshError(f"{obj.name}: mesh has no faces")
    if n_loops == 3 * n_polygons:  # every polygon is a triangle (a polygon has >= 3 corners)
        corners = np.empty(n_loops, dtype=np.int32)
        if ".corner_vert" in data.attributes:
            data.attributes[".corner_vert"].data.foreach_get("value", corners)
        else:
            data.loops.foreach_get("vertex_index", corners)
        return coords, corners.reshape(-1, 3).astype(np.int64), np.full(n_polygons, 3, dtype=np.int64)
    data.calc_loop_triangles()
    tris = np.empty(len(data.loop_triangles) * 3, dtype=np.int64)
    data.loop_triangles.foreach_get("vertices", tris)
    loop_totals = np.empty(n_polygons, dtype=np.int64)
    data.polygons.foreach_get("loop_total", loop_totals)
    return coords, tris.reshape(-1, 3), loop_totals


def object_to_mesh(obj: bpy.types.Object, world: bool = True) -> Mesh:
    """Triangles of a mesh object as a core Mesh named after the object.

    Uses the object's own mesh data (modifiers are not applied), so vertex i of the
    Blender mesh is vertex i of the result. Polygons are triangulated by Blender's loop
    triangulation (handles concave n-gons); degenerate triangles are dropped and counted.
    """
    coords, tris, loop_totals = object_triangles(obj, world)
    split = loop_totals > 3
    mesh = Mesh.from_polygons(coords, tris, name=obj.name)
    if split.any():
        report = MeshReport(int(split.sum()), int((loop_totals[split] - 2).sum()),
                            mesh.report.degenerate_faces_dropped)
        mesh = Mesh(mesh.vertices, mesh.faces, name=mesh.name, report=report)
    return mesh


def mesh_data_from_arrays(name: str, vertices: np.ndarray, faces: np.ndarray) -> bpy.types.Mesh:
    """A new bpy mesh datablock with the given vertices (V, 3) and triangles (F, 3)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    data = bpy.data.meshes.new(name)
    data.vertices.add(len(vertices))
    data.vertices.foreach_set("co", vertices.ravel())
    if len(faces):
        data.loops.add(faces.size)
        data.loops.foreach_set("vertex_index", faces.ravel())
        data.polygons.add(len(faces))
        data.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
    data.update(calc_edges=True)
    data.validate(verbose=False)
    return data


def _import_obj(path: str) -> None:
    # identity axes: objects hold the file's own coordinates, exactly as the CLI reads them
    bpy.ops.wm.obj_import(filepath=path, forward_axis="Y", up_axis="Z",
                          use_split_objects=False, use_split_groups=False)


def _import_ply(path: str) -> None:
    bpy.ops.wm.ply_import(filepath=path, forward_axis="Y", up_axis="Z", merge_verts=False)


def _import_stl(path: str) -> None:
    bpy.ops.wm.stl_import(filepath=path, forward_axis="Y", up_axis="Z")


def _import_gltf(path: str) -> None:
    bpy.ops.import_scene.gltf(filepath=path)


BLENDER_IMPORTERS = {
    ".obj": _import_obj,
    ".ply": _import_ply,
    ".stl": _import_stl,
    ".glb": _import_gltf,
    ".gltf": _import_gltf,
}


def import_mesh_file(path: Path, collection: bpy.types.Collection) -> bpy.types.Object:
    """Import one file as ONE mesh object named after the file, linked to `collection`.

    Raises MeshFileError naming the file when the importer fails or yields no mesh.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".off" or suffix not in BLENDER_IMPORTERS:
        from ..core.io import read_mesh

        mesh = read_mesh(path)
        obj = bpy.data.objects.new(path.stem, mesh_data_from_arrays(path.stem, mesh.vertices, mesh.faces))
        collection.objects.link(obj)
        return obj

    before = set(bpy.data.objects)
    try:
        BLENDER_IMPORTERS[suffix](str(path))
    except RuntimeError as exc:
        raise MeshFileError(f"{path}: Blender's importer failed ({str(exc).strip()})") from None
    new_objects = [o for o in bpy.data.objects if o not in before]
    meshes = [o for o in new_objects if o.type == "MESH"]
    others = [o for o in new_objects if o.type != "MESH"]
    if not meshes:
        for o in new_objects:
            bpy.data.objects.remove(o)
        raise MeshFileError(f"{path}: contains no mesh geometry")
    if len(meshes) > 1:
        # several parts (e.g. a glTF scene): join them into one object, world transforms applied
        with bpy.context.temp_override(active_object=meshes[0], selected_editable_objects=meshes,
                                       selected_objects=meshes):
            bpy.ops.object.join()
    obj = meshes[0]
    for o in others:
        bpy.data.objects.remove(o)
    if len(obj.data.vertices) == 0:
        bpy.data.objects.remove(obj)
        raise MeshFileError(f"{path}: file is empty or holds no vertices")
    # bake the importer's object transform into the data so the object is at identity
    obj.data.transform(obj.matrix_world)
    obj.matrix_world.identity()
    obj.parent = None
    for c in list(obj.users_collection):
        c.objects.unlink(obj)
    collection.objects.link(obj)
    obj.name = path.stem
    obj.data.name = path.stem
    return obj
