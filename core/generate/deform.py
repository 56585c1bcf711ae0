"""Embedded deformation of a template mesh driven by landmarks (thesis §6, Sumner et al. 2007).

Nodes g_j are the template's own landmarks, the graph is the correspondence k-NN graph
(§6.2.2: a fresh k-NN on sampled landmarks can disconnect). Node affines A_j (3×4, absolute
form: A_j [x; 1] is the new position of x) are fitted to target landmarks u_j:

    E(A) = Σ_j ‖A_j x̃_j − u_j‖²  +  α² Σ_{(i,j) ∈ edges} ‖(A_i − A_j) G‖²_F,   G = diag(1,1,1,γ)

(eq. 6.3 + the stiffness of eq. 4.16, in the stacked form ‖B A − C‖² of docs/method.md §3 with
B = [α (M⊗G); X], so α enters squared): the affine-graph problem of registration, solved
by the same `AffineSolver` (core/geometry/affine_graph.py) in the same unit-RMS frame of
the nodes. Every template vertex is then blended over its k
nearest nodes (eq. 6.1–6.2, with the absolute affines: v' = Σ_j w_j(v) A_j [v; 1],
w_j = (1 − ‖v − g_j‖/d_max)², d_max the distance to the (k+1)-th node, normalised).

Two ways to fit the affines:
* `schedule="relax"` — iterative stiffness relaxation (§6.2.3 reusing Alg. 3): for α in a
  decreasing schedule solve for affines relative to the current node positions, move the
  nodes, compose. Correspondences are known, so there is one solve per α.
* `schedule="single"` — one solve at the final α. For fixed template, graph and α the map
  landmarks → vertices is then LINEAR: `LinearMeshMap` solves once for all L unit
  landmark sets, after which each new landmark set costs a dense product and a sparse
  product (docs/method.md §6 **beyond**).

Optional curvature-flow smoothing (§6.2.4, Desbrun et al. 1999): implicit steps
(M − h L) V' = M V with the cotangent Laplacian L and lumped (barycentric) mass M,
followed by a rescaling about the centroid that restores the enclosed volume of a closed
mesh (so smoothing never shrinks a closed mesh's volume).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import factorized
from scipy.spatial import cKDTree

from ..base.errors import ShapeGenError
from ..geometry import AffineSolver, apply_affines, compose_affines, data_blocks, identity_affines, registration_frame
from ..meshes.mesh import Mesh
from ..base.settings import Settings, option

__all__ = [
    "DeformSettings",
    "EmbeddedDeformer",
    "LinearMeshMap",
    "DeformInputError",
    "blend_matrix",
    "cotangent_laplacian",
    "smooth_curvature_flow",
    "enclosed_volume",
]


class DeformInputError(ShapeGenError, ValueError):
    """Landmarks or template unusable for deformation (wrong count, NaN, ...)."""


@dataclass(frozen=True)
class DeformSettings(Settings):
    """Embedded-deformation parameters (thesis §6; defaults as the thesis used for vases).

    final_alpha: stiffness of the last (or only) solve; low = follow landmarks closely,
        high = stay close to the template's shape (thesis: 3 vases, 5 cars, 10 teapots, in
        its own units; ours is measured in the unit-RMS-radius frame). Default 5, not lower:
        sampled landmark sets carry the correspondence's noise at the
        scale of the landmark spacing, and a template's landmarks cover it unevenly (a
        vertex up to 5-11 landmark spacings from the nearest one on PSB Fish), so a soft
        deformation follows the noise and crumples. Samples broken by the quality gate
        (core/generate/quality.py), 200 per class, BGP-LVM, nearest-data template, linear path,
        α 2 → 3 → 5: PSB Fish 23 → 12 → 1, PSB Airplane 5 → 0 → 0, procedural vases
        2 → 0 → 0, PSB Vase 126 → 65 (α 5); the landmark residual grows from 0.53 % to
        0.72 % of the diagonal on Airplane (bench/deform.py: α 1 → 0.39 %, 3 → 0.61 %).
    start_alpha: first stiffness of the relaxation schedule (thesis §4: 100).
    n_stages: number of evenly spaced α values from start_alpha to final_alpha.
    gamma: weight of the translation column in the stiffness (G = diag(1,1,1,γ); thesis 2).
    k_blend: nodes that influence each vertex (Sumner et al.: 4).
    Every value is checked on construction (SettingsError naming the option): a zero
    stiffness would only fail when a sample is meshed ("Factor is exactly singular").
    """

    final_alpha: float = option(5.0, "meshing stiffness: final α of the embedded deformation", flag="--stiffness",
                                above=0)
    start_alpha: float = option(100.0, "first α of the relaxation schedule", above=0)
    n_stages: int = option(8, "α values of the relaxation schedule", minimum=1)
    gamma: float = option(2.0, "weight of the translation column in the stiffness", above=0)
    k_blend: int = option(4, "nodes that influence each vertex", minimum=1)

    def schedule(self) -> np.ndarray:
        return np.linspace(self.start_alpha, self.final_alpha, self.n_stages)


# ---------------------------------------------------------------------------- blending
def blend_matrix(vertices: np.ndarray, nodes: np.ndarray, k: int) -> sp.csr_matrix:
    """Sparse V × 4n matrix W with (W A)_v = Σ_j w_j(v) [v, 1] A_jᵀ (eq. 6.1–6.2)."""
    n_nodes = len(nodes)
    k = min(k, n_nodes - 1)
    if k < 1:
        raise DeformInputError(f"need at least 2 deformation nodes, got {n_nodes}")
    distances, index = cKDTree(nodes).query(vertices, k=k + 1)
    d_max = distances[:, -1:]
    weights = (1.0 - distances[:, :k] / np.maximum(d_max, np.finfo(float).tiny)) ** 2
    total = weights.sum(axis=1, keepdims=True)
    # a vertex equidistant from all k+1 nodes gets equal weights instead of 0/0
    weights = np.where(total > 0, weights / np.where(total > 0, total, 1.0), 1.0 / k)
    homogeneous = np.hstack([vertices, np.ones((len(vertices), 1))])
    n_vertices = len(vertices)
    rows = np.repeat(np.arange(n_vertices), 4 * k)
    cols = (4 * index[:, :k, None] + np.arange(4)[None, None, :]).reshape(n_vertices, -1).ravel()
    vals = (weights[:, :, None] * homogeneous[:, None, :]).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(n_vertices, 4 * n_nodes))


# ---------------------------------------------------------------------------- deformer
class EmbeddedDeformer:
    """Deforms one template mesh so its landmarks (nodes) move to given target landmarks."""

    def __init__(self, template: Mesh, nodes: np.ndarray, edges: np.ndarray,
                 settings: DeformSettings = DeformSettings()):
        nodes = np.asarray(nodes, dtype=np.float64)
        edges = np.asarray(edges, dtype=np.int64)
        label = template.name or "template"
        if nodes.ndim != 2 or nodes.shape[1] != 3 or not np.isfinite(nodes).all():
            raise DeformInputError(f"{label}: nodes must be a finite (L, 3) array, got {nodes.shape}")
        if edges.ndim != 2 or edges.shape[1] != 2 or len(edges) == 0:
            raise DeformInputError(f"{label}: edges must be a non-empty (E, 2) array, got {edges.shape}")
        if edges.min() < 0 or edges.max() >= len(nodes):
            raise DeformInputError(f"{label}: an edge refers to a node outside [0, {len(nodes)})")
        self.template = template
        self.nodes = nodes
        self.edges = edges
        self.settings = settings
        # solve in the registration frame of the nodes (unit RMS radius), so α means the
        # same for every shape size
        self.frame_centre, self.frame_scale = registration_frame(nodes, label, DeformInputError)
        self.nodes_in_frame = self.to_frame(nodes)
        self.blend = blend_matrix(self.to_frame(template.vertices), self.nodes_in_frame, settings.k_blend)
        self.solver = AffineSolver(edges, len(nodes), settings.gamma)

    def to_frame(self, points: np.ndarray) -> np.ndarray:
        return (points - self.frame_centre) / self.frame_scale

    def from_frame(self, points: np.ndarray) -> np.ndarray:
        return points * self.frame_scale + self.frame_centre

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    def check_targets(self, targets: np.ndarray) -> np.ndarray:
        targets = np.asarray(targets, dtype=np.float64)
        label = self.template.name or "template"
        if targets.shape != self.nodes.shape:
            raise DeformInputError(
                f"{label}: target landmarks have shape {targets.shape}, the template has "
                f"{self.n_nodes} landmarks (expected {self.nodes.shape})"
            )
        if not np.isfinite(targets).all():
            bad = int(np.flatnonzero(~np.isfinite(targets).all(axis=1))[0])
            raise DeformInputError(f"{label}: target landmark {bad} is NaN or infinite")
        return targets

    def solve_affines(self, points: np.ndarray, targets: np.ndarray, alpha: float) -> np.ndarray:
        """Minimise ‖X A − U‖² + α²‖(M⊗G) A‖² for nodes at `points`: (XᵀX + α²K) A = XᵀU
        (4.31, unit weights), stacked affines (4L × 3)."""
        n = len(points)
        blocks, rhs = data_blocks(points, np.arange(n), targets, np.ones(n), n)
        return self.solver.solve(alpha, blocks, rhs).reshape(-1, 3)

    def fit(self, targets: np.ndarray, schedule: str = "relax") -> np.ndarray:
        """Absolute node affines (stacked 4L × 3, in the solve frame) moving the nodes onto
        `targets`."""
        targets = self.to_frame(self.check_targets(targets))
        if schedule == "single":
            return self.solve_affines(self.nodes_in_frame, targets, self.settings.final_alpha)
        if schedule != "relax":
            raise ValueError(f"unknown schedule {schedule!r}: 'relax' or 'single'")
        total = identity_affines(self.n_nodes)
        points = self.nodes_in_frame
        for alpha in self.settings.schedule():
            step = self.solve_affines(points, targets, alpha).reshape(-1, 4, 3)
            points = apply_affines(step, points)
            total = compose_affines(step, total)
        return total.reshape(-1, 3)

    def deform(self, targets: np.ndarray, schedule: str = "relax", smooth_iterations: int = 0,
               name: str = "") -> Mesh:
        """The template deformed to `targets` (and optionally smoothed)."""
        affines = self.fit(targets, schedule)
        vertices = self.from_frame(np.asarray(self.blend @ affines))
        mesh = self.template.with_vertices(vertices, name=name or self.template.name)
        if smooth_iterations:
            mesh = smooth_curvature_flow(mesh, smooth_iterations)
        return mesh


class LinearMeshMap:
    """The fast path: landmarks U (L × 3) → vertices = W S⁻¹ Xᵀ U for a fixed template,
    graph and α, with S = XᵀX + α²K.

    `Q = S⁻¹ Xᵀ` (4L × L, dense: column j holds the affines for the unit landmark set e_j)
    comes from ONE solve with L right-hand sides (the shared `AffineSolver`) and is kept, so
    `vertices(U) = W (Q U)`: a dense product with L columns and a sparse product with the
    blend matrix. Whole landmark bases can be pushed through the map, so a model whose
    decode is affine in some coefficients becomes mesh = V₀ + Σ c_k V_k (`linear_part`).
    """

    def __init__(self, deformer: EmbeddedDeformer, alpha: float | None = None):
        self.deformer = deformer
        self.alpha = deformer.settings.final_alpha if alpha is None else float(alpha)
        n = deformer.n_nodes
        blocks, transposed_x = data_blocks(deformer.nodes_in_frame, np.arange(n), np.eye(n), np.ones(n), n)
        self.node_map = deformer.solver.solve(self.alpha, blocks, transposed_x).reshape(4 * n, n)  # Q

    def vertices(self, targets: np.ndarray) -> np.ndarray:
        """Deformed template vertices for one landmark set (L, 3) → (V, 3)."""
        d = self.deformer
        frame = d.to_frame(d.check_targets(targets))
        return d.from_frame(np.asarray(d.blend @ (self.node_map @ frame)))

    def linear_part(self, directions: np.ndarray) -> np.ndarray:
        """The map's linear part applied to landmark displacements (K, L, 3) → (K, V, 3):
        vertices(U + Σ c_k B_k) = vertices(U) + Σ c_k linear_part(B)_k. No NaN / count
        checks (directions need not be shapes)."""
        directions = np.asarray(directions, dtype=np.float64)
        k, n, _ = directions.shape
        stacked = directions.transpose(1, 0, 2).reshape(n, 3 * k)
        verts = np.asarray(self.deformer.blend @ (self.node_map @ stacked))  # V × 3K
        return verts.reshape(-1, k, 3).transpose(1, 0, 2)


# ---------------------------------------------------------------------------- smoothing
def cotangent_laplacian(mesh: Mesh) -> sp.csr_matrix:
    """L with L_ij = ½(cot α_ij + cot β_ij) for edges, L_ii = −Σ_j L_ij (negative semi-definite)."""
    v, f = mesh.vertices, mesh.faces
    n = len(v)
    rows, cols, vals = [], [], []
    for corner in range(3):
        i, j, k = f[:, corner], f[:, (corner + 1) % 3], f[:, (corner + 2) % 3]
        # angle at vertex i, opposite edge (j, k)
        a, b = v[j] - v[i], v[k] - v[i]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        cot = np.einsum("ij,ij->i", a, b) / np.maximum(cross, 1e-300)
        rows.extend([j, k])
        cols.extend([k, j])
        vals.extend([0.5 * cot, 0.5 * cot])
    off = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return (off - sp.diags(np.asarray(off.sum(axis=1)).ravel())).tocsr()


def _lumped_mass(mesh: Mesh) -> np.ndarray:
    """Barycentric vertex areas: a third of each incident face's area."""
    areas = mesh.face_areas()
    mass = np.zeros(mesh.n_vertices)
    for corner in range(3):
        np.add.at(mass, mesh.faces[:, corner], areas / 3.0)
    return np.maximum(mass, 1e-300)


