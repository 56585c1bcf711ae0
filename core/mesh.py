"""Triangle mesh type with validation, normals, areas and surface sampling.

`Mesh` is the one geometry type passed between every stage of the core. It is
immutable by convention (arrays are made read-only) and always valid:

* vertices: (V, 3) float64, all finite;
* faces: (F, 3) int64, every index in [0, V), F >= 1, no degenerate triangle.

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

from .errors import MeshError

if TYPE_CHECKING:
    from .layout import FaceLayout

__all__ = ["Mesh", "MeshReport", "SurfaceSamples"]

#: A triangle whose area is below this fraction of (mean edge length)^2 of the mesh is
#: treated as degenerate (zero area up to rounding) and dropped.
DEGENERATE_AREA_RTOL = 1e-12


@dataclass(frozen=True, eq=False)
class MeshReport:
    """What intake changed on the way in: counts (zero when nothing happened) and the maps
    back to the input's elements (None: the identity, nothing was merged, dropped or turned).

    `vertex_map[i]` is the mesh vertex of input vertex i (welding merges coincident ones);
    `face_source[f]` the input triangle (after fan triangulation) that face f comes from;
    `face_reversed[f]` is True when face f's winding is the reverse of that triangle's
    (corners 1 and 2 swapped), not counting the reversal of a mirrored read (`mirrored`).
    `layout` keeps the file's polygons and UVs (io.read_mesh) so deformed copies, which
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
    vertex_map: np.ndarray | None = field(default=None, repr=False)
    face_source: np.ndarray | None = field(default=None, repr=False)
    face_reversed: np.ndarray | None = field(default=None, repr=False)
    layout: "FaceLayout | None" = field(default=None, repr=False)  # the file's polygons and UVs (core/layout.py)

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
        return "; ".join(parts) if parts else "clean"


@dataclass(frozen=True)
class SurfaceSamples:
    """Points on a mesh surface: position, the face each lies on and its barycentrics."""

    points: np.ndarray  # (n, 3)
    face_index: np.ndarray  # (n,)
    barycentric: np.ndarray  # (n, 3), rows sum to 1


@dataclass(frozen=True, eq=False)
class Mesh:
    """A valid triangle mesh (see module docstring for the invariants)."""

    vertices: np.ndarray
    faces: np.ndarray
    name: str = ""
    report: MeshReport = field(default_factory=MeshReport)

    def __post_init__(self):
        label = self.name or "mesh"
        vertices = np.array(self.vertices, dtype=np.float64, copy=True)
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
        faces = faces_in.astype(np.int64, copy=True)
        _check_face_indices(faces, vertices.shape[0], label)
        vertices.flags.writeable = False
        faces.flags.writeable = False
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "faces", faces)

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
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) corner coordinates of every face."""
        return self.vertices[self.faces]

    def face_normals_unnormalised(self) -> np.ndarray:
        """Cross products (b - a) x (c - a); length = 2 * area."""
        tri = self.triangles
        return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])

    def face_areas(self) -> np.ndarray:
        """Area of every face, (F,)."""
        return 0.5 * np.linalg.norm(self.face_normals_unnormalised(), axis=1)

    def area(self) -> float:
        return float(self.face_areas().sum())

    def face_normals(self) -> np.ndarray:
        """Unit normals, (F, 3), right-hand rule over the face's vertex order."""
        n = self.face_normals_unnormalised()
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted unit vertex normals, (V, 3); isolated vertices get (0, 0, 0)."""
        n = self.face_normals_unnormalised()  # weight by 2*area implicitly
        acc = np.zeros_like(self.vertices)
        for corner in range(3):
            np.add.at(acc, self.faces[:, corner], n)
        length = np.linalg.norm(acc, axis=1, keepdims=True)
        return np.divide(acc, length, out=np.zeros_like(acc), where=length > 0)

    def bounds(self) -> np.ndarray:
        """(2, 3): min and max corner of the axis-aligned bounding box of used vertices."""
        used = self.vertices[np.unique(self.faces)]
        return np.stack([used.min(axis=0), used.max(axis=0)])

    def bbox_diagonal(self) -> float:
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    def _face_edges(self) -> np.ndarray:
        """(3F, 2) the edge of every face corner, smaller index first (shared edges repeat)."""
        e = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]], self.faces[:, [2, 0]]])
        e.sort(axis=1)
        return e

    def edges_unique(self) -> np.ndarray:
        """(E, 2) undirected edges, each once, smaller index first."""
        return np.unique(self._face_edges(), axis=0)

    def is_closed(self) -> bool:
        """True when every edge is shared by exactly two faces (a closed 2-manifold surface)."""
        _, counts = np.unique(self._face_edges(), axis=0, return_counts=True)
        return bool(np.all(counts == 2))

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
        tri = self.triangles[face_index]
        points = np.einsum("nk,nkd->nd", bary, tri)
        return SurfaceSamples(points, face_index.astype(np.int64), bary)


def _check_face_indices(faces: np.ndarray, n_vertices: int, label: str) -> None:
    """MeshError naming the first face whose vertex index is outside [0, n_vertices)."""
    out_of_range = (faces < 0) | (faces >= n_vertices)
    if out_of_range.any():
        row = int(np.flatnonzero(out_of_range.any(axis=1))[0])
        raise MeshError(f"{label}: face {row} has vertex index {faces[row].tolist()} out of range [0, {n_vertices})")


def _triangulate(polygons, label: str) -> tuple[np.ndarray, int, int]:
    """Fan-triangulate polygons. Returns (triangles, n_polygons_split, n_triangles_made)."""
    if isinstance(polygons, np.ndarray) and polygons.ndim == 2:
        if polygons.shape[1] == 3:
            return polygons.astype(np.int64), 0, 0
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
    tri = vertices[triangles]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    twice_area = np.linalg.norm(cross, axis=1)
    edge_sq = (
        ((tri[:, 1] - tri[:, 0]) ** 2).sum(axis=1)
        + ((tri[:, 2] - tri[:, 1]) ** 2).sum(axis=1)
        + ((tri[:, 0] - tri[:, 2]) ** 2).sum(axis=1)
    )
    scale = max(float(np.median(edge_sq)), np.finfo(float).tiny) if len(edge_sq) else 1.0
    flat = twice_area <= DEGENERATE_AREA_RTOL * scale
    return repeated | flat
