"""Exact closest points on a large mesh for a few queries with known upper bounds, at a
cost set by the queries, not by the mesh (placing 800 landmarks on a
million-vertex surface).

`closest_within` answers, per query p with bound u (a point of the surface at distance u
is known): the closest point of the mesh; with normals, the closest point among the faces
whose normal n_f has n_f · normal >= min_cos if one lies within 4 u (looked for first
within the distance to the nearest vertex, then as far as a compatible centroid seen, at
most 4 u), else the closest point. Among equally close faces the lowest face index wins,
so the answer does not depend on which faces were looked at.

The search: `NearFaces` pairs each query with a set of faces that holds every face within
its bound (integer cells of the vertices), or every face is paired with every query
(`everywhere`: the full-mesh search the tests compare with); only the candidate faces are
mapped to the search frame (v − centre) / scale. Pairs whose sphere bound |p − c_f| − R_f
(c_f the centroid, R_f the farthest corner from it) exceeds the query's bound are
dropped; a centroid lies on its face, so the nearest (compatible) centroid is a closer
bound still, and pairs beyond it are dropped too before the exact point–triangle tests.
"""

from __future__ import annotations

import numpy as np

from .nearfaces import NearFaces
from .surface import SurfacePoints, closest_points_on_triangles, empty_surface_points

__all__ = ["closest_within"]

#: faces per chunk when centroids, radii and normals are computed (bounds the temporary memory)
_CHUNK = 1 << 20
#: pairs screened or tested exactly per chunk
_PAIR_CHUNK = 1 << 19
#: how much farther than the bound a compatible point is looked for when none lies within it
_WIDER = 4.0
#: relative tolerance on the bounds (rounding): a pair within bound + tolerance is kept
_TOLERANCE = 1e-9


class _Candidates:
    """Centroids c_f and bounding radii R_f (`spheres`) and unnormalised normals (`with_normals`)
    of the faces `ids` (ascending) in the search frame."""

    def __init__(self, vertices, faces, ids, centre, scale, with_normals: bool, spheres: bool = True):
        self.ids = ids
        self.centroids = np.empty((len(ids), 3)) if spheres else None
        self.radii = np.empty(len(ids)) if spheres else None
        self.cross = np.empty((len(ids), 3)) if with_normals else None
        self.length = np.empty(len(ids)) if with_normals else None
        for start in range(0, len(ids), _CHUNK):
            part = faces[ids[start:start + _CHUNK]]
            corners = [(vertices[part[:, k]] - centre) / scale for k in range(3)]  # (n, 3) each
            if spheres:
                middle = (corners[0] + corners[1] + corners[2]) / 3.0
                self.centroids[start:start + _CHUNK] = middle
                squared = [np.einsum("ij,ij->i", corner - middle, corner - middle) for corner in corners]
                self.radii[start:start + _CHUNK] = np.sqrt(np.maximum(np.maximum(squared[0], squared[1]),
                                                                      squared[2]))
            if with_normals:
                cross = np.cross(corners[1] - corners[0], corners[2] - corners[0])
                self.cross[start:start + _CHUNK] = cross
                self.length[start:start + _CHUNK] = np.linalg.norm(cross, axis=1)

    def screened(self, points, reach, rows, at) -> tuple[np.ndarray, ...]:
        """(row, at, |p − c_f|, |p − c_f| − R_f) of the pairs whose sphere bound is within reach."""
        centre = np.linalg.norm(points[rows] - self.centroids[at], axis=1)
        gap = centre - self.radii[at]
        keep = gap <= reach[rows]
        return rows[keep], at[keep], centre[keep], gap[keep]

    def compatible(self, rows: np.ndarray, at: np.ndarray, normals: np.ndarray, min_cos: float) -> np.ndarray:
        """Per pair: the face has a normal and n_f · normal >= min_cos."""
        length = self.length[at]
        cosine = np.einsum("nd,nd->n", self.cross[at], normals[rows]) / np.where(length > 0, length, 1.0)
        return (length > 0) & (cosine >= min_cos)


