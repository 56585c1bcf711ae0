"""The affine graph: one 3x4 affine per node, tied to its k-NN neighbours (thesis §4.2.4
and §6.2; Amberg et al. 2007, Sumner et al. 2007).

Registration (core/correspond) and meshing (core/deform) both minimise

    ‖B A − C‖²_F,  B = [α (M⊗G); W X],  G = diag(1, 1, 1, γ)             (4.29)

over the stacked affines A (4L × 3, A[i] = A_iᵀ so [x, 1] @ A[i] is the moved point),
with M the edge–node incidence of the graph and the data rows W X, W C of point terms
w ‖A_r x_r − t‖². Its normal equations (4.31), (α² (MᵀM ⊗ G²) + blockdiag_r(Σ w x xᵀ)) A
= (Σ w x tᵀ)_r, are solved by `AffineSolver` from the per-node sums that `data_blocks`
accumulates. Both run in the frame `registration_frame` gives (zero mean, unit RMS
radius of the nodes), so α means the same in any units.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from ..base.errors import CollectionError, MeshError, ShapeGenError

__all__ = [
    "AffineSolver",
    "apply_affines",
    "compose_affines",
    "data_blocks",
    "identity_affines",
    "knn_graph",
    "registration_frame",
    "stiffness_energy",
    "stiffness_matrix",
    "transform_normals",
]


def knn_graph(points: np.ndarray, k: int) -> np.ndarray:
    """Symmetrised k-NN graph (4.17): an edge i–j when j is among the k nearest of i or
    i among those of j. Returns unique undirected edges (E, 2), i < j."""
    points = np.asarray(points, dtype=np.float64)
    k = min(k, len(points) - 1)
    if k < 1:
        raise CollectionError("a landmark graph needs at least 2 landmarks")
    _, neighbours = cKDTree(points).query(points, k=k + 1)
    i = np.repeat(np.arange(len(points)), k)
    j = neighbours[:, 1:].ravel()
    edges = np.sort(np.stack([i, j], axis=1), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]  # duplicate points can list themselves later
    return np.unique(edges, axis=0)


def stiffness_matrix(edges: np.ndarray, n_points: int, gamma: float) -> sp.csc_matrix:
    """(M⊗G)ᵀ(M⊗G) = (MᵀM) ⊗ G² (4.28): the graph Laplacian times diag(1, 1, 1, γ²),
    sparse 4L × 4L. M is the edge–node incidence matrix."""
    n_edges = len(edges)
    incidence = sp.csr_matrix(
        (np.r_[np.ones(n_edges), -np.ones(n_edges)],
         (np.r_[np.arange(n_edges), np.arange(n_edges)], np.r_[edges[:, 0], edges[:, 1]])),
        shape=(n_edges, n_points),
    )
    laplacian = (incidence.T @ incidence).tocsc()
    g_squared = sp.diags([1.0, 1.0, 1.0, gamma**2])
    return sp.kron(laplacian, g_squared, format="csc")


def data_blocks(points: np.ndarray, rows: np.ndarray, targets: np.ndarray, weights: np.ndarray,
                n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Normal-equation contributions of point terms w ‖A_r x_r − t‖² (4.26):
    Σ w x xᵀ into the 4 × 4 diagonal block of node r and Σ w x tᵀ into its 4 × D rows.
    targets (n, D): D = 3 for points; any D for several right-hand sides at once (e.g.
    the identity, giving Xᵀ). Returns (blocks (L, 4, 4), rhs (L, 4, D))."""
    x = np.column_stack([points[rows], np.ones(len(rows))])  # homogeneous
    outer = (weights[:, None, None] * x[:, :, None]) * x[:, None, :]
    cross = (weights[:, None, None] * x[:, :, None]) * targets[:, None, :]
    blocks = np.zeros((n_points, 4, 4))
    rhs = np.zeros((n_points, 4, targets.shape[1]))
    np.add.at(blocks, rows, outer)
    np.add.at(rhs, rows, cross)
    return blocks, rhs


