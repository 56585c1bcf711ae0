"""Exact closest points on a large mesh for a few queries with known upper bounds, in
time linear in the mesh (one sort of its faces by grid cell), without a search tree over
every face (issue 15: placing 800 landmarks on a million-vertex surface).

A query p with an upper bound u (a point of the surface at distance u is known) has its
closest point on a face f with dist(p, f) <= u, hence |p − c_f| <= u + R_f (c_f the
centroid, R_f the farthest corner from it). Faces with R_f <= g/2 are bucketed by the
grid cell (side g) of their centroid and a query looks only at the cells within
u + g/2; the few larger faces (R_f above the 99th percentile) are searched exactly by a
`TargetSurface` of their own. Every face within u of p is therefore tested: the answer
is exact. With normals, a query without a compatible face within u looks 4 u far;
the closest compatible face found (at distance d) is exact once every face within d
has been tested (the search is repeated with the bound d when d is beyond the reach).
"""

from __future__ import annotations

import numpy as np

from .surface import SurfacePoints, TargetSurface, _empty_surface_points, closest_points_on_triangles, keep_closest

__all__ = ["closest_within"]

#: faces per chunk when centroids and radii are computed (bounds the temporary memory)
_CHUNK = 1 << 20
#: pairs tested exactly per chunk
_PAIR_CHUNK = 1 << 19
#: times the reach of a query without a compatible face is widened (x4 each) before its
#: closest point of any normal is taken
_WIDENINGS = 1


class _FaceGrid:
    """Faces of a mesh bucketed by the grid cell of their centroid (small faces only)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.vertices, self.faces = vertices, faces
        centroids = np.empty((len(faces), 3))
        radii = np.empty(len(faces))
        for start in range(0, len(faces), _CHUNK):
            part = faces[start:start + _CHUNK]
            corners = [vertices[part[:, k]] for k in range(3)]  # (n, 3) each: no (n, 3, 3) reductions
            centre = (corners[0] + corners[1] + corners[2]) / 3.0
            centroids[start:start + _CHUNK] = centre
            squared = [np.einsum("ij,ij->i", corner - centre, corner - centre) for corner in corners]
            radii[start:start + _CHUNK] = np.sqrt(np.maximum(np.maximum(squared[0], squared[1]), squared[2]))
        self.centroids, self.radii = centroids, radii
        self.cell = max(2.0 * float(np.quantile(radii, 0.99)), np.finfo(float).tiny)
        small = radii <= self.cell / 2
        self.large = np.flatnonzero(~small)
        self.lower = centroids.min(axis=0)
        index = np.floor((centroids - self.lower) / self.cell).astype(np.int64)
        self.size = index.max(axis=0) + 1
        keys = self._keys(index[:, 0], index[:, 1], index[:, 2])
        members = np.flatnonzero(small)
        order = np.argsort(keys[members], kind="stable")
        self.sorted_faces = members[order]
        self.sorted_keys = keys[members][order]

    def _keys(self, x, y, z):
        return (x * self.size[1] + y) * self.size[2] + z

    def pairs(self, points: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, face) for every small face whose centroid cell lies within reach + g/2 of
        its query, then screened by the sphere bound |p − c_f| − R_f <= reach."""
        half = (reach + self.cell / 2)[:, None]
        low = np.clip(np.floor((points - half - self.lower) / self.cell).astype(np.int64), 0, self.size - 1)
        high = np.clip(np.floor((points + half - self.lower) / self.cell).astype(np.int64), 0, self.size - 1)
        outside = ((points + half) < self.lower).any(axis=1) | \
            ((points - half - self.lower) >= self.size * self.cell).any(axis=1)
        nx, ny = high[:, 0] - low[:, 0] + 1, high[:, 1] - low[:, 1] + 1
        columns = np.where(outside, 0, nx * ny)
        row = np.repeat(np.arange(len(points)), columns)
        local = np.arange(int(columns.sum())) - np.repeat(np.cumsum(columns) - columns, columns)
        x = low[row, 0] + local // ny[row]
        y = low[row, 1] + local % ny[row]
        first = np.searchsorted(self.sorted_keys, self._keys(x, y, low[row, 2]), side="left")
        last = np.searchsorted(self.sorted_keys, self._keys(x, y, high[row, 2]), side="right")
        count = last - first
        rows = np.repeat(row, count)
        at = np.repeat(first - (np.cumsum(count) - count), count) + np.arange(int(count.sum()))
        faces = self.sorted_faces[at]
        gap = np.linalg.norm(points[rows] - self.centroids[faces], axis=1) - self.radii[faces]
        keep = gap <= reach[rows]
        return rows[keep], faces[keep]