class _Search:
    """Closest points of `points` (search frame) among the faces within given bounds."""

    def __init__(self, vertices, faces, points, reach, normals, min_cos, centre, scale, everywhere):
        self.vertices, self.faces = vertices, faces
        self.points, self.normals, self.min_cos = points, normals, min_cos
        self.centre, self.scale = centre, scale
        self.tolerance = _TOLERANCE * (np.abs(points).max(initial=0.0) + reach)
        self.everything = None
        self.near = None
        if everywhere:
            self.everything = _Candidates(vertices, faces, np.arange(len(faces)), centre, scale, normals is not None)
        else:
            farthest = ((_WIDER if normals is not None else 1.0) * reach * (1.0 + 1e-3) + self.tolerance)[:, None]
            in_mesh = points * scale + centre
            self.near = NearFaces(vertices, faces, (in_mesh - farthest * scale).min(axis=0),
                                  (in_mesh + farthest * scale).max(axis=0), float(np.median(reach)) * scale)

    def _pairs(self, query: np.ndarray, normals: np.ndarray | None, reach: np.ndarray, tolerance: np.ndarray,
               tighten: bool, compatible_only: bool) -> tuple:
        """The candidate faces, the bounds used (`reach`, or with `tighten` lowered to
        the nearest vertex where closer), the pairs (row, at, |p − c_f|, gap) whose sphere
        bound is within bound + tolerance (with `compatible_only`, compatible pairs only,
        their faces' spheres computed for those alone) and, with `tighten` and normals,
        per row the distance to the nearest centroid of a compatible candidate (None
        otherwise: an upper bound on the distance to the closest compatible point)."""
        if self.everything is not None:  # every face with every row, a block of rows at a time
            count = len(self.faces)
            step = max(1, _PAIR_CHUNK // max(1, count))
            parts = [self.everything.screened(query, reach + tolerance, np.repeat(block, count),
                                              np.tile(np.arange(count), len(block)))
                     for block in np.array_split(np.arange(len(query)), -(-len(query) // step))]
            return self.everything, reach, tuple(np.concatenate(part) for part in zip(*parts)), None
        ids, rows, at, used = self.near.pairs(query * self.scale + self.centre, reach * self.scale, tighten)
        reach = np.minimum(reach, used / self.scale)
        if compatible_only:
            oriented = _Candidates(self.vertices, self.faces, ids, self.centre, self.scale, True, spheres=False)
            compatible = oriented.compatible(rows, at, normals, self.min_cos)
            kept, at = np.unique(at[compatible], return_inverse=True)
            ids, rows, at = ids[kept], rows[compatible], at.ravel()
        candidates = _Candidates(self.vertices, self.faces, ids, self.centre, self.scale, normals is not None)
        centre = np.linalg.norm(query[rows] - candidates.centroids[at], axis=1)
        nearest = None
        if tighten and normals is not None:
            compatible = candidates.compatible(rows, at, normals, self.min_cos)
            nearest = _row_min(len(query), rows[compatible], centre[compatible])
        gap = centre - candidates.radii[at]
        keep = gap <= (reach + tolerance)[rows]
        return candidates, reach, (rows[keep], at[keep], centre[keep], gap[keep]), nearest

    def run(self, rows: np.ndarray, reach: np.ndarray, plain: bool, tighten: bool = False) -> tuple:
        """(closest point among the faces within `reach` (if `plain`), closest compatible
        point within `reach` (with normals), the bounds used, an upper bound on the closest
        compatible point's distance or None; see `_pairs`) of `points[rows]`; with
        `tighten`, a row's bound is first lowered to its nearest vertex's distance."""
        query = self.points[rows]
        tolerance = self.tolerance[rows]
        normals = None if self.normals is None else self.normals[rows]
        candidates, reach, (pair_rows, at, centre, gap), nearest = self._pairs(
            query, normals, reach, tolerance, tighten, compatible_only=not plain)
        tested = np.zeros(len(pair_rows), dtype=bool)
        if plain:
            tested |= gap <= _row_min(len(rows), pair_rows, centre)[pair_rows] + tolerance[pair_rows]
        compatible = None
        if normals is not None:
            compatible = candidates.compatible(pair_rows, at, normals, self.min_cos)
            bound = _row_min(len(rows), pair_rows[compatible], centre[compatible])
            tested |= compatible & (gap <= bound[pair_rows] + tolerance[pair_rows])
        best_plain = empty_surface_points(len(rows)) if plain else None
        best_compatible = empty_surface_points(len(rows)) if compatible is not None else None
        tested = np.flatnonzero(tested)
        for start in range(0, len(tested), _PAIR_CHUNK):
            chunk = tested[start:start + _PAIR_CHUNK]
            pair, face = pair_rows[chunk], candidates.ids[at[chunk]]
            triangles = (self.vertices[self.faces[face]] - self.centre) / self.scale
            closest, bary = closest_points_on_triangles(query[pair], triangles)
            distance = np.linalg.norm(closest - query[pair], axis=1)
            found = SurfacePoints(closest, face, bary, distance)
            if plain:
                _keep_closest(best_plain, pair, found)
            if compatible is not None:
                within = np.flatnonzero(compatible[chunk] & (distance <= reach[pair]))
                _keep_closest(best_compatible, pair[within], _take(found, within))
        return best_plain, best_compatible, reach, nearest


def closest_within(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, reach: np.ndarray,
                   normals: np.ndarray | None = None, min_cos: float = -1.0, centre: np.ndarray | None = None,
                   scale: float = 1.0, everywhere: bool = False) -> SurfacePoints:
    """The closest point of the mesh to every query (exact), given per query an upper
    bound `reach` on its distance to the surface (e.g. the distance to a known vertex).
    With `normals`, the closest point whose face normal n_f has n_f · normal >= `min_cos`
    if one lies within 4 × reach (exact as well), else the closest point. Queries, bounds
    and answers are in the frame v -> (v − centre) / scale of the `vertices`. Looks only at
    the faces near the queries unless `everywhere` (same answers: the full-mesh search)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    reach = np.asarray(reach, dtype=np.float64)
    centre = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    normals = None if normals is None else np.asarray(normals, dtype=np.float64)
    if len(points) == 0:
        return empty_surface_points(0)
    search = _Search(vertices, faces, points, reach, normals, min_cos, centre, float(scale), everywhere)
    # first within the nearest vertex's distance (below `reach`): a compatible point found
    # there is the closest overall; the other rows look within 4 × reach, or only as far as
    # a compatible face's centroid the first search saw (the closest compatible point is nearer)
    plain, best, _, nearest = search.run(np.arange(len(points)), reach, plain=True, tighten=not everywhere)
    if normals is None:
        return plain
    rows = np.flatnonzero(~np.isfinite(best.distance))
    if len(rows):
        wider = _WIDER * reach[rows]
        if nearest is not None:
            wider = np.minimum(wider, nearest[rows] * (1.0 + _TOLERANCE) + search.tolerance[rows])
        _, found, _, _ = search.run(rows, wider, plain=False)
        _keep_closest(best, rows, found)
    missing = np.flatnonzero(~np.isfinite(best.distance))
    _keep_closest(best, missing, _take(plain, missing))
    return best


def _row_min(rows: int, at: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per row, the smallest of `values` at that row (inf where none)."""
    smallest = np.full(rows, np.inf)
    np.minimum.at(smallest, at, values)
    return smallest


def _take(found: SurfacePoints, rows: np.ndarray) -> SurfacePoints:
    return SurfacePoints(found.points[rows], found.face_index[rows], found.barycentric[rows], found.distance[rows])


def _keep_closest(best: SurfacePoints, rows: np.ndarray, found: SurfacePoints) -> None:
    """`found` (one entry per element of `rows`, rows may repeat) merged into `best`: each
    row keeps its closest entry, the lowest face index among equally close ones."""
    if len(rows) == 0:
        return
    order = np.lexsort((found.face_index, found.distance, rows))
    first = order[np.r_[True, rows[order][1:] != rows[order][:-1]]]
    target = rows[first]
    distance, face = found.distance[first], found.face_index[first]
    better = (distance < best.distance[target]) | ((distance == best.distance[target]) & (face < best.face_index[target]))
    target, first = target[better], first[better]
    best.points[target] = found.points[first]
    best.face_index[target] = found.face_index[first]
    best.barycentric[target] = found.barycentric[first]
    best.distance[target] = found.distance[first]