class AffineSolver:
    """Solves (BᵀB) A = BᵀC (4.31) for the stacked affines, A (4L × 3), on a fixed graph.

    BᵀB = α² (MᵀM ⊗ G²) + blockdiag(Σ w x xᵀ) (+ ridge): symmetric positive definite and
    sparse. Its pattern is the landmark graph's with 4 × 4 blocks, so a fill-reducing
    ordering of the L-node graph is computed once and expanded to the 4L unknowns
    (keeping each node's 4 unknowns together); every solve is then ONE sparse LU
    factorisation (scipy SuperLU, symmetric mode, no pivoting) reused for all right-hand
    sides (the three coordinates, or the L columns of Xᵀ for meshing's linear map). No
    dense matrix is formed."""

    def __init__(self, edges: np.ndarray, n_points: int, gamma: float):
        self.n_points = n_points
        self.stiffness = stiffness_matrix(edges, n_points, gamma)
        self.order = _block_ordering(edges, n_points)
        self.inverse_order = np.argsort(self.order)

    def solve(self, alpha: float, blocks: np.ndarray, rhs: np.ndarray, ridge: float = 0.0) -> np.ndarray:
        """A as (L, 4, D) for rhs (L, 4, D) from `data_blocks`; for points (D = 3)
        A[i] = A_iᵀ, so [x, 1] @ A[i] is the transformed point. `ridge` pulls every affine
        towards the identity, so it needs D = 3."""
        n = self.n_points
        diagonal = sp.bsr_matrix((blocks, np.arange(n), np.arange(n + 1)), shape=(4 * n, 4 * n)).tocsc()
        normal = (alpha**2) * self.stiffness + diagonal
        right = rhs.reshape(4 * n, -1).copy()
        if ridge > 0:  # relative to the data term's scale, so it never competes with α
            if right.shape[1] != 3:
                raise ValueError(f"a ridge towards the identity needs 3 right-hand sides, got {right.shape[1]}")
            weight = ridge * max(float(np.einsum("nii->", blocks)) / (4 * n), np.finfo(float).tiny)
            normal = normal + weight * sp.identity(4 * n, format="csc")
            right += weight * identity_affines(n).reshape(4 * n, 3)
        permuted = normal[self.order][:, self.order].tocsc()
        factor = splu(permuted, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})
        return factor.solve(right[self.order])[self.inverse_order].reshape(n, 4, -1)


def _block_ordering(edges: np.ndarray, n_points: int) -> np.ndarray:
    """Minimum-degree ordering of the landmark graph (SuperLU's MMD on AᵀA + A of the
    graph Laplacian), expanded to the 4 unknowns of every node."""
    adjacency = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n_points, n_points))
    pattern = (adjacency + adjacency.T + sp.identity(n_points)).tocsc()
    laplacian = sp.diags(np.asarray(abs(pattern).sum(axis=1)).ravel() + 1.0) - (adjacency + adjacency.T)
    factor = splu(laplacian.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    node_order = np.argsort(factor.perm_c)
    return (4 * node_order[:, None] + np.arange(4)).ravel()


def identity_affines(n_points: int) -> np.ndarray:
    """L affines that move nothing, (L, 4, 3)."""
    return np.tile(np.vstack([np.eye(3), np.zeros((1, 3))]), (n_points, 1, 1))


def apply_affines(affines: np.ndarray, points: np.ndarray) -> np.ndarray:
    """A_i x_i for every node: (L, 4, 3) affines, (L, 3) points -> (L, 3)."""
    return np.einsum("nk,nkd->nd", np.column_stack([points, np.ones(len(points))]), affines)


def compose_affines(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """Per node, `inner` then `outer`, (L, 4, 3) each: [x, 1] @ inner gives the moved point,
    [that, 1] @ outer moves it again, so the composite is [inner | e₄] @ outer."""
    homogeneous = np.concatenate([inner, np.tile(np.array([0.0, 0.0, 0.0, 1.0])[None, :, None], (len(inner), 1, 1))],
                                 axis=2)
    return np.einsum("nab,nbc->nac", homogeneous, outer)


def transform_normals(affines: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Normals under each affine: n' ∝ A_lin^(−T) n, via the cofactor matrix (no inverse,
    safe for singular A). Normals whose image vanishes are kept unchanged."""
    linear = np.transpose(affines[:, :3, :], (0, 2, 1))  # A_lin, (L, 3, 3)
    c0, c1, c2 = linear[:, :, 0], linear[:, :, 1], linear[:, :, 2]
    cofactor = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=2)
    sign = np.sign(np.einsum("nd,nd->n", c0, np.cross(c1, c2)))[:, None]
    moved = sign * np.einsum("nij,nj->ni", cofactor, normals)
    length = np.linalg.norm(moved, axis=1, keepdims=True)
    return np.where(length > 1e-12, moved / np.maximum(length, 1e-300), normals)


def stiffness_energy(affines: np.ndarray, edges: np.ndarray, gamma: float) -> float:
    """E_s = Σ_edges ‖G (A_iᵀ − A_jᵀ)‖²_F (4.27)."""
    difference = affines[edges[:, 0]] - affines[edges[:, 1]]
    difference[:, 3, :] *= gamma
    return float((difference**2).sum())


def registration_frame(template_points: np.ndarray, name: str = "template",
                       error: type[ShapeGenError] = MeshError) -> tuple[np.ndarray, float]:
    """(centre, scale) of the frame registration and meshing solve in: p -> (p - centre) /
    scale puts the template landmarks (the graph's nodes) at zero mean and unit RMS radius,
    so α means the same in any units. Raises `error` when they are all at one point."""
    template_points = np.asarray(template_points, dtype=np.float64)
    centre = template_points.mean(axis=0)
    scale = float(np.sqrt(((template_points - centre) ** 2).sum(axis=1).mean()))
    if not scale > 0:
        raise error(f"{name}: template landmarks are all at one point")
    return centre, scale
