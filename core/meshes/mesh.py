"""Triangle mesh type with validation, normals, areas and surface sampling.

`Mesh` is the one geometry type passed between every stage of the core. It is
immutable by convention (arrays are made read-only) and always valid:

* vertices: (V, 3) float64, all finite;
* faces: (F, 3) int32 (int64 beyond 2³¹ vertices), every index in [0, V), F >= 1, no
  degenerate triangle.

Faces are int32 and an array that is already read-only and of the right dtype is kept,
not copied (a mesh of a million vertices held its faces as int64 and every
`with_vertices` copied them). Per-face quantities are computed in chunks of
`FACE_CHUNK` faces (no (F, 3, 3) temporaries), and the used vertices come from a mask,
not a sort, so the cost stays linear in the mesh.

Build one with `Mesh.from_polygons` (triangulates polygons, drops degenerate faces and
counts what it did in `Mesh.report`) or `Mesh(vertices, faces)` for data already clean;
neither changes the vertex order (vertex i of the input is vertex i of the mesh). Meshes
read from files or Blender go through `intake.clean_mesh`, which also welds coincident
vertices and winds the faces outward; its `MeshReport` keeps the maps back to the input.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..base.errors import MeshError

if TYPE_CHECKING:
    from .layout import FaceLayout

__all__ = ["Mesh", "MeshReport", "MeshSizes", "SurfaceSamples", "triangle_cross", "cross_rows"]

#: Faces per chunk of the per-face computations (bounds their temporary memory).
FACE_CHUNK = 1 << 18

#: A triangle whose area is below this fraction of (mean edge length)^2 of the mesh is
#: treated as degenerate (zero area up to rounding) and dropped.
DEGENERATE_AREA_RTOL = 1e-12

#: A face whose shortest altitude is below this fraction of its longest edge (2 × area /
#: longest edge², scale-free) is a sliver: a needle or a flat cap that draws as a crack and
#: has no usable normal. Set well below the thinnest face of every clean mesh of PSB, TOSCA
#: and the procedural classes (`bench/cad.py --thinnest`, docs/results.md), which lose none.
SLIVER_RATIO = 1e-4


@dataclass(frozen=True, eq=False)
class MeshReport:
    """What intake changed on the way in: counts (zero when nothing happened) and the maps
    back to the input's elements (None: the identity, nothing was merged, dropped or turned).

    `vertex_map[i]` is the mesh vertex of input vertex i (welding merges coincident ones);
    `face_source[f]` the input triangle (after fan triangulation) that face f comes from;
    `face_reversed[f]` is True when face f's winding is the reverse of that triangle's
    (corners 1 and 2 swapped), not counting the reversal of a mirrored read (`mirrored`).
    A double-sided surface is one surface in the mesh: `twin_source[k]` is the input
    triangle of the k-th dropped side and `twin_of[k]` the mesh face it lay on, so the
    file's faces all map to a mesh face. Written files have one side.
    `layout` keeps the file's polygons and UVs (reading.read_mesh) so deformed copies, which
    keep the report (`Mesh.with_vertices`), are written with them.
    """

    polygons_triangulated: int = 0
    triangles_from_polygons: int = 0
    degenerate_faces_dropped: int = 0
    vertices_welded: int = 0  # input vertices merged into a coincident one
    mirrored: bool = False  # read through a mirroring transform (det < 0): every face reversed
    faces_rewound: int = 0  # faces reversed to agree with their neighbours
    parts_turned_outward: int = 0  # connected parts that faced inwards, reversed whole
    parts_without_inside: int = 0  # open, nearly flat parts: no side is outside, winding kept
    unorientable_parts: int = 0  # non-orientable parts (no winding makes all neighbours agree)
    unorientable_faces: int = 0  # their faces, each wound towards its own outside
    vertices_unused: int = 0  # vertices of the file no face uses (a file cut short between faces?)
    unterminated: bool = False  # the file's last line has no line end (valid OBJ, or a file cut short)
    sliver_faces_dropped: int = 0  # faces thinner than SLIVER_RATIO on a border or non-manifold edge
    sliver_faces_kept: int = 0  # such faces inside the surface (dropping one would open a hole)
    internal_faces_dropped: int = 0  # faces of sheets inside a closed volume (walls between cells)
    twin_faces_dropped: int = 0  # faces on the vertices of a kept face (a double-sided sheet's back)
    separate_parts: int = 1  # connected parts of the surface (handles, labels, decals)
    largest_part_share: float = 1.0  # the largest part's share of the surface area
    vertex_map: np.ndarray | None = field(default=None, repr=False)
    face_source: np.ndarray | None = field(default=None, repr=False)
    face_reversed: np.ndarray | None = field(default=None, repr=False)
    twin_source: np.ndarray | None = field(default=None, repr=False)  # input triangle of each dropped twin
    twin_of: np.ndarray | None = field(default=None, repr=False)  # the mesh face each dropped twin repeats
    layout: "FaceLayout | None" = field(default=None, repr=False)  # the file's polygons and UVs (core/meshes/layout.py)

    def summary(self) -> str:
        parts = []
        if self.polygons_triangulated:
            parts.append(
                f"{self.polygons_triangulated} polygon(s) triangulated into "
                f"{self.triangles_from_polygons} triangles"
            )
        if self.degenerate_faces_dropped:
            parts.append(f"{self.degenerate_faces_dropped} degenerate face(s) dropped")
        if self.vertices_welded:
            parts.append(f"{self.vertices_welded} duplicate vertices welded")
        if self.mirrored:
            parts.append("mirrored (negative scale): winding reversed")
        if self.parts_turned_outward:
            parts.append(f"{self.parts_turned_outward} inside-out part(s) turned outward")
        if self.faces_rewound:
            parts.append(f"{self.faces_rewound} face(s) re-wound to agree with their neighbours")
        if self.parts_without_inside:
            parts.append(f"{self.parts_without_inside} open flat part(s) with no outside: winding kept")
        if self.unorientable_parts:
            parts.append(f"{self.unorientable_parts} non-orientable part(s) ({self.unorientable_faces} faces, like a "
                         "Möbius strip) wound face by face, outward")
        if self.vertices_unused:
            parts.append(f"{self.vertices_unused} vertices used by no face (kept; is the file cut short?)")
        if self.unterminated:
            parts.append("its last line has no line end (read as it is; is the file cut short?)")
        if self.sliver_faces_dropped:
            parts.append(f"{self.sliver_faces_dropped} loose sliver face(s) dropped (thinner than {SLIVER_RATIO:g} of "
                         "their longest edge)")
        if self.sliver_faces_kept:
            parts.append(f"{self.sliver_faces_kept} sliver face(s) inside the surface kept (dropping them would open it)")
        if self.internal_faces_dropped:
            parts.append(f"{self.internal_faces_dropped} internal face(s) (walls inside a closed volume) left out of "
                         "the surface")
        if self.twin_faces_dropped:
            parts.append(f"{self.twin_faces_dropped} double-sided or repeated face(s) read as one surface "
                         "(samples are written one-sided)")
        if self.separate_parts > 1:
            parts.append(f"{self.separate_parts} separate parts (the largest {100 * self.largest_part_share:.1f} % "
                         "of the area; the others, e.g. labels or handles, are deformed with it)")
        return "; ".join(parts) if parts else "clean"


@dataclass(frozen=True)
class SurfaceSamples:
    """Points on a mesh surface: position, the face each lies on and its barycentrics."""

    points: np.ndarray  # (n, 3)
    face_index: np.ndarray  # (n,)
    barycentric: np.ndarray  # (n, 3), rows sum to 1


class MeshSizes:
    """What a mesh and a handle of one kept on disk (core/meshes/spill.py) both answer from their
    `vertices` and `faces` shapes and their `bounds()`."""

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def bbox_diagonal(self) -> float:
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))


@dataclass(frozen=True, eq=False)
class Mesh(MeshSizes):
    """A valid triangle mesh (see module docstring for the invariants)."""

    vertices: np.ndarray
    faces: np.ndarray
    name: str = ""
    report: MeshReport = field(default_factory=MeshReport)

    def __post_init__(self):
        label = self.name or "mesh"
        vertices = _frozen(self.vertices, np.float64)
        faces_in = np.asarray(self.faces)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise MeshError(f"{label}: vertices must have shape (V, 3), got {vertices.shape}")
        if vertices.shape[0] == 0:
            raise MeshError(f"{label}: mesh is empty (no vertices)")
        bad = ~np.isfinite(vertices).all(axis=1)
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise MeshError(
                f"{label}: {int(bad.sum())} vertex coordinate row(s) are NaN or infinite "
                f"(first: vertex {first})"
            )
        if faces_in.size == 0:
            raise MeshError(f"{label}: mesh has no faces")
        if faces_in.ndim != 2 or faces_in.shape[1] != 3:
            raise MeshError(
                f"{label}: faces must be triangles of shape (F, 3), got {faces_in.shape}; "
                "use Mesh.from_polygons for polygons"
            )
        if not np.issubdtype(faces_in.dtype, np.integer):
            if not np.all(np.equal(np.mod(faces_in, 1), 0)):
                raise MeshError(f"{label}: face indices must be integers")
        faces = _frozen(faces_in, face_dtype(vertices.shape[0]))
        _check_face_indices(faces, vertices.shape[0], label)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces)

    def __setstate__(self, state: dict) -> None:
        """Unpickled (a mesh sent to or from a worker process): read-only again."""
        self.__dict__.update(state)
        for key in ("vertices", "faces"):
            state[key].flags.writeable = False

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_polygons(
        cls,
        vertices: np.ndarray,
        polygons: np.ndarray | Sequence[Sequence[int]],
        name: str = "",
    ) -> "Mesh":
        """Validate raw data: fan-triangulate polygons, drop degenerate triangles.

        Raises MeshError naming `name` when nothing usable remains.
        """
        label = name or "mesh"
        vertices = np.asarray(vertices, dtype=np.float64)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise MeshError(f"{label}: vertices must have shape (V, 3), got {vertices.shape}")
        if vertices.shape[0] == 0:
            raise MeshError(f"{label}: mesh is empty (no vertices)")
        triangles, n_poly, n_from_poly = _triangulate(polygons, label)
        if triangles.shape[0] == 0:
            raise MeshError(f"{label}: mesh has no faces")
        # index range is checked before area so the error names the real problem
        _check_face_indices(triangles, vertices.shape[0], label)
        if not np.isfinite(vertices).all():
            first = int(np.flatnonzero(~np.isfinite(vertices).all(axis=1))[0])
            raise MeshError(f"{label}: vertex {first} has a NaN or infinite coordinate")
        keep = ~_degenerate_mask(vertices, triangles)
        n_dropped = int((~keep).sum())
        if n_dropped:
            triangles = triangles[keep]
        if triangles.shape[0] == 0:
            raise MeshError(f"{label}: every face is degenerate (zero area or repeated vertex)")
        report = MeshReport(n_poly, n_from_poly, n_dropped,
                            face_source=np.flatnonzero(keep) if n_dropped else None)
        return cls(vertices, triangles, name=name, report=report)

    def with_vertices(self, vertices: np.ndarray, name: str | None = None) -> "Mesh":
        """Same connectivity, new vertex positions (e.g. after a transform)."""
        return Mesh(vertices, self.faces, name=self.name if name is None else name,
                    report=self.report)

    # ------------------------------------------------------------------ geometry
    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) corner coordinates of every face."""
        return self.vertices[self.faces]

    def face_corners(self, faces: np.ndarray) -> np.ndarray:
        """(n, 3, 3) corner coordinates of the given faces only."""
        return self.vertices[self.faces[faces]]

    def face_normals_unnormalised(self) -> np.ndarray:
        """Cross products (b - a) x (c - a); length = 2 * area."""
        out = np.empty((self.n_faces, 3))
        for start in range(0, self.n_faces, FACE_CHUNK):
            out[start:start + FACE_CHUNK] = triangle_cross(self.vertices, self.faces[start:start + FACE_CHUNK])
        return out

    def face_areas(self) -> np.ndarray:
        """Area of every face, (F,)."""
        out = np.empty(self.n_faces)
        for start in range(0, self.n_faces, FACE_CHUNK):
            cross = triangle_cross(self.vertices, self.faces[start:start + FACE_CHUNK])
            out[start:start + FACE_CHUNK] = 0.5 * np.linalg.norm(cross, axis=1)
        return out

    def area(self) -> float:
        """Total surface area (computed once per mesh)."""
        return self.cached("area", lambda mesh: float(mesh.face_areas().sum()))

    def face_normals(self) -> np.ndarray:
        """Unit normals, (F, 3), right-hand rule over the face's vertex order."""
        n = self.face_normals_unnormalised()
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted unit vertex normals, (V, 3); isolated vertices get (0, 0, 0)."""
        n = self.face_normals_unnormalised()  # weight by 2*area implicitly
        acc = np.zeros_like(self.vertices)
        for corner in range(3):  # summed in this order (the results of every stage depend on its last bits)
            np.add.at(acc, self.faces[:, corner], n)
        length = np.linalg.norm(acc, axis=1, keepdims=True)
        return np.divide(acc, length, out=np.zeros_like(acc), where=length > 0)

    def bounds(self) -> np.ndarray:
        """(2, 3): min and max corner of the axis-aligned bounding box of used vertices
        (computed once per mesh: the mesh is immutable)."""
        return self.cached("bounds", _used_bounds).copy()

    def cached(self, key: str, compute):
        """`compute(self)`, computed once per mesh and kept (the mesh is immutable): for
        small derived values (bounds, surface moments) that several stages ask for."""
        store = self.__dict__.setdefault("_cached", {})
        if key not in store:
            store[key] = compute(self)
        return store[key]

    def used_vertices(self) -> np.ndarray:
        """Sorted indices of the vertices some face uses (`np.unique(faces)`, by a mask)."""
        used = np.zeros(self.n_vertices, dtype=bool)
        used[self.faces.ravel()] = True
        return np.flatnonzero(used)

    def _face_edges(self) -> np.ndarray:
        """(3F, 2) the edge of every face corner, smaller index first (shared edges repeat)."""
        e = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        e.sort(axis=1)
        return e

    def edges_unique(self) -> np.ndarray:
        """(E, 2) undirected edges, each once, smaller index first (sorted)."""
        keys = np.unique(self._edge_keys())
        return np.stack([keys // self.n_vertices, keys % self.n_vertices], axis=1).astype(self.faces.dtype)

    def is_closed(self) -> bool:
        """True when every edge is shared by exactly two faces (a closed 2-manifold surface)."""
        _, counts = np.unique(self._edge_keys(), return_counts=True)
        return bool(np.all(counts == 2))

    def _edge_keys(self) -> np.ndarray:
        """(3F,) int64 key a · V + b of every face corner's edge (a < b)."""
        edges = self._face_edges().astype(np.int64)
        return edges[:, 0] * self.n_vertices + edges[:, 1]

    def mean_edge_length(self) -> float:
        e = self.edges_unique()
        return float(np.linalg.norm(self.vertices[e[:, 0]] - self.vertices[e[:, 1]], axis=1).mean())

    # ------------------------------------------------------------------ sampling
    def sample_surface(self, n: int, rng: np.random.Generator) -> SurfaceSamples:
        """`n` points uniformly distributed over the surface (area-weighted).

        A face is drawn with probability area / total area, then a point uniformly in it
        via the square-root barycentric map (Osada et al. 2002).
        """
        if n < 1:
            raise ValueError(f"{self.name or 'mesh'}: sample count must be >= 1, got {n}")
        areas = self.face_areas()
        cdf = np.cumsum(areas)
        cdf /= cdf[-1]
        face_index = np.searchsorted(cdf, rng.random(n), side="right")
        face_index = np.minimum(face_index, self.n_faces - 1)
        r1 = np.sqrt(rng.random(n))
        r2 = rng.random(n)
        bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
        tri = self.vertices[self.faces[face_index]]
        points = np.einsum("nk,nkd->nd", bary, tri)
        return SurfaceSamples(points, face_index.astype(np.int64), bary)


