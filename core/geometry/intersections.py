"""Self-intersections of a triangle mesh: the pairs of faces that cross each other.

Broad phase: the triangles' axis-aligned bounding boxes in a uniform grid (cells the
median box's size; a large triangle enters every cell its box touches), the pairs that
share a cell and whose boxes overlap. Then a pair is dropped when one triangle lies
strictly on one side of the other's plane (most near pairs of a smooth surface).

Narrow phase: two non-coplanar triangles intersect exactly when an edge of one crosses the
other (the ends of their intersection segment lie on edges of one or the other), so each
candidate pair is six segment-triangle tests (Möller & Trumbore 1997), vectorised. Faces
that share a vertex are neighbours on the surface and never count; touching at a point or
along an edge (within a relative tolerance) does not count either, nor do coplanar
overlaps (no crossing, and of measure zero for deformed meshes).
"""

from __future__ import annotations

import numpy as np

__all__ = ["candidate_pairs", "intersecting_pairs", "pair_keys"]

#: Relative tolerance of the crossing tests: a segment must cross strictly inside the
#: triangle and strictly between its ends, by this fraction of the barycentric range.
CROSSING_TOLERANCE = 1e-9


#: Grid entries per triangle on average before the cells are made coarser.
MAX_CELLS_PER_TRIANGLE = 16


def _pairs_within_groups(members: np.ndarray, group_start: np.ndarray, group_size: np.ndarray) -> np.ndarray:
    """Every pair of entries within each group of the sorted `members` (groups given by
    their start and size): (P, 2) member pairs."""
    size = np.repeat(group_size, group_size)
    local = np.arange(len(members)) - np.repeat(group_start, group_size)
    partners = size - 1 - local  # entries after this one in its group
    first = np.repeat(np.arange(len(members)), partners)
    run_start = np.cumsum(partners) - partners
    step = np.arange(len(first)) - np.repeat(run_start, partners) + 1
    return np.stack([members[first], members[first + step]], axis=1)


def candidate_pairs(triangles: np.ndarray) -> np.ndarray:
    """(P, 2) face pairs i < j whose axis-aligned bounding boxes overlap; `triangles` (F, 3, 3).

    A uniform grid of cells as large as the median box's longest side (doubled while the
    triangles would enter more than MAX_CELLS_PER_TRIANGLE cells on average): every triangle is
    entered in each cell its box touches, the pairs sharing a cell are the candidates
    (each once), and those whose boxes do not overlap are dropped."""
    triangles = np.asarray(triangles, dtype=np.float64)
    low, high = triangles.min(axis=1), triangles.max(axis=1)
    cell = float(np.median((high - low).max(axis=1)))
    if len(triangles) < 2 or cell <= 0:
        return np.empty((0, 2), dtype=np.int64)
    origin = low.min(axis=0)
    while True:  # a few huge triangles among small ones would enter too many cells: coarser cells
        first_cell = np.floor((low - origin) / cell).astype(np.int64)
        last_cell = np.floor((high - origin) / cell).astype(np.int64)
        span = last_cell - first_cell + 1
        count = span.prod(axis=1)
        if count.sum() <= MAX_CELLS_PER_TRIANGLE * len(triangles):
            break
        cell *= 2.0
    owner = np.repeat(np.arange(len(triangles)), count)
    local = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
    span_y, span_z = np.repeat(span[:, 1], count), np.repeat(span[:, 2], count)
    cell_index = np.repeat(first_cell, count, axis=0) + np.stack(
        [local // (span_y * span_z), (local // span_z) % span_y, local % span_z], axis=1)
    dims = last_cell.max(axis=0) + 1
    key = (cell_index[:, 0] * dims[1] + cell_index[:, 1]) * dims[2] + cell_index[:, 2]
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    group_start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    group_size = np.diff(np.r_[group_start, len(key)])
    pairs = np.sort(_pairs_within_groups(owner, group_start, group_size), axis=1)
    unique = np.unique(pair_keys(pairs, len(triangles)))
    pairs = np.stack([unique // len(triangles), unique % len(triangles)], axis=1)
    meet = ((low[pairs[:, 0]] <= high[pairs[:, 1]]) & (low[pairs[:, 1]] <= high[pairs[:, 0]])).all(axis=1)
    return pairs[meet]


def _segments_cross(start: np.ndarray, end: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(P,) True where segment start→end crosses triangle (P, 3, 3) strictly inside both."""
    direction = end - start
    edge1 = triangles[:, 1] - triangles[:, 0]
    edge2 = triangles[:, 2] - triangles[:, 0]
    h = np.cross(direction, edge2)
    det = np.einsum("ij,ij->i", edge1, h)
    scale = np.linalg.norm(direction, axis=1) * np.linalg.norm(edge1, axis=1) * np.linalg.norm(edge2, axis=1)
    usable = np.abs(det) > 1e-12 * np.maximum(scale, np.finfo(float).tiny)
    inverse = np.divide(1.0, det, out=np.zeros_like(det), where=usable)
    offset = start - triangles[:, 0]
    u = inverse * np.einsum("ij,ij->i", offset, h)
    q = np.cross(offset, edge1)
    v = inverse * np.einsum("ij,ij->i", direction, q)
    t = inverse * np.einsum("ij,ij->i", edge2, q)
    tol = CROSSING_TOLERANCE
    return usable & (u > tol) & (v > tol) & (u + v < 1 - tol) & (t > tol) & (t < 1 - tol)


def _straddles(plane_of: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(P,) True where the corners of triangles `other` are not all strictly on one side of
    the planes of triangles `plane_of` (both (P, 3, 3)): only these can cross."""
    normal = np.cross(plane_of[:, 1] - plane_of[:, 0], plane_of[:, 2] - plane_of[:, 0])
    side = np.einsum("pj,pkj->pk", normal, other - plane_of[:, :1])
    size = np.linalg.norm(normal, axis=1) * np.abs(other - plane_of[:, :1]).max(axis=(1, 2))
    tol = CROSSING_TOLERANCE * size
    return ~((side > tol[:, None]).all(axis=1) | (side < -tol[:, None]).all(axis=1))


def intersecting_pairs(vertices: np.ndarray, faces: np.ndarray, chunk: int = 200_000) -> np.ndarray:
    """(K, 2) face pairs i < j of the mesh that cross each other (module docstring); faces
    sharing a vertex are never a pair."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    triangles = vertices[faces]
    pairs = candidate_pairs(triangles)
    shares = (faces[pairs[:, 0]][:, :, None] == faces[pairs[:, 1]][:, None, :]).any(axis=(1, 2))
    pairs = pairs[~shares]
    crossing = np.zeros(len(pairs), dtype=bool)
    for lo in range(0, len(pairs), chunk):
        first, second = triangles[pairs[lo:lo + chunk, 0]], triangles[pairs[lo:lo + chunk, 1]]
        near = _straddles(first, second)
        near[near] = _straddles(second[near], first[near])
        first, second = first[near], second[near]
        hit = np.zeros(len(first), dtype=bool)
        for one, other in ((first, second), (second, first)):
            for k in range(3):
                hit |= _segments_cross(one[:, k], one[:, (k + 1) % 3], other)
        crossing[lo:lo + chunk][near] = hit
    return pairs[crossing]


def pair_keys(pairs: np.ndarray, n_faces: int) -> np.ndarray:
    """One integer per face pair (i < j): i × n_faces + j, for set operations."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return pairs[:, 0] * int(n_faces) + pairs[:, 1]
