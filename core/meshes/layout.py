"""A mesh's faces as its file had them: polygons (quads, n-gons) and UVs per face corner.

The core works on welded triangles (`Mesh`); a `FaceLayout` remembers how the file laid the
same surface out, so a deformed copy is written with the file's own faces and UVs:

* `vertex_map` (Vf,): the mesh vertex of each file vertex (welding merges coincident file
  vertices, e.g. the copies a glTF file makes along UV seams);
* `sizes` (P,) and `corners` (C,): the file's polygons, corner by corner, as file vertex
  indices, each wound like the mesh's faces (a polygon the intake turned outward is
  stored turned, its first corner kept);
* `uv` (C, 2): the texture coordinates of every corner, or None.

A deformed copy with mesh vertices X is the file's vertices at X[vertex_map] with the same
polygons and UVs (`positions`). Arrays of many layouts pack into one model file
(`pack_layouts` / `unpack_layouts`). A double-sided surface is laid out one-sided
(`one_sided`): the mesh has one surface there, and written files have no coincident twins.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..base.errors import ModelFileError, ShapeGenError

__all__ = ["FaceLayout", "pack_layouts", "unpack_layouts", "LAYOUT_KEYS"]


@dataclass(frozen=True, eq=False)
class FaceLayout:
    """The file's polygons and UVs of one mesh (module docstring)."""

    vertex_map: np.ndarray
    sizes: np.ndarray
    corners: np.ndarray
    uv: np.ndarray | None = None

    def __post_init__(self):
        vertex_map = np.asarray(self.vertex_map, dtype=np.int64)
        sizes = np.asarray(self.sizes, dtype=np.int64)
        corners = np.asarray(self.corners, dtype=np.int64)
        if vertex_map.ndim != 1 or sizes.ndim != 1 or corners.ndim != 1:
            raise ShapeGenError("a face layout's vertex map, sizes and corners must be flat arrays")
        if len(sizes) == 0 or sizes.min() < 3 or sizes.sum() != len(corners):
            raise ShapeGenError("a face layout's polygons need at least 3 corners each and must add up to its corners")
        if corners.min() < 0 or corners.max() >= len(vertex_map) or vertex_map.min() < 0:
            raise ShapeGenError("a face layout's corner refers to a vertex outside its file")
        uv = None if self.uv is None else np.asarray(self.uv, dtype=np.float64)
        if uv is not None and uv.shape != (len(corners), 2):
            raise ShapeGenError(f"a face layout's UVs must be one (u, v) per corner ({len(corners)}), got {uv.shape}")
        for name, value in (("vertex_map", vertex_map), ("sizes", sizes), ("corners", corners), ("uv", uv)):
            object.__setattr__(self, name, value)

    @classmethod
    def wound_like(cls, vertex_map, sizes, corners, uv, faces: np.ndarray) -> "FaceLayout":
        """A layout whose polygons run like the mesh's `faces` (F, 3): each polygon edge
        a→b is compared with the mesh triangle on the polygon's side of it (the one whose
        third corner is also a corner of the polygon), and a polygon whose edges mostly run
        against its own triangles is reversed (first corner kept)."""
        layout = cls(vertex_map, sizes, corners, uv)
        faces = np.asarray(faces, dtype=np.int64)
        n = int(max(faces.max(), layout.vertex_map.max())) + 1
        half_key = faces.ravel() * n + faces[:, [1, 2, 0]].ravel()  # half-edge a→b of each face corner
        third = faces[:, [2, 0, 1]].ravel()  # the face's corner opposite that half-edge
        order = np.argsort(half_key, kind="stable")
        half_key, third = half_key[order], third[order]
        polygon = np.repeat(np.arange(len(layout.sizes)), layout.sizes)
        start = layout.vertex_map[layout.corners]
        end = start[layout._next_corner()]
        members = np.unique(polygon * n + start)

        def own_side(keys):
            """True where half-edge `keys` exists and its face lies inside the polygon."""
            at = np.minimum(np.searchsorted(half_key, keys), len(half_key) - 1)
            return (half_key[at] == keys) & np.isin(polygon * n + third[at], members)

        vote = np.bincount(polygon, own_side(end * n + start).astype(np.int64)
                           - own_side(start * n + end).astype(np.int64), len(layout.sizes))
        return layout.reversed(vote > 0) if (vote > 0).any() else layout

    def one_sided(self) -> "FaceLayout":
        """The layout without the polygons on the same mesh vertices as an earlier one (the
        back of a double-sided sheet, or a repeat): written, the two would be coincident
        faces that z-fight. The first polygon of each vertex set is kept."""
        on_mesh = self.vertex_map[self.corners]
        polygon = np.repeat(np.arange(len(self.sizes)), self.sizes)
        repeat = np.zeros(len(self.sizes), dtype=bool)
        for size in np.unique(self.sizes):
            members = np.flatnonzero(self.sizes == size)
            rows = np.sort(on_mesh[np.isin(polygon, members)].reshape(-1, size), axis=1)
            _, first = np.unique(rows, axis=0, return_index=True)
            repeat[members] = True
            repeat[members[first]] = False
        if not repeat.any():
            return self
        keep_corner = ~repeat[polygon]
        return FaceLayout(self.vertex_map, self.sizes[~repeat], self.corners[keep_corner],
                          None if self.uv is None else self.uv[keep_corner])

    def _first_corner(self) -> np.ndarray:
        return np.cumsum(self.sizes) - self.sizes

    def _next_corner(self) -> np.ndarray:
        """(C,): the index of the corner after each corner in its polygon."""
        index = np.arange(len(self.corners))
        last = np.cumsum(self.sizes) - 1
        following = index + 1
        following[last] = self._first_corner()
        return following

    def reversed(self, flip: np.ndarray) -> "FaceLayout":
        """The layout with polygons `flip` (P,) bool wound the other way, first corner kept."""
        first = np.repeat(self._first_corner(), self.sizes)
        local = np.arange(len(self.corners)) - first
        size = np.repeat(self.sizes, self.sizes)
        source = np.where(np.repeat(flip, self.sizes), first + (size - local) % size, first + local)
        return FaceLayout(self.vertex_map, self.sizes, self.corners[source],
                          None if self.uv is None else self.uv[source])

    @property
    def n_file_vertices(self) -> int:
        return len(self.vertex_map)

    def positions(self, vertices: np.ndarray) -> np.ndarray:
        """(Vf, 3): the file vertices of a deformed copy with mesh vertices `vertices`."""
        return np.asarray(vertices)[self.vertex_map]

    def polygons(self) -> list[np.ndarray]:
        """The polygons as lists of file vertex indices."""
        return np.split(self.corners, np.cumsum(self.sizes)[:-1])

    def triangles(self) -> np.ndarray:
        """(T, 3): the polygons fan-triangulated, in file vertex indices (for formats of
        triangles only)."""
        first = np.repeat(self._first_corner(), self.sizes - 2)
        offset = np.concatenate([np.arange(1, s - 1) for s in self.sizes])
        return self.corners[np.stack([first, first + offset, first + offset + 1], axis=1)]

    def vertex_uv(self) -> np.ndarray | None:
        """(Vf, 2): UVs per file vertex, when every corner of a vertex has the same UV (as
        PLY and glTF store them); None otherwise or without UVs."""
        if self.uv is None:
            return None
        per_vertex = np.full((self.n_file_vertices, 2), np.nan)
        per_vertex[self.corners] = self.uv
        if np.isnan(per_vertex[self.corners]).any() or not np.allclose(per_vertex[self.corners], self.uv):
            return None
        return np.nan_to_num(per_vertex)


