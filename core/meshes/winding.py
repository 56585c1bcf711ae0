"""Which side of a surface is outside, the geometric steps of intake (intake.py's
docstring, steps 4, 6 and 7): sheets inside a closed volume (`internal_faces`, by
generalised winding numbers), every face wound like its neighbours and every part
outwards (`orient_faces`, `outwardness`, `outside_sides` for a non-orientable part),
and the surface's connected parts (`separate_parts`); the edge topology they share
(`faces_per_edge`, `shared_edges`)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .mesh import FACE_CHUNK, triangle_cross

__all__ = ["internal_faces", "separate_parts", "orient_faces", "outside_sides", "shared_edges", "outwardness",
           "winding_numbers", "faces_per_edge", "OPEN_PART_MIN_OUTWARDNESS"]

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

#: An open part (one with a border) is turned outward only when its `outwardness` is at
#: least this large in magnitude. A spherical cap of half-angle φ has outwardness ≈ 0.7 φ,
#: so parts flatter than a cap of about 4° (a sheet, a leaf) have no outside and keep
#: their winding. A closed part is decided by the sign of its enclosed volume alone.
OPEN_PART_MIN_OUTWARDNESS = 0.05

#: A closed part with |outwardness| below this encloses no volume (two coincident sheets
#: facing apart): its winding is kept. Rounding alone gives ~1e-16.
CLOSED_PART_MIN_OUTWARDNESS = 1e-9


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
    doubled areas and centroids (chunks bound a dense mesh's temporary memory)."""
    faces = faces[start:start + FACE_CHUNK]
    cross = triangle_cross(vertices, faces)
    centroid = (vertices[faces[:, 0]] + vertices[faces[:, 1]] + vertices[faces[:, 2]]) / 3.0
    return part[start:start + FACE_CHUNK], cross, np.linalg.norm(cross, axis=1), centroid


def shared_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Face pairs across manifold edges (edges used by exactly two faces): first (E,),
    second (E,), and whether both faces run along the edge in the same direction (E,);
    plus the faces with a border or non-manifold edge (a face per such half-edge).
    Built with at most three int64 arrays of the half-edges alive at a time (a
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
