"""Groupwise refinement by kernel warps (**beyond** the thesis; after Davies et al. 2002,
"A minimum description length approach to statistical shape modelling", whose
parameterisations move by sums of kernels, wide ones first): every shape's landmarks
move by one smooth tangent displacement field with few parameters, and the population
objective of objective.py is minimised over those parameters by a quasi-Newton search.

Why: on 40 procedural vases the objective prefers the ground truth by far, but
landmark-wise steepest descent (refine.py) stops soon; the hope was a long, shallow
valley that a field of K wide kernels (2K parameters per shape) searched by L-BFGS would
follow. Measured (bench/refine_warps.py; docs/results.md, issue 13, third round): it
lowers E, but the true error rises on every collection, because the objective charges
the smooth part of the way to the truth (NICP + the truth's displacement fitted in
these fields has E above NICP's); so this is a measured tool, not a `refine` option.

The field of shape m, at landmark l (every stage starts from the current landmarks x⁰):

    d_ml = P⁰_ml Σ_k w_kl (a_mk1 t_mk1 + a_mk2 t_mk2) · σ / s_m,
    x_ml(a) = closest compatible point of shape m to x⁰_ml + d_ml

* w_kl = exp(−g_kl² / 2σ²): Gaussian kernels of the geodesic distance g_kl on the
  landmark graph of the population's mean (aligned) landmarks, from K centres picked by
  farthest-point sampling on that graph; edges whose endpoints' mean normals disagree are
  cut (the two faces of a thin wall do not move together); σ = `width` × the largest
  distance of a landmark from its nearest centre (the kernels cover the surface).
  Centres, weights and frames live in the template's landmark space, the same for every
  shape: no class-specific parameterisation.
* t_mk1, t_mk2: two directions tangent to the mean shape at centre k, turned into shape
  m's frame by its Procrustes rotation; P⁰_ml projects onto landmark l's tangent plane;
  s_m is shape m's Procrustes scale (σ is measured on the mean, so a = 1 moves by one
  kernel width on every shape). |a| ≤ `MAX_COEFFICIENT` keeps a single kernel's field
  one-to-one (its largest slope is 0.61 |a|).
* ∂E/∂a_mkj = Σ_l w_kl t_mkj · P⁰_ml P_ml ∂E/∂x_ml σ / s_m (P_ml: the tangent projector at
  the moved landmark, the closest-point map's Jacobian on a face).

Stages go coarse to fine (`kernels`, e.g. 4, 8, 16, 32): each stage runs L-BFGS-B
(scipy) on all shapes' coefficients together from a = 0, keeps the best point it
evaluated if that lowers E, makes it the current landmarks (the warps compose), and
re-estimates the shapes' similarities (kept only if E drops). E therefore decreases
monotonically from stage to stage. The per-shape work (closest points, normals, spread)
runs in `jobs` processes (shards.py), as for refine.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from ..mesh import Mesh
from ..progress import CancelCheck, Progress, no_progress
from .objective import CompactnessTerm
from .refine import Refinement, population_objective
from .shards import Shards

__all__ = ["WarpBasis", "warp_basis", "refine_warps", "MAX_COEFFICIENT", "KERNELS", "WIDTH"]

#: bound on every kernel coefficient (in kernel widths): one kernel's field stays one-to-one
MAX_COEFFICIENT = 0.5
#: kernels of the stages, coarse to fine (Davies et al.: wide kernels first)
KERNELS = (4, 8, 16, 32)
#: kernel width σ relative to the largest distance of a landmark from its nearest centre
WIDTH = 1.0


@dataclass(frozen=True)
class WarpBasis:
    """K kernels on the landmark graph: centre landmarks, weights (K, L), the width σ
    (in the aligned frame) and two tangent directions per centre (K, 2, 3), aligned frame."""

    centres: np.ndarray
    weights: np.ndarray
    width: float
    directions: np.ndarray


def _graph(points: np.ndarray, normals: np.ndarray, edges: np.ndarray):
    """The landmark graph with edge lengths, cut where the endpoints' normals disagree."""
    i, j = np.asarray(edges, dtype=np.int64).T
    keep = np.einsum("nd,nd->n", normals[i], normals[j]) > 0
    i, j = i[keep], j[keep]
    length = np.maximum(np.linalg.norm(points[i] - points[j], axis=1), np.finfo(float).tiny)
    n = len(points)
    return coo_matrix((np.r_[length, length], (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()


def warp_basis(points: np.ndarray, normals: np.ndarray, edges: np.ndarray, n_kernels: int, width: float
               ) -> WarpBasis:
    """Kernels on the landmarks `points` (L, 3) with unit `normals` (module docstring):
    farthest-point sampling on the graph, starting from the landmark farthest from the
    centroid (deterministic)."""
    points = np.asarray(points, dtype=np.float64)
    graph = _graph(points, normals, edges)
    n_kernels = int(min(n_kernels, len(points)))
    centres = [int(np.argmax(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))]
    distances = [dijkstra(graph, indices=centres[0])]
    nearest = distances[0].copy()
    for _ in range(n_kernels - 1):
        finite = np.where(np.isfinite(nearest), nearest, np.inf)
        centres.append(int(np.argmax(finite)))  # an unreachable landmark (another component) first
        distances.append(dijkstra(graph, indices=centres[-1]))
        nearest = np.minimum(nearest, distances[-1])
    distances = np.stack(distances)
    reach = float(np.max(np.where(np.isfinite(nearest), nearest, 0.0)))
    sigma = max(width * reach, np.finfo(float).tiny)
    weights = np.exp(-np.where(np.isfinite(distances), distances, np.inf) ** 2 / (2 * sigma**2))  # unreachable: 0
    directions = np.stack([_tangent_frame(normals[c]) for c in centres])
    return WarpBasis(np.array(centres), weights, sigma, directions)


def _tangent_frame(normal: np.ndarray) -> np.ndarray:
    """Two orthonormal directions perpendicular to `normal` (2, 3)."""
    normal = normal / max(np.linalg.norm(normal), np.finfo(float).tiny)
    axis = np.eye(3)[int(np.argmin(np.abs(normal)))]
    first = axis - (axis @ normal) * normal
    first /= np.linalg.norm(first)
    return np.stack([first, np.cross(normal, first)])


def _tangent(vectors: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """v − (v · n) n per landmark."""
    return vectors - np.einsum("...d,...d->...", vectors, normals)[..., None] * normals


class _Stage:
    """One stage: the field of every shape as a function of the coefficients a (N, K, 2)."""

    def __init__(self, basis: WarpBasis, compactness: CompactnessTerm, start_normals: np.ndarray):
        self.basis = basis
        # directions in every shape's own frame, × σ / s_m: (N, K, 2, 3)
        self.directions = np.einsum("kjd,mde->mkje", basis.directions, compactness.rotations) \
            * (basis.width / compactness.scales)[:, None, None, None]
        self.start_normals = start_normals

    def field(self, coefficients: np.ndarray) -> np.ndarray:
        """d (N, L, 3) for coefficients (N, K, 2)."""
        vectors = np.einsum("mkj,mkjd->mkd", coefficients, self.directions)
        return _tangent(np.einsum("kl,mkd->mld", self.basis.weights, vectors), self.start_normals)

    def chain(self, gradient: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """∂E/∂a (N, K, 2) from ∂E/∂x (N, L, 3) at the moved landmarks (face `normals`)."""
        projected = _tangent(_tangent(gradient, normals), self.start_normals)
        per_kernel = np.einsum("kl,mld->mkd", self.basis.weights, projected)
        return np.einsum("mkd,mkjd->mkj", per_kernel, self.directions)


def refine_warps(meshes: Sequence[Mesh], points: np.ndarray, face_index: np.ndarray, barycentric: np.ndarray,
                 settings, edges: np.ndarray, kernels: Sequence[int] = KERNELS, width: float = WIDTH,
                 progress: Progress | None = None, should_cancel=None, jobs: int = 1, compactness=None):
    """Refine the landmarks (N, L, ...) of `meshes` (normalised frame) by coarse-to-fine
    kernel warps (module docstring): one stage per entry of `kernels`, kernel `width`;
    the objective, L-BFGS iterations per stage (`refine_iterations`) and tolerance from
    the CorrespondenceSettings `settings` (`refine_*`). edges: the landmark graph the
    kernels live on. compactness: as for refine.refine_population. Returns a
    refine.Refinement whose trace has E at the start and after every L-BFGS iteration
    that lowered the best E so far."""

    report = progress or no_progress
    cancel = CancelCheck(should_cancel, "correspondence")
    shards = Shards(meshes, np.asarray(points), np.asarray(face_index), np.asarray(barycentric), settings.refine_sigma,
                    jobs)
    try:
        return Refinement(*_search(shards, settings, edges, kernels, width, report, cancel, compactness))
    finally:
        shards.close()


def _search(shards: Shards, settings, edges, stages, width, report: Progress, cancel, make_compactness):
    answer = shards.propose(None)
    compactness, evaluate = population_objective(answer, settings, make_compactness)
    value, _ = evaluate(answer)
    trace, rejected = [value.as_row()], 0
    budget = settings.refine_iterations
    for number, n_kernels in enumerate(stages):
        cancel()
        state = answer.state
        aligned = compactness.aligned(state.points)
        mean_points = aligned.mean(axis=0)
        mean_normals = (state.face_normals @ compactness.rotations.transpose(0, 2, 1)).mean(axis=0)
        mean_normals /= np.maximum(np.linalg.norm(mean_normals, axis=1, keepdims=True), np.finfo(float).tiny)
        basis = warp_basis(mean_points, mean_normals, edges, n_kernels, width)
        stage = _Stage(basis, compactness, state.face_normals)
        shape = (len(state.points), len(basis.centres), 2)
        best = {"value": value, "answer": answer, "x": np.zeros(int(np.prod(shape)))}

        def objective(x):
            cancel()
            candidate = shards.propose(stage.field(x.reshape(shape)))
            candidate_value, gradient = evaluate(candidate)
            if candidate_value.total < best["value"].total:
                best.update(value=candidate_value, answer=candidate, x=x.copy())
            return candidate_value.total, stage.chain(gradient, candidate.state.face_normals).ravel()

        def progressed(_):
            if trace[-1][0] > best["value"].total:
                trace.append(best["value"].as_row())
            report((number + min(len(trace), budget) / max(budget, 1)) / len(stages),
                   f"refining by warps ({len(basis.centres)} kernels, objective {best['value'].total:.4f})")

        result = minimize(objective, np.zeros(int(np.prod(shape))), jac=True, method="L-BFGS-B",
                          bounds=[(-MAX_COEFFICIENT, MAX_COEFFICIENT)] * int(np.prod(shape)), callback=progressed,
                          options={"maxiter": budget, "ftol": settings.refine_tolerance, "gtol": 1e-9})
        rejected += max(result.nfev - result.nit - 1, 0)
        if best["value"].total >= value.total:
            continue
        shards.propose(stage.field(best["x"].reshape(shape)))  # the best point becomes the current landmarks
        shards.accept()
        value, answer = best["value"], best["answer"]
        if trace[-1][0] > value.total:
            trace.append(value.as_row())
        if settings.refine_alignment != "none" and settings.refine_compactness:
            old = compactness.scales, compactness.rotations
            compactness.realign(answer.state.points)  # kept only if it lowers E as well
            realigned, _ = evaluate(answer)
            if realigned.total < value.total:
                value = realigned
                trace.append(value.as_row())
            else:
                compactness.scales, compactness.rotations = old
    points, face_index, barycentric = shards.current()
    return points, face_index, barycentric, np.array(trace), rejected
