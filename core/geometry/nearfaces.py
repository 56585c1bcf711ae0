"""The faces of a large mesh that may lie within given distances of a few points, paired
with those points, found by integer cell arithmetic over its vertices and faces: no sort
and no tree over the mesh, float work only near the points (placing ~800
landmarks on a surface of a million vertices costs what the landmarks need, not a search
structure over every face).

Every vertex gets integer coordinates on a fine grid of side h (int16 per axis; h an
eighth of the size of the mesh's larger faces). With s_a the spread of a face's corners'
cells along axis a, its corners differ by less than (s_a + 1) h along that axis, so every
point of it lies within D_f = h √(Σ_a (s_a + 1)²) of each corner; the face is *compact*
when every s_a <= 15 (D_f <= 16√3 h). If a point of a compact face lies within ρ of a
query p, each corner v has |v − p| <= ρ + D_f. So:

1. coarse cells (blocks of 2^k fine cells) whose box lies within ρ + 16√3 h of a query are
   marked, each with the queries that marked it;
2. each vertex in a marked cell gets e_v = min over those queries of |v − p| − ρ_p;
3. a compact face is kept when e_v <= D_f at all three corners, paired with the queries
   of its first corner that satisfy it there; a face that is not compact (rare) is paired
   with every query.

Every (query, face) pair with the face within ρ of the query is among the pairs; the
caller screens them exactly. Vertices outside the queries' region are clipped to its
border cells, which are never marked (a compact face there lies wholly outside it).
"""

from __future__ import annotations

import numpy as np

__all__ = ["NearFaces"]

#: fine cells per axis at most (int16 coordinates)
_FINE_LIMIT = 32_000
#: coarse cells of the marked grid at most (slots of the grid)
_COARSE_LIMIT = 1 << 24
#: cells looked at for the queries' balls at most (coarser cells beyond)
_MARK_LIMIT = 1 << 21
#: faces sampled (evenly spaced) to size the fine grid
_SAMPLE = 4096
#: relative slack on every bound (absorbs rounding of coordinates and frame changes)
_SLACK = 1e-6
#: fine cells per sampled face size, and the largest spread of a compact face (in fine cells)
_SUBDIVISION, _COMPACT = 8, 15