def enclosed_volume(mesh: Mesh) -> float:
    """Signed volume (divergence theorem); meaningful for closed, consistently oriented meshes."""
    tri = mesh.triangles
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def smooth_curvature_flow(mesh: Mesh, iterations: int = 1, step: float = 0.5,
                          preserve_volume: bool = True) -> Mesh:
    """Implicit mean-curvature flow (Desbrun et al. 1999, thesis eq. 6.4).

    Each iteration solves (M − h L) V' = M V with h = step × (mean edge length)², the
    Laplacian and mass rebuilt from the current mesh. With `preserve_volume` a closed mesh
    is rescaled about its centroid after each step to its original enclosed volume.
    """
    if iterations < 0:
        raise ValueError(f"smoothing iterations must be >= 0, got {iterations}")
    closed = preserve_volume and mesh.is_closed()
    volume0 = enclosed_volume(mesh) if closed else None
    current = mesh
    for _ in range(iterations):
        laplacian = cotangent_laplacian(current)
        mass = _lumped_mass(current)
        h = step * current.mean_edge_length() ** 2
        system = (sp.diags(mass) - h * laplacian).tocsc()
        solve = factorized(system)
        rhs = mass[:, None] * current.vertices
        vertices = np.column_stack([solve(rhs[:, d]) for d in range(3)])
        if closed and volume0:
            trial = current.with_vertices(vertices)
            volume = enclosed_volume(trial)
            if volume * volume0 > 0:
                centre = vertices.mean(axis=0)
                vertices = centre + (vertices - centre) * np.cbrt(volume0 / volume)
        current = current.with_vertices(vertices)
    return current
