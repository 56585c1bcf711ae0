"""Raw mesh data -> a clean `Mesh`, the way every reader hands meshes to the core (files:
reading.read_mesh; Blender: convert.object_to_mesh, and meshset.load_mesh_set in the worker):

1. `Mesh.from_polygons`: fan-triangulate polygons, drop degenerate triangles;
2. `weld_vertices`: merge coincident vertices. STL files and other triangle soups give
   every triangle its own three corners; welded, smoothing, the closedness test and the
   written files see one connected surface instead of loose triangles;
3. `drop_twin_faces`: a face on the same three (welded) vertices as an earlier one is the
   other side of a double-sided surface (CAD files store every sheet twice, wound opposite
   ways) or a plain duplicate; one surface is kept, so every edge of a double-sided sheet
   has two faces again instead of four, and the dropped sides are recorded (`twin_source`,
   `twin_of`) so a caller can map them back to the file's faces;
4. `internal_faces`: a sheet inside a closed volume (the wall between two cells of a CAD
   model, met by the outer surface along edges of three or more faces) is dropped from the
   surface and counted: Prepare, correspondence and the closedness test see the outside;
5. `loose_slivers`: faces thinner than SLIVER_RATIO of their longest edge (CAD tessellators
   leave needles along trimmed edges; zero-area faces went in step 1) are dropped where
   that opens no hole (on a border or a non-manifold edge) and counted; the others are
   counted and kept;
6. `orient_faces`: wind every face like its neighbours and every connected part outwards
   (files wound inwards or inconsistently); a non-orientable part (no winding makes all
   its neighbours agree: a Möbius-like band, a sheet stitched to itself with a twist) is
   wound face by face, each face towards the side of it that is outside (`outside_sides`).
7. `separate_parts`: the surface's connected parts are counted and the largest one's share
   of the area recorded (labels, decals, a bouquet in a vase): they stay in the mesh and
   are deformed with it; the report names them.

Each step counts what it changed in `Mesh.report`, which also keeps the maps back to the
input (`vertex_map`, `face_source`, `face_reversed`). A clean input comes out as it went
in: the same vertices in the same order and the same faces. Steps 4, 6 and 7, which side of
the surface is outside, are winding.py's.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..base.errors import MeshError
from .mesh import FACE_CHUNK, SLIVER_RATIO, Mesh, cross_rows
from .winding import faces_per_edge, internal_faces, orient_faces, separate_parts

__all__ = ["clean_mesh", "weld_vertices", "sliver_faces", "loose_slivers", "drop_twin_faces", "WELD_RTOL",
           "SLIVER_RATIO"]

#: Vertices closer than this fraction of the bounding-box diagonal are one vertex. The
#: corners a soup repeats are bitwise equal (STL stores float32 and every writer prints the
#: same float for the same corner), so exact equality would do for them; the tolerance also
#: merges copies of a point that reached the file through different float64 arithmetic
#: (rounding ~1e-16 of the coordinates). It stays far below what any model distinguishes:
#: float32, the precision of STL, PLY, glTF and Blender, resolves ~6e-8 of a coordinate.
WELD_RTOL = 1e-9


#: Passes of `loose_slivers`: a fan of slivers along a border loses one layer per pass.
SLIVER_PEELS = 8


def clean_mesh(vertices: np.ndarray, polygons, name: str = "", mirrored: bool = False,
               polygon_of: np.ndarray | None = None) -> Mesh:
    """A valid, welded, outward-wound Mesh from raw vertices and polygons (module docstring).

    `mirrored` records that the caller already reversed every polygon because it read them
    through a mirroring transform (a Blender object with negative scale); the report says
    so. `polygon_of` (T,), when the input triangles were cut from polygons (Blender's
    n-gons), is the polygon of each: a polygon on the vertices of an earlier one is a twin
    however the two were triangulated. Raises MeshError naming `name` when nothing usable
    remains.
    """
    label = name or "mesh"
    mesh = Mesh.from_polygons(vertices, polygons, name=name)
    welded, vertex_map = weld_vertices(mesh.vertices)
    welded_away = len(vertex_map) - len(welded)
    faces, source = mesh.faces, mesh.report.face_source
    collapsed = np.zeros(len(faces), dtype=bool)
    if welded_away:  # nothing welded: from_polygons already dropped faces with a repeated corner
        faces = vertex_map[faces].astype(mesh.faces.dtype)
        collapsed = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 2] == faces[:, 0])
        if collapsed.all():
            raise MeshError(f"{label}: every face is degenerate (its corners coincide once duplicates are welded)")
        if collapsed.any():
            source = np.arange(mesh.n_faces) if source is None else source
            faces, source = faces[~collapsed], source[~collapsed]
    kept, twin_of = drop_twin_faces(faces, None if polygon_of is None else np.asarray(polygon_of)[
        np.arange(len(faces)) if source is None else source])
    source = np.arange(len(faces)) if source is None else source
    twin_source = np.empty(0, dtype=np.int64)
    if len(twin_of):
        dropped = np.ones(len(faces), dtype=bool)
        dropped[kept] = False
        twin_source, faces, source = source[dropped], faces[kept], source[kept]
    n_faces = len(faces) + len(twin_of)
    faces, source, twin_source, twin_of = _without(internal_faces(welded, faces), faces, source,
                                                   twin_source, twin_of)
    n_inside = n_faces - len(faces) - len(twin_of)  # with their other sides
    n_thin = 0
    for _ in range(SLIVER_PEELS):  # a fan of slivers along a border comes off one layer per pass
        loose, thin = loose_slivers(welded, faces)
        if not loose.any() or loose.all():  # none loose, or none would be left
            break
        n_thin += int(loose.sum())
        faces, source, twin_source, twin_of = _without(loose, faces, source, twin_source, twin_of)
    else:
        thin = sliver_faces(welded, faces)
    if len(source) == mesh.n_faces and np.array_equal(source, np.arange(mesh.n_faces)):
        source = None
    faces, reversed_faces, counts = orient_faces(welded, faces)
    n_parts, largest_share = separate_parts(welded, faces)
    report = replace(
        mesh.report,
        degenerate_faces_dropped=mesh.report.degenerate_faces_dropped + int(collapsed.sum()),
        vertices_welded=welded_away, mirrored=bool(mirrored), **counts,
        sliver_faces_dropped=n_thin, sliver_faces_kept=int(thin.sum()), internal_faces_dropped=n_inside,
        twin_faces_dropped=len(twin_of), separate_parts=n_parts, largest_part_share=largest_share,
        vertex_map=vertex_map if welded_away else None,
        face_source=source,
        face_reversed=reversed_faces if reversed_faces.any() else None,
        twin_source=twin_source if len(twin_of) else None, twin_of=twin_of if len(twin_of) else None,
    )
    return Mesh(welded, faces, name=name, report=report)


def weld_vertices(vertices: np.ndarray, rtol: float = WELD_RTOL) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices closer than `rtol` × the bounding-box diagonal: every close pair (a
    k-d tree query) joins one group, transitively. A group keeps the position of its
    lowest-index vertex, and groups are numbered by first occurrence, so a mesh without
    duplicates keeps its vertex order. Returns (welded vertices (W, 3), vertex_map (V,):
    the welded vertex of each input vertex)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    n = len(vertices)
    tolerance = rtol * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    pairs = cKDTree(vertices, balanced_tree=False).query_pairs(tolerance, output_type="ndarray")  # exact either way
    if len(pairs) == 0:
        return vertices, np.arange(n)
    graph = sp.coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_groups, group = connected_components(graph, directed=False)
    first = np.full(n_groups, n)
    np.minimum.at(first, group, np.arange(n))
    order = np.argsort(first)
    rank = np.empty(n_groups, dtype=np.int64)
    rank[order] = np.arange(n_groups)
    return vertices[first[order]], rank[group]


def _without(dropped: np.ndarray, faces: np.ndarray, source: np.ndarray, twin_source: np.ndarray,
             twin_of: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(faces, source, twin_source, twin_of) without the faces `dropped` (F,) bool: the
    twins of a dropped face (its other side) leave with it, the others are renumbered."""
    if not dropped.any():
        return faces, source, twin_source, twin_of
    renumber = np.cumsum(~dropped) - 1
    stays = ~dropped[twin_of]
    return faces[~dropped], source[~dropped], twin_source[stays], renumber[twin_of[stays]]


