"""The Laplace–Beltrami spectrum of a triangle mesh and the descriptors read from it
(**beyond** the thesis: the intrinsic start of correspondence; docs/method.md).

The operator is the cotangent Laplacian with a lumped mass matrix (Pinkall & Polthier
1993; Meyer et al. 2003): the stiffness W has w_ij = ½ (cot α_ij + cot β_ij) over the
two angles facing edge ij, the mass M is diagonal, a third of the area of the faces around
each vertex. The eigenpairs solve W φ = λ M φ (the weak form of −Δφ = λφ with natural,
i.e. Neumann, boundary conditions), M-orthonormal. They are intrinsic: bending a shape
without stretching it (a limb moved) leaves them nearly unchanged, which is what makes
them a pose-invariant basis for matching (core/correspond/functional_map.py).

Robustness, as done here (no intrinsic Delaunay remeshing):
- a face whose area is below DEGENERATE_AREA times the mean face area adds neither
  stiffness nor mass (its cotangents would be unbounded);
- every remaining cotangent is clamped to ±COT_LIMIT (a needle triangle cannot dominate
  its row); negative weights of obtuse angles are kept, so the operator stays exact on
  well-shaped meshes (the closed forms of tests/core/test_spectral.py);
- vertices no face uses get no row: the spectrum lives on the used vertices;
- several parts: each part has its own zero eigenvalue, so the low spectrum mixes parts.
  `Spectrum.largest_part_share` reports the largest part's share of the area; the caller
  decides whether to trust it (the spectrum itself is computed on the largest part only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sparse
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import eigsh

__all__ = ["Spectrum", "cotangent_laplacian", "laplace_beltrami_spectrum", "wave_kernel_signature",
           "SpectrumError", "COT_LIMIT", "DEGENERATE_AREA"]

#: cotangents are clamped to ±COT_LIMIT (an angle below about 0.06° or above 179.94°)
COT_LIMIT = 1e3
#: faces with less than this share of the mean face area are left out of the operator
DEGENERATE_AREA = 1e-10


class SpectrumError(ValueError):
    """The eigen-solve did not give a usable spectrum (the caller falls back and says why)."""


@dataclass(frozen=True)
class Spectrum:
    """The first k eigenpairs of the Laplace–Beltrami operator on a mesh's largest part,
    computed after scaling the part to unit area (so eigenvalues and eigenfunctions of
    shapes of any size compare directly).

    vertices: (n,) indices into the mesh's vertices of the part's vertices; the rows of
    `vectors` and `mass` follow this order.
    faces: (F, 3) the part's faces, numbered in that order.
    values: (k,) ascending eigenvalues λ (the first is ~0: the constant function).
    vectors: (n, k) eigenfunctions, M-orthonormal: vectorsᵀ diag(mass) vectors = I.
    mass: (n,) lumped vertex areas (of the unit-area part; they sum to 1).
    largest_part_share: the part's share of the mesh's area (1: one part).
    parts: how many connected parts the mesh has."""

    vertices: np.ndarray
    faces: np.ndarray
    values: np.ndarray
    vectors: np.ndarray
    mass: np.ndarray
    largest_part_share: float
    parts: int

    def project(self, functions: np.ndarray, k: int) -> np.ndarray:
        """(k, d) coefficients of `functions` (n, d) on the first k eigenfunctions (Φᵀ M f)."""
        return self.vectors[:, :k].T @ (self.mass[:, None] * functions)


def _face_geometry(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) areas and (F, 3) cotangents of the angle at each corner (clamped, 0 on degenerate faces)."""
    corners = vertices[faces]  # (F, 3, 3)
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    usable = double_area > 2 * DEGENERATE_AREA * max(double_area.mean() / 2, np.finfo(float).tiny)
    cot = np.zeros((len(faces), 3))
    for corner in range(3):
        u = corners[:, (corner + 1) % 3] - corners[:, corner]
        v = corners[:, (corner + 2) % 3] - corners[:, corner]
        dot = np.einsum("fd,fd->f", u, v)
        cot[usable, corner] = np.clip(dot[usable] / double_area[usable], -COT_LIMIT, COT_LIMIT)
    return np.where(usable, double_area / 2, 0.0), cot


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray) -> tuple[sparse.csr_matrix, np.ndarray]:
    """(W, m): the cotangent stiffness matrix W (n × n, symmetric, rows summing to 0,
    positive semi-definite on well-shaped meshes) and the lumped mass m (n,) of a triangle
    mesh over all its `vertices`; degenerate faces and clamping as in the module docstring."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(vertices)
    areas, cot = _face_geometry(vertices, faces)
    # the angle at corner c faces the edge between the other two corners
    rows = np.concatenate([faces[:, (c + 1) % 3] for c in range(3)])
    cols = np.concatenate([faces[:, (c + 2) % 3] for c in range(3)])
    weights = 0.5 * np.concatenate([cot[:, c] for c in range(3)])
    off_diagonal = sparse.coo_matrix((-weights, (rows, cols)), shape=(n, n)).tocsr()
    off_diagonal = off_diagonal + off_diagonal.T
    stiffness = off_diagonal - sparse.diags(np.asarray(off_diagonal.sum(axis=1)).ravel())
    mass = np.bincount(faces.ravel(), weights=np.repeat(areas / 3.0, 3), minlength=n)
    return stiffness.tocsr(), mass


def _largest_part(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, float, int]:
    """(vertex indices of the connected part with the largest area, its share of the area,
    the number of parts). Parts: connected through shared face corners."""
    n = len(vertices)
    corners = faces.ravel()
    owners = np.repeat(np.arange(len(faces)), 3)
    incidence = sparse.coo_matrix((np.ones(len(corners)), (corners, owners)), shape=(n, len(faces))).tocsr()
    adjacency = incidence @ incidence.T
    used = np.zeros(n, dtype=bool)
    used[corners] = True
    count, labels = connected_components(adjacency, directed=False)
    areas = 0.5 * np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                          vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    part_area = np.bincount(labels[faces[:, 0]], weights=areas, minlength=count)
    parts = len(np.unique(labels[used]))
    largest = int(np.argmax(part_area))
    total = part_area.sum()
    share = float(part_area[largest] / total) if total > 0 else 0.0
    return np.flatnonzero((labels == largest) & used), share, parts


def laplace_beltrami_spectrum(vertices: np.ndarray, faces: np.ndarray, k: int) -> Spectrum:
    """The first `k` eigenpairs of W φ = λ M φ on the mesh's largest part, scaled to unit
    area (module docstring). Solved by scipy's Lanczos (eigsh) in shift-invert mode about
    a small negative σ (W is singular: σ = 0 cannot be factorised), which finds the
    eigenvalues nearest σ, i.e. the smallest, in a few iterations. Raises SpectrumError
    when the part is too small for k eigenpairs or the solver fails."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    part, share, parts = _largest_part(vertices, faces)
    if len(part) <= k + 1:
        raise SpectrumError(f"the largest part has {len(part)} vertices, too few for {k} eigenpairs")
    renumber = np.full(len(vertices), -1, dtype=np.int64)
    renumber[part] = np.arange(len(part))
    part_faces = renumber[faces[np.isin(faces[:, 0], part)]]
    points = vertices[part]
    area = 0.5 * np.linalg.norm(np.cross(points[part_faces[:, 1]] - points[part_faces[:, 0]],
                                         points[part_faces[:, 2]] - points[part_faces[:, 0]]), axis=1).sum()
    if not area > 0:
        raise SpectrumError("the largest part has no area")
    stiffness, mass = cotangent_laplacian(points / np.sqrt(area), part_faces)
    if not (mass > 0).all():
        raise SpectrumError(f"{int((mass <= 0).sum())} vertices touch only degenerate faces")
    try:
        start = np.random.default_rng(0).uniform(0.5, 1.5, len(mass))  # seeded: the same signs on every run
        values, vectors = eigsh(stiffness.tocsc(), k=k, M=sparse.diags(mass).tocsc(), sigma=-1e-3, which="LM",
                                v0=start)
    except Exception as exc:  # ArpackNoConvergence, a singular factorisation
        raise SpectrumError(f"the eigensolver failed: {exc}") from exc
    order = np.argsort(values)
    values, vectors = values[order], vectors[:, order]
    if not (np.isfinite(values).all() and np.isfinite(vectors).all()):
        raise SpectrumError("the eigensolver returned non-finite values")
    return Spectrum(part, part_faces, np.maximum(values, 0.0), vectors, mass, share, parts)


def wave_kernel_signature(spectrum: Spectrum, energies: int = 50, k: int | None = None) -> np.ndarray:
    """(n, energies) wave kernel signature (Aubry et al. 2011): at log-energy e_t,
    Σ_k φ_k(x)² exp(−(e_t − log λ_k)² / 2σ²), normalised by Σ_k exp(…), for e_t evenly
    spaced over the log-eigenvalues (the constant function left out), σ = 7 steps. Each
    column is then scaled to unit M-norm so every energy weighs the same."""
    k = len(spectrum.values) if k is None else k
    values, vectors = spectrum.values[1:k], spectrum.vectors[:, 1:k]
    logs = np.log(np.maximum(values, 1e-12))
    levels = np.linspace(logs[0], logs[-1], energies)
    sigma = 7.0 * (levels[1] - levels[0]) if energies > 1 else 1.0
    filters = np.exp(-((levels[None, :] - logs[:, None]) ** 2) / (2 * sigma**2))  # (k-1, energies)
    signature = (vectors**2) @ filters / filters.sum(axis=0)
    norms = np.sqrt(spectrum.mass @ signature**2)
    return signature / np.where(norms > 0, norms, 1.0)