def closest_within(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, reach: np.ndarray,
                   normals: np.ndarray | None = None, min_cos: float = -1.0) -> SurfacePoints:
    """The closest point of the mesh to every query (exact), given per query an upper
    bound `reach` on its distance to the surface (e.g. the distance to a known vertex).
    With `normals`, the closest point whose face normal n_f has n_f · normal >= `min_cos`
    (exact as well), or, for a query with no compatible face at all, the closest point."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    points = np.asarray(points, dtype=np.float64)
    reach = np.asarray(reach, dtype=np.float64)
    grid = _FaceGrid(vertices, faces)
    large = TargetSurface(vertices, faces[grid.large]) if len(grid.large) else None
    plain = _search(grid, large, points, np.arange(len(points)), reach, None, min_cos)
    if normals is None:
        return plain
    normals = np.asarray(normals, dtype=np.float64)
    best = _search(grid, large, points, np.arange(len(points)), reach, normals, min_cos)
    searched = reach.copy()
    for _ in range(_WIDENINGS):  # no compatible face within the bound: look farther
        none = np.flatnonzero(~np.isfinite(best.distance))
        if len(none) == 0:
            break
        searched[none] *= 4.0
        _update(best, none, _search(grid, large, points, none, searched[none], normals, min_cos))
    wider = np.flatnonzero(np.isfinite(best.distance) & (best.distance > searched))
    if len(wider):  # found beyond the searched reach: exact once every face within it is tested
        _update(best, wider, _search(grid, large, points, wider, best.distance[wider], normals, min_cos))
    missing = np.flatnonzero(~np.isfinite(best.distance))
    _update(best, missing, _take(plain, missing))
    return best


def _take(found: SurfacePoints, rows: np.ndarray) -> SurfacePoints:
    return SurfacePoints(found.points[rows], found.face_index[rows], found.barycentric[rows], found.distance[rows])


def _update(best: SurfacePoints, rows: np.ndarray, found: SurfacePoints) -> None:
    """Rows `rows` of `best` replaced by `found` (one entry per row) where it is closer."""
    better = found.distance < best.distance[rows]
    rows = rows[better]
    best.points[rows] = found.points[better]
    best.face_index[rows] = found.face_index[better]
    best.barycentric[rows] = found.barycentric[better]
    best.distance[rows] = found.distance[better]


def _search(grid: _FaceGrid, large: TargetSurface | None, points: np.ndarray, rows: np.ndarray,
            reach: np.ndarray, normals: np.ndarray | None, min_cos: float) -> SurfacePoints:
    """Closest (compatible) points of `points[rows]` among the faces within `reach`."""
    query = points[rows]
    best = _empty_surface_points(len(rows))
    pair_rows, pair_faces = grid.pairs(query, reach)
    for start in range(0, len(pair_rows), _PAIR_CHUNK):
        _test(grid, query, pair_rows[start:start + _PAIR_CHUNK], pair_faces[start:start + _PAIR_CHUNK], best,
              None if normals is None else normals[rows], min_cos)
    if large is not None:
        found = large.closest(query, None if normals is None else normals[rows], min_cos)
        found = SurfacePoints(found.points, grid.large[found.face_index], found.barycentric, found.distance)
        _update(best, np.arange(len(rows)), found)
    return best


def _test(grid: _FaceGrid, query: np.ndarray, rows: np.ndarray, faces: np.ndarray, best: SurfacePoints,
          normals: np.ndarray | None, min_cos: float) -> None:
    """Exact point–triangle tests of (row, face) pairs; `best` keeps each row's closest."""
    triangles = grid.vertices[grid.faces[faces]]
    if normals is not None:
        cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
        length = np.linalg.norm(cross, axis=1)
        cosine = np.einsum("nd,nd->n", cross, normals[rows]) / np.where(length > 0, length, 1.0)
        ok = (length > 0) & (cosine >= min_cos)
        rows, faces, triangles = rows[ok], faces[ok], triangles[ok]
    if len(rows) == 0:
        return
    closest, bary = closest_points_on_triangles(query[rows], triangles)
    keep_closest(best, rows, faces, closest, bary, np.linalg.norm(closest - query[rows], axis=1))