def loose_slivers(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(loose (F,), thin (F,)): `sliver_faces`, and those of them on a border or
    non-manifold edge (an edge not shared by exactly two faces). Dropping a loose sliver
    leaves no new hole; one inside a closed surface is kept (dropping it would open the
    surface: a deformed sample has thin faces where it is stretched)."""
    thin = sliver_faces(vertices, faces)
    if not thin.any():
        return thin, thin
    open_edge = (faces_per_edge(faces) != 2).reshape(-1, 3).any(axis=1)
    return thin & open_edge, thin


def sliver_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) True for faces thinner than SLIVER_RATIO: shortest altitude (2 × area / longest
    edge) over longest edge."""
    thin = np.zeros(len(faces), dtype=bool)
    for start in range(0, len(faces), FACE_CHUNK):
        corners = vertices[faces[start:start + FACE_CHUNK]]
        u, v, w = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], corners[:, 2] - corners[:, 1]
        longest = np.maximum(np.maximum(np.einsum("ij,ij->i", u, u), np.einsum("ij,ij->i", v, v)),
                             np.einsum("ij,ij->i", w, w))
        cross = cross_rows(u, v)
        thin[start:start + FACE_CHUNK] = np.einsum("ij,ij->i", cross, cross) < (SLIVER_RATIO * longest) ** 2
    return thin