def _used_bounds(mesh: Mesh) -> np.ndarray:
    used = mesh.vertices[mesh.used_vertices()]
    return np.stack([used.min(axis=0), used.max(axis=0)])


def face_dtype(n_vertices: int):
    """The dtype of a mesh's faces: int32, int64 for more than 2³¹ − 1 vertices."""
    return np.int32 if n_vertices <= np.iinfo(np.int32).max else np.int64


def _frozen(array, dtype) -> np.ndarray:
    """`array` as a read-only array of `dtype`: itself when it is one already and nothing
    can write to it (its memory is read-only too), else a read-only copy."""
    if isinstance(array, np.ndarray) and array.dtype == dtype and not array.flags.writeable:
        base = array
        while isinstance(base, np.ndarray) and base.base is not None:
            base = base.base
        if isinstance(base, np.ndarray) and not base.flags.writeable:
            return array
    out = np.array(array, dtype=dtype, copy=True)
    out.flags.writeable = False
    return out


def triangle_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) cross products (b − a) × (c − a) of the given faces (length 2 × area),
    component by component (no (F, 3, 3) array)."""
    a = vertices[faces[:, 0]]
    return cross_rows(vertices[faces[:, 1]] - a, vertices[faces[:, 2]] - a)


def cross_rows(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise u × v of (n, 3) arrays."""
    return np.stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1], u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
                     u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]], axis=1)


