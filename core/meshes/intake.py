"""Raw mesh data -> a clean `Mesh`, the way every reader hands meshes to the core (files:
io.read_mesh; Blender: convert.object_to_mesh, and meshset.load_mesh_set in the worker):

1. `Mesh.from_polygons`: fan-triangulate polygons, drop degenerate triangles;
2. `weld_vertices`: merge coincident vertices. STL files and other triangle soups give
   every triangle its own three corners; welded, smoothing, the closedness test and the
   written files see one connected surface instead of loose triangles;
3. `drop_twin_faces`: a face on the same three (welded) vertices as an earlier one is the
   other side of a double-sided surface (CAD files store every sheet twice, wound opposite
   ways) or a plain duplicate; one surface is kept, so every edge of a double-sided sheet
   has two faces again instead of four, and the dropped sides are recorded (`twin_source`,
   `twin_of`) so a caller can map them back to the file's faces (issue 31);
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
in: the same vertices in the same order and the same faces.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..base.errors import MeshError
from .mesh import FACE_CHUNK, SLIVER_RATIO, Mesh, cross_rows, triangle_cross

__all__ = ["clean_mesh", "weld_vertices", "sliver_faces", "loose_slivers", "drop_twin_faces", "internal_faces", "separate_parts",
           "orient_faces", "outside_sides", "shared_edges", "outwardness", "winding_numbers", "WELD_RTOL",
           "SLIVER_RATIO", "OPEN_PART_MIN_OUTWARDNESS"]

#: Vertices closer than this fraction of the bounding-box diagonal are one vertex. The
#: corners a soup repeats are bitwise equal (STL stores float32 and every writer prints the
#: same float for the same corner), so exact equality would do for them; the tolerance also
#: merges copies of a point that reached the file through different float64 arithmetic
#: (rounding ~1e-16 of the coordinates). It stays far below what any model distinguishes:
#: float32, the precision of STL, PLY, glTF and Blender, resolves ~6e-8 of a coordinate.
WELD_RTOL = 1e-9

#: A sheet is inside a closed volume when the rest of the surface winds around points just
#: off both of its sides at least this much (generalised winding number: 1 inside a closed
#: outward surface, 0 outside).
INSIDE_WINDING = 0.5

#: Faces of a candidate sheet whose both sides are probed, and how far off the face (a
#: fraction of the bounding-box diagonal).
INTERNAL_PROBES = 4
PROBE_OFFSET = 1e-4

#: Directions `outside_sides` casts rays along (spread evenly over the sphere): each side
#: of a face gets those within its hemisphere, about 40 % of them.
SIDE_RAY_DIRECTIONS = 40

#: Passes of `loose_slivers`: a fan of slivers along a border loses one layer per pass.
SLIVER_PEELS = 8

#: An open part (one with a border) is turned outward only when its `outwardness` is at
#: least this large in magnitude. A spherical cap of half-angle φ has outwardness ≈ 0.7 φ,
#: so parts flatter than a cap of about 4° (a sheet, a leaf) have no outside and keep
#: their winding. A closed part is decided by the sign of its enclosed volume alone.
OPEN_PART_MIN_OUTWARDNESS = 0.05

#: A closed part with |outwardness| below this encloses no volume (two coincident sheets
#: facing apart): its winding is kept. Rounding alone gives ~1e-16.
CLOSED_PART_MIN_OUTWARDNESS = 1e-9


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


def faces_per_edge(faces: np.ndarray) -> np.ndarray:
    """(3F,): for each half-edge (face f's corner k → k + 1 at 3f + k), how many faces
    share its edge (either direction): 2 inside a manifold surface, 1 on a border, 3 or
    more where sheets branch."""
    _, edge, count = np.unique(_edge_keys(faces), return_inverse=True, return_counts=True)
    return count[np.asarray(edge).ravel()]


def _edge_keys(faces: np.ndarray) -> np.ndarray:
    """(3F,) one int64 per half-edge, the same for both directions of an edge."""
    start, end = faces.ravel().astype(np.int64), faces[:, [1, 2, 0]].ravel().astype(np.int64)
    return np.minimum(start, end) * (int(faces.max()) + 1) + np.maximum(start, end)


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


def internal_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) True for the faces of sheets inside a closed volume (a wall between two cells).

    Candidates are the sheets (faces connected across edges of exactly two faces) with no
    border whose rim runs along edges of three or more faces: a wall meets the outside
    there. A candidate is internal when the rest of the surface, each sheet wound
    consistently and outwards (`orient_faces`), winds around points just off both sides of
    most of its probed faces (|winding number| ≥ INSIDE_WINDING): there is volume on both
    sides. The two halves of the outside around a wall are candidates too, but have nothing
    on their outer side. A clean mesh (no edge of three faces) costs one sort of its edges.
    """
    faces = np.asarray(faces)
    inside = np.zeros(len(faces), dtype=bool)
    half_face = np.repeat(np.arange(len(faces)), 3)
    keys = np.sort(_edge_keys(faces))
    if len(keys) < 3 or not (keys[2:] == keys[:-2]).any():  # no edge of three faces: a plain sort decides
        return inside
    faces_on_edge = faces_per_edge(faces)
    first, second, _, _ = shared_edges(faces)
    graph = sp.coo_matrix((np.ones(len(first), dtype=np.int8), (first, second)), shape=(len(faces),) * 2)
    n_sheets, sheet = connected_components(graph, directed=False)
    bordered = np.bincount(sheet[half_face[faces_on_edge == 1]], minlength=n_sheets) > 0
    branching = np.bincount(sheet[half_face[faces_on_edge >= 3]], minlength=n_sheets) > 0
    candidates = np.flatnonzero(branching & ~bordered)
    if len(candidates) < 2:  # a wall has the outside's sheets around it, candidates too
        return inside
    oriented, _, _ = orient_faces(vertices, faces)
    cross = triangle_cross(vertices, oriented)
    twice_area = np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(twice_area, np.finfo(float).tiny)[:, None]
    offset = PROBE_OFFSET * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    probes = []  # (sheet, probed face) pairs
    for candidate in candidates:
        members = np.flatnonzero(sheet == candidate)
        probes += [(candidate, f) for f in members[np.argsort(-twice_area[members], kind="stable")[:INTERNAL_PROBES]]]
    probe_sheet, probe_face = np.array(probes).T
    centre = vertices[oriented[probe_face]].mean(axis=1)
    points = np.concatenate([centre + offset * normal[probe_face], centre - offset * normal[probe_face]])
    winding = winding_numbers(vertices, oriented, points)
    for candidate in candidates:  # the sheet's own share taken out: the rest of the surface around it
        at = np.flatnonzero(np.tile(probe_sheet == candidate, 2))
        winding[at] -= winding_numbers(vertices, oriented[sheet == candidate], points[at])
    both_sides = np.minimum(*np.abs(winding).reshape(2, -1)) >= INSIDE_WINDING
    share = np.bincount(probe_sheet, both_sides, n_sheets) / np.maximum(np.bincount(probe_sheet, minlength=n_sheets), 1)
    return share[sheet] > 0.5


def winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Generalised winding number of the surface at each point (Q,): the solid angle its
    faces subtend, signed by their winding, over 4π. 1 inside a closed outward surface, 0
    outside, in between near an open one.

    libigl's fast winding number (Barill et al. 2018): exact for the faces near a point,
    a second-order expansion of far clusters of faces (a tree over the faces), so the cost
    grows as (faces + points) × log(faces) instead of faces × points. Its small error is
    far below the thresholds intake compares against (INSIDE_WINDING)."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(faces)
    if len(faces) == 0 or len(points) == 0:  # libigl would return uninitialised values for no faces
        return np.zeros(len(points))
    import igl  # here, not at the top: the add-on imports this module when it is enabled

    return igl.fast_winding_number(np.ascontiguousarray(vertices, dtype=np.float64),
                                   np.ascontiguousarray(faces, dtype=np.int64), points)


def separate_parts(vertices: np.ndarray, faces: np.ndarray) -> tuple[int, float]:
    """(number of connected parts of the surface (faces sharing a vertex), the largest
    part's share of the area)."""
    faces = np.asarray(faces)
    n = len(vertices)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = sp.coo_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    _, part = np.unique(label[faces[:, 0]], return_inverse=True)
    part = np.asarray(part).ravel()
    area = np.bincount(part, np.linalg.norm(triangle_cross(vertices, faces), axis=1))
    return len(area), float(area.max() / max(area.sum(), np.finfo(float).tiny))


def orient_faces(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """Wind every face like its neighbours, then every connected part outwards.

    Parts are the faces connected across manifold edges (edges of exactly two faces; a
    border or non-manifold edge separates them). Within a part the relative windings are
    fixed by a 2-colouring of the signed face graph: node f is face f as given, node f + F
    face f reversed, and a shared edge joins the windings under which the two faces run
    along it in opposite directions. Each part keeps the winding of its lowest-index face,
    then is reversed whole when its `outwardness` is negative (open parts only beyond
    OPEN_PART_MIN_OUTWARDNESS).

    A part whose two colours meet (f and f reversed in one component) is non-orientable:
    no winding makes every pair of its neighbours agree, and it has no outside as a whole.
    It is wound face by face instead: each face towards its outside side (`outside_sides`),
    and where neither side is outside (a band inside a closed body) as a breadth-first
    walk from its first face winds it (libigl's `bfs_orient`: every neighbour agrees but
    along one seam).

    Returns (faces (F, 3) with reversed faces' corners 1 and 2 swapped, reversed (F,) bool,
    counts for MeshReport: faces_rewound, parts_turned_outward, parts_without_inside,
    unorientable_parts, unorientable_faces).
    """
    faces = np.asarray(faces)
    n = len(faces)
    first, second, same_direction, border = shared_edges(faces)
    if same_direction.any():
        rows = np.concatenate([first, first + n])
        cols = np.concatenate([np.where(same_direction, second + n, second),
                               np.where(same_direction, second, second + n)])
        graph = sp.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(2 * n, 2 * n))
        _, colour = connected_components(graph, directed=False)
        as_given, as_reversed = colour[:n], colour[n:]
    else:  # every neighbour agrees already (the usual file): the face graph alone, half the size
        graph = sp.coo_matrix((np.ones(len(first), dtype=np.int8), (first, second)), shape=(n, n))
        n_parts, as_given = connected_components(graph, directed=False)
        as_reversed = as_given + n_parts
    _, part = np.unique(np.minimum(as_given, as_reversed), return_inverse=True)
    part = np.asarray(part).ravel()
    n_parts = int(part.max()) + 1
    root = np.full(n_parts, n)
    np.minimum.at(root, part, np.arange(n))
    rewound = as_given != as_given[root[part]]
    unorientable = np.zeros(n_parts, dtype=bool)
    unorientable[part[as_given == as_reversed]] = True
    if unorientable.any():
        import igl  # here: only a non-orientable part needs it

        rewound = rewound.copy()
        for index in np.flatnonzero(unorientable):
            members = np.flatnonzero(part == index)
            walked, _ = igl.bfs_orient(np.ascontiguousarray(faces[members], dtype=np.int64))
            rewound[members] = (walked != faces[members]).any(axis=1)  # bfs_orient reverses rows it turns
        members = np.flatnonzero(unorientable[part])
        consistent = np.where(rewound[:, None], faces[:, [0, 2, 1]], faces)
        inwards, decided_face = outside_sides(vertices, consistent, members)
        rewound[members] ^= inwards & decided_face
    consistent = np.where(rewound[:, None], faces[:, [0, 2, 1]], faces)

    score = outwardness(vertices, consistent, part, n_parts)
    is_open = np.zeros(n_parts, dtype=bool)
    is_open[part[border]] = True
    decided = np.abs(score) >= np.where(is_open, OPEN_PART_MIN_OUTWARDNESS, CLOSED_PART_MIN_OUTWARDNESS)
    decided |= unorientable  # wound face by face above
    turned = decided & (score < 0) & ~unorientable
    reversed_faces = rewound ^ turned[part]
    n_reversed = np.bincount(part, reversed_faces, n_parts)
    size = np.bincount(part, minlength=n_parts)
    counts = {
        "faces_rewound": int(n_reversed[(n_reversed > 0) & (n_reversed < size) & ~unorientable].sum()),
        "parts_turned_outward": int(np.sum((n_reversed == size) & ~unorientable)),
        "parts_without_inside": int(np.sum(~decided)),
        "unorientable_parts": int(unorientable.sum()),
        "unorientable_faces": int(size[unorientable].sum()),
    }
    if reversed_faces.any():
        faces = np.where(reversed_faces[:, None], faces[:, [0, 2, 1]], faces)
    return faces, reversed_faces, counts


def outside_sides(vertices: np.ndarray, faces: np.ndarray, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which side of each face `which` (indices into `faces`) is outside, by ray parity:
    (inwards (W,), the face's front, where its winding's normal points, is the inside;
    decided (W,), one side is outside more clearly than the other).

    From a point just off each side of a face (PROBE_OFFSET of the diagonal), rays along
    fixed directions within that side's hemisphere (SIDE_RAY_DIRECTIONS over the sphere,
    the same every time, so a file reads the same every time) cross the surface, all of
    `faces` whatever their winding, an odd number of times from inside a closed volume and
    an even number from outside. The side whose rays cross oddly less often is outside (the
    ray casting of Takayama et al. 2014, voting per face; Embree through libigl). Winding
    numbers cannot decide this: they jump by one across any face the way it is wound, so
    the side with the lower |winding number| is whichever the face's own winding says.
    """
    which = np.asarray(which, dtype=np.int64)
    vertices = np.asarray(vertices, dtype=np.float64)
    middle = (vertices.min(axis=0) + vertices.max(axis=0)) / 2  # float32 rays: coordinates near 0
    local = vertices - middle
    cross = triangle_cross(local, faces[which])
    length = np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(length, np.finfo(float).tiny)[:, None]
    offset = PROBE_OFFSET * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    centre = local[faces[which]].mean(axis=1)
    directions = _sphere_directions(SIDE_RAY_DIRECTIONS)
    import igl.embree  # here: only non-orientable parts cast rays

    intersector = igl.embree.EmbreeIntersector()
    intersector.init(np.asfortranarray(local, dtype=np.float32), np.asfortranarray(faces, dtype=np.int32))
    odd = np.zeros((len(which), 2))
    for k in range(len(which)):
        ahead = directions[directions @ normal[k] > 0.1]  # not grazing the face's plane
        for side, sign in enumerate((1.0, -1.0)):
            origin = (centre[k] + sign * offset * normal[k]).astype(np.float32)
            for direction in sign * ahead:
                hits, _ = intersector.intersectRay(origin, direction.astype(np.float32))
                odd[k, side] += len(hits) % 2
    return odd[:, 0] > odd[:, 1], (odd[:, 0] != odd[:, 1]) & (length > 0)


def _sphere_directions(n: int) -> np.ndarray:
    """`n` unit vectors spread evenly over the sphere (a Fibonacci lattice), turned off
    the axes so that none runs along the edges or faces of an axis-aligned model."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    angle = np.pi * (3 - np.sqrt(5)) * k
    points = np.stack([np.sqrt(1 - z * z) * np.cos(angle), np.sqrt(1 - z * z) * np.sin(angle), z], axis=1)
    a, b = 0.3, 0.7  # radians about x, then about z
    turn_x = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    turn_z = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
    return points @ (turn_z @ turn_x).T


def outwardness(vertices: np.ndarray, faces: np.ndarray, part: np.ndarray | None = None,
                n_parts: int | None = None) -> np.ndarray:
    """How much each part's normals point away from its middle, per part (n_parts,):
    Σ A_f n_f · (c_f − c) / (A R), with A_f, n_f, c_f each face's area, unit normal and
    centroid, c the part's area-weighted centroid, A its area and R the area-weighted RMS
    distance of the face centroids from c. For a closed part the sum is 3 × its enclosed
    volume (divergence theorem), so the sign is the volume's; it also decides open parts
    (a vase open at the top, a bowl), which enclose nothing. 1 for a sphere, 0 for a flat
    sheet, negative when the part is inside out. `part` (F,) numbers the parts (all
    faces one part by default). Summed over chunks of FACE_CHUNK faces (up to that many,
    the same floating-point operations as over the whole mesh)."""
    part = np.zeros(len(faces), dtype=np.int64) if part is None else part
    n_parts = int(part.max()) + 1 if n_parts is None else n_parts
    chunks = range(0, len(faces), FACE_CHUNK)  # one chunk up to FACE_CHUNK faces: the sums as over the whole
    weight, moment = np.zeros(n_parts), np.zeros((n_parts, 3))
    for start in chunks:
        cut, cross, twice_area, centroid = _face_terms(vertices, faces, part, start)
        weight += np.bincount(cut, twice_area, n_parts)
        moment += np.stack([np.bincount(cut, twice_area * centroid[:, d], n_parts) for d in range(3)], axis=1)
    middle = moment / np.maximum(weight, np.finfo(float).tiny)[:, None]
    flux, second = np.zeros(n_parts), np.zeros(n_parts)
    for start in chunks:
        cut, cross, twice_area, centroid = _face_terms(vertices, faces, part, start)
        offset = centroid - middle[cut]
        flux += np.bincount(cut, np.einsum("ij,ij->i", cross, offset), n_parts)
        second += np.bincount(cut, twice_area * np.einsum("ij,ij->i", offset, offset), n_parts)
    spread = np.sqrt(second / np.maximum(weight, np.finfo(float).tiny))
    scale = weight * spread
    return np.divide(flux, scale, out=np.zeros(n_parts), where=scale > 0)


def _face_terms(vertices: np.ndarray, faces: np.ndarray, part: np.ndarray, start: int):
    """For the FACE_CHUNK faces from `start`: their parts, cross products (2 A_f n_f),
    doubled areas and centroids (chunks bound a dense mesh's temporary memory, issue 15)."""
    faces = faces[start:start + FACE_CHUNK]
    cross = triangle_cross(vertices, faces)
    centroid = (vertices[faces[:, 0]] + vertices[faces[:, 1]] + vertices[faces[:, 2]]) / 3.0
    return part[start:start + FACE_CHUNK], cross, np.linalg.norm(cross, axis=1), centroid


def shared_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Face pairs across manifold edges (edges used by exactly two faces): first (E,),
    second (E,), and whether both faces run along the edge in the same direction (E,);
    plus the faces with a border or non-manifold edge (a face per such half-edge).
    Built with at most three int64 arrays of the half-edges alive at a time (issue 15: a
    reading worker's peak memory on a mesh of millions of faces)."""
    faces = np.asarray(faces)
    end = faces[:, [1, 2, 0]]  # half-edge h runs faces.ravel()[h] -> end.ravel()[h] in face h // 3
    rising = (faces < end).ravel()
    key = np.minimum(faces, end).ravel().astype(np.int64)
    key *= int(faces.max()) + 1
    key += np.maximum(faces, end).ravel()
    del end
    order = np.argsort(key)  # any order within an edge: the pairs and border faces are the same
    key = key[order]
    run_start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    count = len(key)
    del key
    run_length = np.diff(np.r_[run_start, count])
    pair = run_start[run_length == 2]
    a, b = order[pair], order[pair + 1]
    same_direction = rising[a] == rising[b]
    border = order[np.repeat(run_length != 2, run_length)] // 3
    return a // 3, b // 3, same_direction, border
