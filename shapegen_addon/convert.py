"""Blender data <-> core data. No algorithm lives here: only conversion.

* `object_triangles`: a mesh object's vertices (world coordinates by default) and triangles
  as raw arrays, read the way the artist sees the object: the evaluated mesh (modifiers
  applied, as in the viewport) unless `evaluated=False` asks for the object's own mesh
  data. A mirroring world matrix (negative determinant) would turn the faces inside out:
  their winding is reversed on reading.
* `read_object` / `object_to_mesh`: the same as a core `Mesh` through `intake.clean_mesh`
  (welded, wound outwards, what changed in its report), plus the polygons whose winding
  the core reversed.
* `mesh_copy`: a new mesh datablock of an object as read (object-local, every layer kept);
  `world_mesh_copy`: the same in world coordinates, its winding as the core's Mesh has it
  (the prepared copies); `reverse_polygons` / `winding_to_reverse` turn a copy's polygons.
* `mesh_data_from_arrays`: a new bpy mesh from vertex / face arrays (`foreach_set`).
* `import_mesh_file`: a file through Blender's own importer (OBJ, PLY, STL, glTF), which
  keeps what the file holds (polygons, UVs, materials), after the core's damage check
  (`reading.check_mesh_file`, no intake); OFF, which Blender cannot read, through the core
  reader alone (trimesh, bundled).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import bmesh
import bpy
import numpy as np

from ..core.base.errors import MeshError, MeshFileError
from ..core.meshes.intake import clean_mesh
from ..core.meshes.mesh import Mesh

__all__ = ["ObjectTriangles", "ObjectReading", "object_triangles", "read_object", "object_to_mesh",
           "mesh_copy", "reverse_polygons", "winding_to_reverse", "world_mesh_copy", "evaluated_depsgraph",
           "mesh_data_from_arrays", "import_mesh_file", "BLENDER_IMPORTERS"]


@dataclass(frozen=True)
class ObjectTriangles:
    """Raw arrays of a mesh object as read (see `object_triangles`)."""

    vertices: np.ndarray  # (V, 3) float64, world coordinates unless read with world=False
    triangles: np.ndarray  # (F, 3) int64, reversed (corners 1 and 2 swapped) when mirrored
    polygon_sizes: np.ndarray  # (P,) corners of each polygon
    triangle_polygon: np.ndarray  # (F,) the polygon each triangle belongs to
    mirrored: bool  # read through a world matrix with negative determinant


@dataclass(frozen=True)
class ObjectReading:
    """A mesh object as a core Mesh (`read_object`), with what the Blender layer needs to
    make its prepared copy agree with it."""

    mesh: Mesh
    reversed_polygons: np.ndarray  # polygons the core re-wound (beyond a mirrored read's reversal)
    n_vertices: int  # vertices of the mesh as read, before welding


def evaluated_depsgraph(scene: bpy.types.Scene):
    """The evaluated dependency graph of `scene`, also where the context has no window or
    shows another scene (the job timer applying a job's end): the context's view layer
    when it is `scene`'s, else the scene's first."""
    context = bpy.context
    view_layer = context.view_layer if context.scene == scene and context.view_layer else scene.view_layers[0]
    with context.temp_override(scene=scene, view_layer=view_layer):
        return bpy.context.evaluated_depsgraph_get()


@contextmanager
def _mesh_as_read(obj: bpy.types.Object, evaluated: bool, depsgraph):
    """(mesh data, world matrix) of `obj`: the evaluated mesh (a temporary, freed on exit)
    or the object's own data. The world matrix comes from the evaluated depsgraph, so a
    transform set just before (and not evaluated yet) counts."""
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    evaluated_object = obj.evaluated_get(depsgraph)
    matrix = np.array(evaluated_object.matrix_world, dtype=np.float64)
    if not evaluated:
        yield obj.data, matrix
        return
    data = evaluated_object.to_mesh()
    try:
        yield data, matrix
    finally:
        evaluated_object.to_mesh_clear()


def object_triangles(obj: bpy.types.Object, world: bool = True, evaluated: bool = True,
                     depsgraph=None) -> ObjectTriangles:
    """Raw arrays of a mesh object (`ObjectTriangles`): the evaluated mesh (modifiers
    applied) unless evaluated=False, world coordinates unless world=False.

    Bulk reads only: the position attribute and, for all-triangle meshes, the corner
    vertex attribute (well under 1 ms per 100k vertices); other meshes go through
    Blender's loop triangulation (handles concave n-gons). No validation beyond "has
    vertices and faces" (the core's intake does that).
    """
    if obj.type != "MESH":
        raise MeshError(f"{obj.name}: is a {obj.type.lower()} object, not a mesh")
    with _mesh_as_read(obj, evaluated, depsgraph) as (data, matrix):
        n_vertices = len(data.vertices)
        if n_vertices == 0:
            raise MeshError(f"{obj.name}: mesh is empty (no vertices)")
        coords = np.empty(n_vertices * 3, dtype=np.float32)
        data.attributes["position"].data.foreach_get("vector", coords)
        coords = coords.reshape(-1, 3).astype(np.float64)
        n_polygons, n_loops = len(data.polygons), len(data.loops)
        if n_polygons == 0:
            raise MeshError(f"{obj.name}: mesh has no faces")
        if n_loops == 3 * n_polygons:  # every polygon is a triangle (a polygon has >= 3 corners)
            corners = np.empty(n_loops, dtype=np.int32)
            if ".corner_vert" in data.attributes:
                data.attributes[".corner_vert"].data.foreach_get("value", corners)
            else:
                data.loops.foreach_get("vertex_index", corners)
            tris = corners.reshape(-1, 3).astype(np.int64)
            sizes, tri_polygon = np.full(n_polygons, 3, dtype=np.int64), np.arange(n_polygons)
        else:
            data.calc_loop_triangles()
            tris = np.empty(len(data.loop_triangles) * 3, dtype=np.int64)
            data.loop_triangles.foreach_get("vertices", tris)
            tris = tris.reshape(-1, 3)
            tri_polygon = np.empty(len(data.loop_triangles), dtype=np.int64)
            data.loop_triangles.foreach_get("polygon_index", tri_polygon)
            sizes = np.empty(n_polygons, dtype=np.int64)
            data.polygons.foreach_get("loop_total", sizes)
    mirrored = world and bool(np.linalg.det(matrix[:3, :3]) < 0)
    if world:
        coords = coords @ matrix[:3, :3].T + matrix[:3, 3]
    if mirrored:
        tris = tris[:, [0, 2, 1]]
    return ObjectTriangles(coords, tris, sizes, tri_polygon, mirrored)


def read_object(obj: bpy.types.Object, world: bool = True, evaluated: bool = True, depsgraph=None) -> ObjectReading:
    """A mesh object as a core Mesh named after it (`object_triangles` read through
    `intake.clean_mesh`: degenerate triangles dropped, duplicates welded, faces wound
    outwards, a mirrored read said so), and the polygons whose winding the core reversed.
    The back of a double-sided sheet (a face the core dropped as its kept face's twin) is
    reversed with its kept face, so a copy keeps the object's two sides facing apart."""
    read = object_triangles(obj, world, evaluated, depsgraph)
    mesh = clean_mesh(read.vertices, read.triangles, name=obj.name, mirrored=read.mirrored,
                      polygon_of=read.triangle_polygon)
    split = read.polygon_sizes > 3
    if split.any():
        mesh = Mesh(mesh.vertices, mesh.faces, name=mesh.name, report=replace(
            mesh.report, polygons_triangulated=int(split.sum()),
            triangles_from_polygons=int((read.polygon_sizes[split] - 2).sum())))
    reversed_polygons = np.empty(0, dtype=np.int64)
    report = mesh.report
    if report.face_reversed is not None:
        source = report.face_source if report.face_source is not None else np.arange(mesh.n_faces)
        reversed_triangles = source[report.face_reversed]
        if report.twin_of is not None:  # the other side of a double-sided sheet turns with its kept side
            back_sides = report.twin_source[report.face_reversed[report.twin_of]]
            reversed_triangles = np.concatenate([reversed_triangles, back_sides])
        reversed_polygons = np.unique(read.triangle_polygon[reversed_triangles])
    return ObjectReading(mesh, reversed_polygons, len(read.vertices))


def object_to_mesh(obj: bpy.types.Object, world: bool = True, evaluated: bool = True, depsgraph=None) -> Mesh:
    """`read_object`'s core Mesh: what the core sees of a mesh object."""
    return read_object(obj, world, evaluated, depsgraph).mesh


def mesh_copy(obj: bpy.types.Object, evaluated: bool = True, depsgraph=None) -> bpy.types.Mesh:
    """A new mesh datablock of `obj` as read, object-local: the evaluated mesh (modifiers
    applied, every data layer kept) or a copy of its own data; polygons, UV maps,
    materials, sharp edges, smooth flags and vertex weights come with it."""
    if not evaluated:
        return obj.data.copy()
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    return bpy.data.meshes.new_from_object(obj.evaluated_get(depsgraph), preserve_all_data_layers=True,
                                           depsgraph=depsgraph)


def reverse_polygons(data: bpy.types.Mesh, flip: np.ndarray) -> None:
    """Reverse the winding of the polygons where `flip` (P,) is True (their corners and
    corner data such as UVs, through bmesh)."""
    if not flip.any():
        return
    editable = bmesh.new()
    editable.from_mesh(data)
    editable.faces.ensure_lookup_table()
    bmesh.ops.reverse_faces(editable, faces=[editable.faces[i] for i in np.flatnonzero(flip)])
    editable.to_mesh(data)
    editable.free()


def winding_to_reverse(n_polygons: int, mirrored: bool, reversed_polygons=()) -> np.ndarray:
    """(P,) bool: the polygons to reverse so a copy is wound like its core Mesh: every
    polygon when read through a mirroring matrix, xor `reversed_polygons` (`read_object`'s)."""
    flip = np.zeros(n_polygons, dtype=bool)
    flip[np.asarray(reversed_polygons, dtype=np.int64)] = True
    return ~flip if mirrored else flip


def world_mesh_copy(obj: bpy.types.Object, name: str, evaluated: bool = True, depsgraph=None,
                    reversed_polygons=()) -> bpy.types.Mesh:
    """A new mesh datablock of `obj` as read (`mesh_copy`) in world coordinates, wound like
    its core Mesh: every polygon reversed when the world matrix mirrors, and
    `reversed_polygons` (`read_object`'s)."""
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    data = mesh_copy(obj, evaluated, depsgraph)
    data.name = name
    matrix = obj.evaluated_get(depsgraph).matrix_world.copy()
    data.transform(matrix)
    reverse_polygons(data, winding_to_reverse(len(data.polygons), matrix.to_3x3().determinant() < 0,
                                              reversed_polygons))
    return data


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
    from ..core.meshes.reading import check_mesh_file, read_mesh

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".off" or suffix not in BLENDER_IMPORTERS:  # the core's read is the only one
        mesh = read_mesh(path)
        obj = bpy.data.objects.new(path.stem, mesh_data_from_arrays(path.stem, mesh.vertices, mesh.faces))
        collection.objects.link(obj)
        return obj
    # Blender's importers accept damaged files silently (a NaN or a face past the last vertex
    # read as something else), so the core checks the file first and refuses what
    # `shapegen prepare` refuses as damage, naming it; intake's cleaning, the costly part of
    # the core's read, is left to Prepare, which cleans the object as the artist sees it
    check_mesh_file(path)

    before = set(bpy.data.objects)
    try:
        BLENDER_IMPORTERS[suffix](str(path))
    except Exception as exc:  # importers raise RuntimeError, and others on damage the core let through
        for o in [o for o in bpy.data.objects if o not in before]:
            bpy.data.objects.remove(o)
        raise MeshFileError(f"{path}: Blender's importer failed ({type(exc).__name__}: {str(exc).strip()})") from None
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