def drop_twin_faces(faces: np.ndarray, polygon_of: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The faces to keep when faces on the same three vertices are one surface: (kept (K,)
    increasing indices of the first face on each vertex triple, twin_of (F − K,) the
    position in `kept` of the face each dropped face repeats, dropped faces in increasing
    order). Either winding repeats: the opposite one is the back of a double-sided sheet,
    the same one a plain duplicate; both would z-fight with the kept face when drawn.
    With `polygon_of` (F,) the faces of a polygon on the same vertices as an earlier
    polygon are twins too, of that polygon's first face (a polygon and its reverse may be
    cut into different triangles)."""
    faces = np.asarray(faces)
    key = np.sort(faces, axis=1).astype(np.int64)
    if polygon_of is not None:
        twin_face = _repeated_polygon_first_face(faces, polygon_of)
        key = np.where(twin_face[:, None] >= 0, key[np.maximum(twin_face, 0)], key)
    n = int(faces.max()) + 1 if len(faces) else 1
    if n <= 2_000_000:  # one int64 per triple (n³ < 2⁶³): a flat sort, several times faster than rows
        key = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
        _, first, group = np.unique(key, return_index=True, return_inverse=True)
    else:
        _, first, group = np.unique(key, axis=0, return_index=True, return_inverse=True)
    group = np.asarray(group).ravel()
    if len(first) == len(faces):
        return np.arange(len(faces)), np.empty(0, dtype=np.int64)
    kept = np.sort(first)
    position = np.empty(len(faces), dtype=np.int64)
    position[kept] = np.arange(len(kept))
    is_kept = np.zeros(len(faces), dtype=bool)
    is_kept[kept] = True
    return kept, position[first[group[~is_kept]]]


def _repeated_polygon_first_face(faces: np.ndarray, polygon_of: np.ndarray) -> np.ndarray:
    """(F,): for a face of a polygon on the same vertex set as an earlier polygon, the
    first face of that earlier polygon; −1 for every other face."""
    polygon_of = np.asarray(polygon_of, dtype=np.int64)
    members = np.unique(np.stack([np.repeat(polygon_of, 3), faces.ravel()], axis=1), axis=0)  # (polygon, vertex)
    polygons, start, size = np.unique(members[:, 0], return_index=True, return_counts=True)
    first_face = np.full(int(polygon_of.max()) + 1, len(faces))
    np.minimum.at(first_face, polygon_of, np.arange(len(faces)))
    twin_face = np.full(int(polygon_of.max()) + 1, -1)
    for n in np.unique(size):
        group = np.flatnonzero(size == n)
        rows = members[(start[group][:, None] + np.arange(n)).ravel(), 1].reshape(-1, n)  # sorted vertex sets
        _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
        earliest = polygons[group[first[np.asarray(inverse).ravel()]]]
        repeat = earliest != polygons[group]
        twin_face[polygons[group[repeat]]] = first_face[earliest[repeat]]
    return twin_face[polygon_of]