def _check_face_indices(faces: np.ndarray, n_vertices: int, label: str) -> None:
    """MeshError naming the first face whose vertex index is outside [0, n_vertices)."""
    if faces.size and faces.min() >= 0 and faces.max() < n_vertices:
        return
    out_of_range = (faces < 0) | (faces >= n_vertices)
    if out_of_range.any():
        row = int(np.flatnonzero(out_of_range.any(axis=1))[0])
        raise MeshError(f"{label}: face {row} has vertex index {faces[row].tolist()} out of range [0, {n_vertices})")


def _triangulate(polygons, label: str) -> tuple[np.ndarray, int, int]:
    """Fan-triangulate polygons. Returns (triangles, n_polygons_split, n_triangles_made)."""
    if isinstance(polygons, np.ndarray) and polygons.ndim == 2:
        if polygons.shape[1] == 3:
            return polygons, 0, 0
        if polygons.shape[1] < 3:
            raise MeshError(f"{label}: faces need at least 3 vertices, got {polygons.shape[1]}")
        polygons = polygons.tolist()
    triangles: list[tuple[int, int, int]] = []
    n_poly = 0
    n_made = 0
    for index, poly in enumerate(polygons):
        poly = [int(v) for v in poly]
        if len(poly) < 3:
            raise MeshError(f"{label}: face {index} has {len(poly)} vertices; a face needs at least 3")
        if len(poly) == 3:
            triangles.append((poly[0], poly[1], poly[2]))
            continue
        n_poly += 1
        for k in range(1, len(poly) - 1):
            triangles.append((poly[0], poly[k], poly[k + 1]))
            n_made += 1
    return np.asarray(triangles, dtype=np.int64).reshape(-1, 3), n_poly, n_made


def _degenerate_mask(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """True for triangles with a repeated vertex index or (numerically) zero area."""
    repeated = (
        (triangles[:, 0] == triangles[:, 1])
        | (triangles[:, 1] == triangles[:, 2])
        | (triangles[:, 2] == triangles[:, 0])
    )
    twice_area = np.empty(len(triangles))
    edge_sq = np.empty(len(triangles))
    for start in range(0, len(triangles), FACE_CHUNK):
        part = triangles[start:start + FACE_CHUNK]
        a, b, c = vertices[part[:, 0]], vertices[part[:, 1]], vertices[part[:, 2]]
        u, v, w = b - a, c - a, c - b
        cross = cross_rows(u, v)
        twice_area[start:start + FACE_CHUNK] = np.linalg.norm(cross, axis=1)
        edge_sq[start:start + FACE_CHUNK] = (u ** 2).sum(axis=1) + (w ** 2).sum(axis=1) + (v ** 2).sum(axis=1)
    scale = max(float(np.median(edge_sq)), np.finfo(float).tiny) if len(edge_sq) else 1.0
    flat = twice_area <= DEGENERATE_AREA_RTOL * scale
    return repeated | flat
