"""The quality gate: is a generated mesh one an artist can use?

Every generated mesh is a deformed copy of a template training mesh (same faces, new
positions, §6), so it is judged against that template and against the training shapes:

* flipped triangles: a face whose normal points against the template face's normal
  (n_sample · n_template ≤ 0; a face collapsed to zero area counts too). The training
  shapes are aligned (§3.4), so no face of a sound sample turns by more than 90°;
* edge-length distortion: r_e = log(ℓ_e / ℓ⁰_e) per template edge, minus its median (the
  sample's overall scale); the largest |r_e| and its 99th percentile;
* self-intersections: face pairs that cross (geometry/intersections.py) where the template
  does not cross. A mug's handle pushed into its body is the artist's choice: crossings
  between two connected parts that already cross in the template do not count, wherever
  along them the crossing moves; within one part, crossings near (within two rings of)
  the template's own crossings do not count either. Any other crossing is a fold;
* extent: the sample's bounding-box extents per axis and its diagonal against the
  smallest and largest of the training shapes' (all in the model's normalised frame);
* roughness: the mean angle between the normals of faces sharing an edge, the sample's
  over the template's (a crumpled shoulder renders as dark creases);
* coincident faces: pairs of faces lying on top of each other (every corner of one within
  1e-6 of the bounding-box diagonal of a corner of the other), which z-fight when drawn.

`QualityGate.check(mesh, template_index)` returns a `MeshQuality` with these numbers and
its reasons for failing (empty: it passes). The template's own intersections, normals and
edge lengths are computed once per template.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..base.errors import ShapeGenError
from ..geometry.intersections import intersecting_pairs, pair_keys
from scipy.spatial import cKDTree

from ..meshes.winding import shared_edges
from ..meshes.mesh import Mesh, triangle_cross
from ..base.settings import Settings, option

__all__ = ["QualitySettings", "MeshQuality", "QualityGate", "training_extents"]


@dataclass(frozen=True)
class QualitySettings(Settings):
    """Thresholds of the quality gate (a sample failing any one is redrawn).

    max_flipped: flipped or collapsed faces a sample may have. 0: a single flipped face is
        a visible crease in shading, and sound samples have none (bench/samples.py).
    max_edge_stretch: largest |log(ℓ/ℓ⁰) − median| over the template's edges. ln 4 ≈ 1.39:
        no edge 4× longer or shorter than the template's relative to the sample's overall
        scale. Training shapes meshed from the model (their own landmarks through another
        template) stay below about 0.9 (ratio 2.5) on every class measured.
    max_edge_stretch_p99: the same at the 99th percentile over edges (a wide region
        stretched): ln 2 ≈ 0.69, a region at twice or half its template's edge lengths.
    check_self_intersections: search for new crossing face pairs (the slowest check,
        about 20-60 ms for 10-20k faces); off skips it.
    max_self_intersections: crossing face pairs beyond the template's own. 0.
    extent_tolerance: a sample's extent along each axis (and its diagonal) may exceed the
        largest training shape's by this fraction and fall short of the smallest's by
        the same fraction (1/(1+t)). 0.5: samples extrapolate a little beyond the
        training range; an explosion (the mug sample that became a disc 5× the class's
        size) is far outside it.
    stiffer_remesh: a draw that fails on its nearest templates is meshed again on them at
        this many times the model's final α before it is redrawn (core/generate/sampling.py). 2: on
        PSB Cup at α 5, 23 of 24 draws that failed on 3 templates pass at α 10, which keeps
        the draw (the sample's distribution) and costs landmark fidelity only where the
        soft mesh folds. 1 skips it.
    max_roughness_ratio: the sample's roughness (mean angle between the normals of
        edge-adjacent faces) over its template's. 1.5 (docs/results.md: clean classes'
        samples stay below it).
    max_coincident_faces: face pairs on top of each other a sample may have. 0: each pair
        z-fights (a checkerboard of dark triangles in a viewport).
    max_redraws: redraws per requested sample, pooled over the run: a run of n samples
        makes at most n·(1 + max_redraws) draws in all (core/generate/sampling.py, `draw_budget`),
        each sample first getting 1 + max_redraws and those still failing sharing what the
        passing ones left. 20: where half the draws pass, a sample's own 21 draws all
        fail about once in two million (0.5^21), and a run that cannot pass stops after
        21 draws per sample. A run in which a sample still fails when they are spent writes
        nothing (`shapegen sample` exits 2) or, in Blender, adds only the passing ones.
    """

    max_flipped: int = option(0, "flipped or collapsed faces a sample may have", minimum=0)
    max_edge_stretch: float = option(float(np.log(4.0)), "largest |log edge-length ratio| against the template "
                                     "(after the sample's overall scale)", above=0)
    max_edge_stretch_p99: float = option(float(np.log(2.0)), "99th percentile of |log edge-length ratio|",
                                         above=0)
    check_self_intersections: bool = option(True, "count crossing face pairs (the slowest check)")
    max_self_intersections: int = option(0, "crossing face pairs beyond the template's own", minimum=0)
    extent_tolerance: float = option(0.5, "fraction by which a sample's extents may leave the training range",
                                     minimum=0)
    stiffer_remesh: float = option(2.0, "factor on the meshing stiffness (final α) for a last re-mesh of a "
                                   "failing draw before it is redrawn (1: none)", minimum=1)
    max_roughness_ratio: float = option(1.5, "largest roughness (mean angle between adjacent face normals) "
                                        "over the template's", above=0)
    max_coincident_faces: int = option(0, "face pairs on top of each other (z-fighting)", minimum=0)
    max_redraws: int = option(20, "redraws per requested sample, pooled over the run: at most N x (1 + this) "
                              "draws in all before the run fails", flag="--max-redraws", minimum=0)


@dataclass(frozen=True)
class MeshQuality:
    """The gate's numbers for one mesh and its reasons for failing (empty: it passes)."""

    flipped: int
    flipped_fraction: float
    edge_stretch: float
    edge_stretch_p99: float
    self_intersections: int  # -1: not checked
    extent_ratio: float  # largest extent (axis or diagonal) over the training maximum
    extent_shrink: float  # smallest extent over the training minimum
    reasons: tuple[str, ...] = field(default=())
    roughness_ratio: float = 1.0  # mean adjacent-normal angle over the template's
    coincident_faces: int = 0  # face pairs on top of each other

    @property
    def ok(self) -> bool:
        return not self.reasons

    def summary(self) -> str:
        return "; ".join(self.reasons) if self.reasons else "passes"

    def as_dict(self) -> dict:
        return {"flipped": self.flipped, "flipped_fraction": self.flipped_fraction, "edge_stretch": self.edge_stretch,
                "edge_stretch_p99": self.edge_stretch_p99, "self_intersections": self.self_intersections,
                "extent_ratio": self.extent_ratio, "extent_shrink": self.extent_shrink,
                "roughness_ratio": self.roughness_ratio, "coincident_faces": self.coincident_faces,
                "reasons": list(self.reasons)}