class NearFaces:
    """(query, face) pairs of (vertices, faces) for queries whose balls lie inside the box
    `low`..`high`; `typical`: a typical distance asked for (sets the coarse cells)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, low: np.ndarray, high: np.ndarray, typical: float):
        self.vertices, self.faces = vertices, faces
        low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        span = float(np.max(high - low))
        self.slack = _SLACK * max(span, float(np.max(np.abs(low))), float(np.max(np.abs(high))), np.finfo(float).tiny)
        fine = max(_sampled_face_extent(vertices, faces) / _SUBDIVISION, span / (_FINE_LIMIT / 4),
                   np.finfo(float).tiny)
        self.margin = (_COMPACT + 1) * np.sqrt(3.0) * fine * (1.0 + _SLACK) + self.slack
        # coarse cells of about a quarter of a typical query's reach, as many as the grid allows
        start = self._shift_for(typical + self.margin, fine)
        for shift in range(start, 15):
            coarse = fine * 2.0 ** shift
            self.origin = low - self.margin - 2.0 * coarse
            self.size = np.floor((high + self.margin + 2.0 * coarse - self.origin) / coarse).astype(np.int64) + 1
            if np.prod(self.size) <= _COARSE_LIMIT and self.size.max() * 2 ** shift <= _FINE_LIMIT:
                break
        else:
            raise ValueError("NearFaces: no grid fits the region")  # unreachable: fine >= span / 8000
        self.fine, self.shift, self.top = fine, shift, self.size * 2 ** shift - 1
        self._columns: list[np.ndarray] | None = None
        self._coarse_cells: dict[int, np.ndarray] = {}
        self._spread: np.ndarray | None = None

    @staticmethod
    def _shift_for(distance: float, fine: float) -> int:
        """Coarse cells of 2^shift fine cells, about a quarter of `distance` (at least 2)."""
        return max(1, int(np.floor(np.log2(max(distance / 4.0, fine) / fine))))

    def _grid(self, shift: int) -> tuple[float, np.ndarray, np.ndarray]:
        """(side, size, per vertex the flat index) of the coarse cells of 2^shift fine cells."""
        size = (self.top >> shift) + 1
        if shift not in self._coarse_cells:
            flat = (self._columns[0] >> shift).astype(np.int32)
            for axis in (1, 2):
                flat *= int(size[axis])
                flat += self._columns[axis] >> shift
            self._coarse_cells[shift] = flat
        return self.fine * 2.0 ** shift, size, self._coarse_cells[shift]

    def _prepare(self) -> None:
        """Per vertex its fine cell (int16 per axis); per face Σ_a (s_a + 1)² (0: not compact)."""
        cells = self.vertices - self.origin
        cells *= 1.0 / self.fine
        np.floor(cells, out=cells)
        np.clip(cells, 0, self.top, out=cells)
        columns = [cells[:, axis].astype(np.int16) for axis in range(3)]
        del cells
        self._columns = columns
        spread = np.zeros(len(self.faces), dtype=np.int16)
        compact = np.ones(len(self.faces), dtype=bool)
        a, b, c = self.faces[:, 0], self.faces[:, 1], self.faces[:, 2]
        for column in columns:
            x, y, z = column[a], column[b], column[c]
            axis = np.maximum(np.maximum(x, y), z)
            axis -= np.minimum(np.minimum(x, y), z)
            compact &= axis <= _COMPACT
            axis += 1
            axis *= axis
            spread += axis
        spread[~compact] = 0
        self._spread = spread

    def pairs(self, points: np.ndarray, distance: np.ndarray, tighten: bool = False
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(faces, rows, at, distance): `faces` ascending, and pairs (row, faces[at])
        containing every (query, face) with a point of the face within `distance` of the
        query; each ball lies inside the box. With `tighten`, a query's distance is first
        lowered to that of its nearest vertex if closer (a point of the surface, so still an
        upper bound on its distance to the surface); the distances used are returned."""
        if self._columns is None:
            self._prepare()
        points = np.asarray(points, dtype=np.float64)
        distance = np.asarray(distance, dtype=np.float64)
        reach = distance * (1.0 + _SLACK) + self.slack + self.margin
        # coarse cells for this call's typical reach, coarser while the queries' boxes span too many
        shift = max(self.shift, self._shift_for(float(np.median(reach)), self.fine))
        while shift < 14 and self._box_cells(points, reach, self.fine * 2.0 ** shift) > _MARK_LIMIT:
            shift += 1
        side, size, vertex_cells = self._grid(shift)
        cells, cell_rows = self._marks(points, reach, side, size)
        # the marked cells, and per vertex the slot of its cell among them (-1: not marked)
        boundary = np.flatnonzero(np.r_[True, cells[1:] != cells[:-1]])
        slot = np.full(int(np.prod(size)), -1, dtype=np.int32)
        slot[cells[boundary]] = np.arange(len(boundary), dtype=np.int32)
        slots = slot[vertex_cells]
        candidates = np.flatnonzero(slots >= 0)
        slots = slots[candidates]
        # every (candidate vertex, query that marked its cell), grouped by vertex
        count = np.diff(np.r_[boundary, len(cells)])[slots]
        start = np.cumsum(count) - count
        at = np.repeat(boundary[slots] - start, count) + np.arange(int(count.sum()))
        vertex_rows = cell_rows[at]
        offset = self.vertices[np.repeat(candidates, count)] - points[vertex_rows]
        gap = np.sqrt(np.einsum("ij,ij->i", offset, offset))
        if tighten:
            nearest = np.full(len(points), np.inf)
            np.minimum.at(nearest, vertex_rows, gap)
            distance = np.minimum(distance, nearest * (1.0 + _SLACK / 10))
        bounded = distance * (1.0 + _SLACK) + self.slack
        excess = gap - bounded[vertex_rows]
        least = np.full(len(self.vertices), np.inf, dtype=np.float32)  # rounding far below the slack
        least[candidates] = np.minimum.reduceat(excess, start) if len(excess) else np.inf
        # compact faces: every corner within its bound D_f (at most the margin); the others: always
        worst = np.maximum(np.maximum(least[self.faces[:, 0]], least[self.faces[:, 1]]), least[self.faces[:, 2]])
        compact = self._spread > 0
        faces = np.flatnonzero((worst <= self.margin) | ~compact)
        bound = self.fine * (1.0 + _SLACK) * np.sqrt(self._spread[faces]) + self.slack
        loose = ~compact[faces]
        kept = loose | (worst[faces] <= bound)
        faces, bound, loose = faces[kept], bound[kept], loose[kept]
        # a compact face pairs with the queries its first corner is near enough to
        tight = np.flatnonzero(~loose)
        position = np.zeros(len(self.vertices), dtype=np.int32)
        position[candidates] = np.arange(len(candidates), dtype=np.int32)
        corner = position[self.faces[faces[tight], 0]]
        n = count[corner]
        pair_at = np.repeat(start[corner] - (np.cumsum(n) - n), n) + np.arange(int(n.sum()))
        pair_face = np.repeat(tight, n)
        keep = excess[pair_at] <= bound[pair_face]
        rows, at = [vertex_rows[pair_at[keep]]], [pair_face[keep]]
        others = np.flatnonzero(loose)
        rows.append(np.tile(np.arange(len(points)), len(others)))
        at.append(np.repeat(others, len(points)))
        return faces, np.concatenate(rows), np.concatenate(at), distance

    def _box_cells(self, points: np.ndarray, reach: np.ndarray, side: float) -> int:
        """Cells of side `side` in the bounding boxes of the queries' balls, summed."""
        low = np.floor((points - reach[:, None] - self.origin) / side)
        high = np.floor((points + reach[:, None] - self.origin) / side)
        return int((high - low + 1).prod(axis=1).sum())

    def _marks(self, points: np.ndarray, reach: np.ndarray, side: float, size: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """(cell, row) of every coarse cell (of `side`, `size` per axis) whose box lies within
        `reach` of point `row`, sorted by cell (flat index)."""
        low = np.clip(np.floor((points - reach[:, None] - self.origin) / side).astype(np.int64), 0, size - 1)
        high = np.clip(np.floor((points + reach[:, None] - self.origin) / side).astype(np.int64), 0, size - 1)
        extent = high - low + 1
        count = extent.prod(axis=1)
        row = np.repeat(np.arange(len(points)), count)
        local = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
        ny, nz = extent[row, 1], extent[row, 2]
        cell = np.stack([low[row, 0] + local // (ny * nz), low[row, 1] + (local // nz) % ny, low[row, 2] + local % nz],
                        axis=1)
        box_low = self.origin + cell * side
        outside = np.maximum(np.maximum(box_low - points[row], points[row] - (box_low + side)), 0.0)
        keep = np.einsum("ij,ij->i", outside, outside) <= reach[row] ** 2
        flat = ((cell[:, 0] * size[1] + cell[:, 1]) * size[2] + cell[:, 2])[keep]
        order = np.argsort(flat, kind="stable")
        return flat[order], row[keep][order]


def _sampled_face_extent(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The 99th percentile of the largest axis extent of evenly spaced sampled faces (the
    fine cell side: about 99 % of the faces fit in it, and so are compact)."""
    sample = faces[np.linspace(0, len(faces) - 1, min(len(faces), _SAMPLE)).astype(np.int64)]
    corners = vertices[sample]
    extent = (corners.max(axis=1) - corners.min(axis=1)).max(axis=1)
    return float(np.quantile(extent, 0.99))