LAYOUT_KEYS = ("layout_present", "layout_vertex_map", "layout_vertex_offsets", "layout_sizes",
               "layout_polygon_offsets", "layout_corners", "layout_corner_offsets", "layout_uv", "layout_has_uv")


def pack_layouts(layouts: Sequence[FaceLayout | None], prefix: str = "") -> dict[str, np.ndarray]:
    """Flat arrays of many layouts (None: a mesh without one): concatenated vertex maps,
    polygon sizes, corners and per-corner UVs (zeros where a layout has none), with
    offsets (M + 1 each) and flags (M,)."""
    present = [layout is not None for layout in layouts]
    kept = [layout for layout in layouts if layout is not None]

    def offsets(counts):
        return np.cumsum([0] + list(counts)).astype(np.int64)

    def concat(parts, dtype, shape=()):
        return np.concatenate(parts).astype(dtype) if parts else np.empty((0, *shape), dtype=dtype)

    arrays = {
        "layout_present": np.asarray(present, dtype=bool),
        "layout_vertex_map": concat([l.vertex_map for l in kept], np.int64),
        "layout_vertex_offsets": offsets(l.n_file_vertices for l in kept),
        "layout_sizes": concat([l.sizes for l in kept], np.int64),
        "layout_polygon_offsets": offsets(len(l.sizes) for l in kept),
        "layout_corners": concat([l.corners for l in kept], np.int64),
        "layout_corner_offsets": offsets(len(l.corners) for l in kept),
        "layout_uv": concat([l.uv if l.uv is not None else np.zeros((len(l.corners), 2)) for l in kept],
                            np.float64, (2,)),
        "layout_has_uv": np.asarray([l.uv is not None for l in kept], dtype=bool),
    }
    return {f"{prefix}{key}": value for key, value in arrays.items()}


def unpack_layouts(arrays, n_meshes: int, label: str, prefix: str = "") -> list[FaceLayout | None]:
    """The layouts of `pack_layouts`' arrays ([None] * n_meshes when the file has none);
    inconsistent arrays raise ModelFileError starting with `label`."""
    if f"{prefix}layout_present" not in arrays:
        return [None] * n_meshes
    get = {key: np.asarray(arrays[f"{prefix}{key}"]) for key in LAYOUT_KEYS}
    present = get["layout_present"]
    if present.shape != (n_meshes,) or present.dtype != bool:
        raise ModelFileError(f"{label}: layout flags do not match the {n_meshes} meshes")
    k = int(present.sum())
    try:
        cuts = {}
        for key, offsets_key in (("layout_vertex_map", "layout_vertex_offsets"),
                                 ("layout_sizes", "layout_polygon_offsets"),
                                 ("layout_corners", "layout_corner_offsets"), ("layout_uv", "layout_corner_offsets")):
            offsets = get[offsets_key]
            if len(offsets) != k + 1 or offsets[0] != 0 or offsets[-1] != len(get[key]) or np.any(np.diff(offsets) < 0):
                raise ModelFileError(f"{label}: {offsets_key} do not match the layouts and their data")
            cuts[key] = [get[key][offsets[i]:offsets[i + 1]] for i in range(k)]
        if get["layout_has_uv"].shape != (k,):
            raise ModelFileError(f"{label}: layout UV flags do not match the layouts")
        made = iter(FaceLayout(cuts["layout_vertex_map"][i], cuts["layout_sizes"][i], cuts["layout_corners"][i],
                               cuts["layout_uv"][i] if get["layout_has_uv"][i] else None) for i in range(k))
        return [next(made) if flag else None for flag in present]
    except ShapeGenError as exc:
        if isinstance(exc, ModelFileError):
            raise
        raise ModelFileError(f"{label}: a face layout is invalid: {exc}") from None