#: Short names of the criteria, as reasons start (counted by `shapegen sample`).
CRITERIA = ("flipped", "edge stretch", "self-intersections", "extent", "roughness", "coincident")

#: Faces are coincident when every corner of one lies within this fraction of the bounding-box
#: diagonal of a corner of the other (exact copies in practice: float32 resolves ~6e-8).
COINCIDENT_RTOL = 1e-6


def roughness(vertices: np.ndarray, faces: np.ndarray, first: np.ndarray, second: np.ndarray) -> float:
    """Mean angle (radians) between the unit normals of face pairs (first[k], second[k])
    sharing an edge; 0 for a plane, larger the more crumpled the surface."""
    if len(first) == 0:
        return 0.0
    normals = triangle_cross(vertices, faces)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), np.finfo(float).tiny)
    cosine = np.clip(np.einsum("ij,ij->i", normals[first], normals[second]), -1.0, 1.0)
    return float(np.mean(np.arccos(cosine)))


def coincident_faces(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Pairs of distinct faces on top of each other (module docstring): candidates by
    centroid (a k-d tree), confirmed corner by corner."""
    corners = vertices[faces]
    tolerance = COINCIDENT_RTOL * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    pairs = cKDTree(corners.mean(axis=1)).query_pairs(tolerance, output_type="ndarray")
    if len(pairs) == 0:
        return 0
    a, b = corners[pairs[:, 0]], corners[pairs[:, 1]]
    distance = np.linalg.norm(a[:, :, None, :] - b[:, None, :, :], axis=3)  # (pairs, 3, 3)
    return int(np.count_nonzero(distance.min(axis=2).max(axis=1) <= tolerance))


def training_extents(meshes: Sequence[Mesh]) -> np.ndarray:
    """(N, 4): bounding-box extents along x, y, z and the diagonal of each mesh."""
    extents = np.array([np.ptp(m.vertices, axis=0) for m in meshes], dtype=np.float64)
    return np.column_stack([extents, np.linalg.norm(extents, axis=1)])


class _TemplateFacts:
    """What the gate compares a sample of one template with (computed once)."""

    def __init__(self, template: Mesh, check_self_intersections: bool):
        self.faces = template.faces
        self.n_vertices = template.n_vertices
        self.normals = template.face_normals_unnormalised()
        self.edges = template.edges_unique()
        self.lengths = _edge_lengths(template.vertices, self.edges)
        self.adjacent_first, self.adjacent_second, _, _ = shared_edges(template.faces)
        self.roughness = roughness(template.vertices, template.faces, self.adjacent_first, self.adjacent_second)
        if check_self_intersections:
            self._own_crossings(template)

    def _own_crossings(self, template: Mesh) -> None:
        """The template's crossings: which pairs of parts cross, and the faces within two
        rings of a crossing inside one part."""
        n_faces, n_vertices = template.n_faces, template.n_vertices
        incidence = sp.csr_matrix((np.ones(3 * n_faces), (np.repeat(np.arange(n_faces), 3), template.faces.ravel())),
                                  shape=(n_faces, n_vertices))
        _, vertex_part = connected_components(incidence.T @ incidence, directed=False)
        self.part = vertex_part[template.faces[:, 0]]
        pairs = intersecting_pairs(template.vertices, template.faces)
        between = self.part[pairs[:, 0]] != self.part[pairs[:, 1]]
        self.crossing_parts = pair_keys(np.sort(self.part[pairs[between]], axis=1), self.part.max() + 1)
        near = np.zeros(n_faces, dtype=bool)
        near[pairs[~between].ravel()] = True
        neighbours = incidence @ incidence.T
        for _ in range(2):
            near = np.asarray(neighbours @ near.astype(np.float64)).ravel() > 0
        self.near_own_crossing = near

    def new_crossings(self, pairs: np.ndarray) -> int:
        """How many crossing face pairs of a sample the template does not explain."""
        part_a, part_b = self.part[pairs[:, 0]], self.part[pairs[:, 1]]
        between = part_a != part_b
        known_parts = np.isin(pair_keys(np.sort(np.stack([part_a, part_b], axis=1), axis=1), self.part.max() + 1),
                              self.crossing_parts)
        near = self.near_own_crossing[pairs[:, 0]] & self.near_own_crossing[pairs[:, 1]]
        return int(np.count_nonzero(np.where(between, ~known_parts, ~near)))


def _edge_lengths(vertices: np.ndarray, edges: np.ndarray) -> np.ndarray:
    return np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)


class QualityGate:
    """Checks generated meshes against their templates and the training shapes' extents.

    `templates[i]` is the mesh whose deformed copies are checked with template_index=i;
    `extents` the training shapes' `training_extents` (same frame as the samples)."""

    def __init__(self, templates: Sequence[Mesh], extents: np.ndarray,
                 settings: QualitySettings = QualitySettings()):
        extents = np.asarray(extents, dtype=np.float64)
        if extents.ndim != 2 or extents.shape[1] != 4 or len(extents) == 0:
            raise ShapeGenError(f"training extents must have shape (N, 4), got {extents.shape}")
        self.templates = list(templates)
        self.settings = settings
        self.extent_low = extents.min(axis=0)
        self.extent_high = extents.max(axis=0)
        self._facts: dict[int, _TemplateFacts] = {}

    def facts(self, index: int) -> _TemplateFacts:
        if index not in self._facts:
            self._facts[index] = _TemplateFacts(self.templates[index], self.settings.check_self_intersections)
        return self._facts[index]

    def check(self, mesh: Mesh | np.ndarray, template_index: int) -> MeshQuality:
        """The gate's verdict on a deformed copy of template `template_index` (a Mesh with
        the template's faces, or its (V, 3) vertices)."""
        facts = self.facts(int(template_index))
        vertices = np.asarray(mesh.vertices if isinstance(mesh, Mesh) else mesh, dtype=np.float64)
        if vertices.shape != (facts.n_vertices, 3):
            raise ShapeGenError(f"a mesh of template {self.templates[template_index].name!r} must have "
                                f"{facts.n_vertices} vertices, got {vertices.shape}")
        settings = self.settings
        reasons = []
        if not np.isfinite(vertices).all():
            return MeshQuality(len(facts.faces), 1.0, np.inf, np.inf, -1, np.inf, 0.0,
                               ("not finite: a vertex is NaN or infinite",))

        tri = vertices[facts.faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        flipped = int(np.count_nonzero(np.einsum("ij,ij->i", normals, facts.normals) <= 0))
        if flipped > settings.max_flipped:
            reasons.append(f"flipped: {flipped} face(s) turned against the template's "
                           f"({100 * flipped / len(facts.faces):.3f} %)")

        ratio = np.log(np.maximum(_edge_lengths(vertices, facts.edges), np.finfo(float).tiny)
                       / np.maximum(facts.lengths, np.finfo(float).tiny))
        stretch = np.abs(ratio - np.median(ratio))
        stretch_max, stretch_p99 = float(stretch.max()), float(np.percentile(stretch, 99))
        if stretch_max > settings.max_edge_stretch or stretch_p99 > settings.max_edge_stretch_p99:
            reasons.append(f"edge stretch: an edge {np.exp(stretch_max):.1f}× (1 % of edges beyond "
                           f"{np.exp(stretch_p99):.2f}×) its template's length, limits "
                           f"{np.exp(settings.max_edge_stretch):.1f}× and "
                           f"{np.exp(settings.max_edge_stretch_p99):.2f}×")

        crossings = -1
        if settings.check_self_intersections:
            crossings = facts.new_crossings(intersecting_pairs(vertices, facts.faces))
            if crossings > settings.max_self_intersections:
                reasons.append(f"self-intersections: {crossings} crossing face pair(s) the template does not have")

        extent = np.ptp(vertices, axis=0)
        extent = np.append(extent, np.linalg.norm(extent))
        grow = float(np.max(extent / np.maximum(self.extent_high, np.finfo(float).tiny)))
        shrink = float(np.min(extent / np.maximum(self.extent_low, np.finfo(float).tiny)))
        limit = 1.0 + settings.extent_tolerance
        if grow > limit or shrink < 1.0 / limit:
            reasons.append(f"extent: {grow:.2f}× the largest training shape's, {shrink:.2f}× the smallest's "
                           f"(allowed {1 / limit:.2f}-{limit:.2f})")
        rough = roughness(vertices, facts.faces, facts.adjacent_first, facts.adjacent_second)
        rough_ratio = rough / facts.roughness if facts.roughness > 0 else (1.0 if rough == 0 else np.inf)
        if rough_ratio > settings.max_roughness_ratio:
            reasons.append(f"roughness: {rough_ratio:.2f}× the template's mean angle between adjacent faces "
                           f"(limit {settings.max_roughness_ratio:.2f}×)")
        coincident = coincident_faces(vertices, facts.faces)
        if coincident > settings.max_coincident_faces:
            reasons.append(f"coincident: {coincident} face pair(s) on top of each other (they z-fight when drawn)")
        return MeshQuality(flipped, flipped / len(facts.faces), stretch_max, stretch_p99, crossings, grow, shrink,
                           tuple(reasons), rough_ratio, coincident)
