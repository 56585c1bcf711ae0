"""Groupwise refinement after non-rigid ICP (**beyond** the thesis): every landmark slides
on its own shape's surface to lower the population objective of objective.py
(compactness of the landmark population + a spread term per shape; Davies et al. 2002,
Cates et al. 2007).

One iteration (projected gradient descent with backtracking):

1. E and ∂E/∂x of every landmark (objective.py; N × N dual for the compactness);
2. the gradient projected onto the landmark's tangent plane (its face normal n:
   g − (g · n) n), then onto the `refinement.smooth_fields` smoothest fields of the landmark
   graph (Laplacian eigenvectors, per coordinate; whole regions slide together rather
   than landmark by landmark) and onto the tangent plane again; a step −τ g with every
   landmark's move capped at `max_move` × the shape's landmark spacing √(area / L);
3. each moved landmark mapped back onto its surface by the closest point whose face
   normal is compatible (n_new · n_old >= 0: never through a thin wall), giving its new
   face index and barycentric coordinates (a landmark with no compatible face nearby
   stays put); every shape's closest-point structure is built once and tracks its
   landmarks between iterations (geometry.TargetSurface.tracker), so the cost per
   iteration is O(N L log L) plus the closest-point queries, whatever the mesh size
   (this per-shape work runs in `jobs` processes, shards.py);
4. the step is kept only if E went down (then τ grows by `GROW`), otherwise τ is halved
   and the step tried again (up to `MAX_BACKTRACKS` times): E decreases monotonically;
5. every `REALIGN_EVERY` steps the shapes' similarities (generalised Procrustes) are
   estimated again from the moved landmarks, kept only if that lowers E as well.

It stops after `iterations` accepted steps, when no step lowers E, or when an accepted
step lowers E by less than `tolerance` (relative to |E|). Shapes flagged as outliers keep
their NICP landmarks and stay out of the objective.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..meshes.mesh import Mesh
from ..base.progress import CancelCheck, Progress, no_progress
from .objective import CompactnessTerm, LandmarkState, combined
from .shards import ShapeShard, ShardAnswer, Shards, interpolated_normals
from .settings import REFINE_METHODS, CorrespondenceSettings

__all__ = ["Refinement", "refine_population", "population_objective", "landmark_state", "smooth_basis", "interpolated_normals",
           "REFINE_METHODS", "GROW", "MAX_BACKTRACKS", "REALIGN_EVERY"]

#: τ grows by this factor after an accepted step
GROW = 1.5
#: halvings of τ tried before an iteration gives up
MAX_BACKTRACKS = 8
#: every this many accepted steps the shapes' similarities are estimated again (kept if E drops)
REALIGN_EVERY = 10


@dataclass(frozen=True)
class Refinement:
    """The refined landmarks of every shape and how the objective went."""

    points: np.ndarray  # (N, L, 3) normalised frame
    face_index: np.ndarray  # (N, L)
    barycentric: np.ndarray  # (N, L, 3)
    trace: np.ndarray  # (T, 3) E, compactness, spread: at the start and after every accepted step
    rejected: int  # step attempts rejected because E would have risen


def _tangent(gradient: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """g − (g · n) n per landmark."""
    return gradient - np.einsum("mld,mld->ml", gradient, normals)[..., None] * normals


def _capped(step: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """Every landmark's move shortened to at most `cap` (per shape)."""
    length = np.linalg.norm(step, axis=2)
    return step * np.minimum(1.0, cap[:, None] / np.maximum(length, np.finfo(float).tiny))[..., None]


def landmark_state(meshes: Sequence[Mesh], points, face_index, barycentric) -> LandmarkState:
    """The objective's view (positions, face and smooth normals, normal Jacobians) of
    landmarks given on `meshes` (for diagnostics; refine_population keeps its own)."""
    return ShapeShard(meshes, points, face_index, barycentric, 1.0).state(
        np.asarray(points, dtype=np.float64), np.asarray(face_index), np.asarray(barycentric, dtype=np.float64))


def smooth_basis(edges: np.ndarray, n_landmarks: int, size: int) -> np.ndarray | None:
    """The `size` smoothest landmark fields on the landmark graph `edges` (eigenvectors of
    its Laplacian with the smallest eigenvalues, orthonormal columns (L, size)); None
    when `size` is 0 or the graph is too small (plain gradient steps)."""
    if size <= 0 or size >= n_landmarks - 1 or len(edges) == 0:
        return None
    from scipy.sparse import coo_matrix, diags
    from scipy.sparse.linalg import eigsh

    i, j = np.asarray(edges).T
    adjacency = coo_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(n_landmarks,) * 2).tocsr()
    adjacency.data[:] = 1.0
    laplacian = diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency
    _, vectors = eigsh(laplacian, k=size, sigma=-1e-3, which="LM", v0=np.ones(n_landmarks))
    return vectors


def refine_population(meshes: Sequence[Mesh], points: np.ndarray, face_index: np.ndarray, barycentric: np.ndarray,
                      settings: CorrespondenceSettings, progress: Progress | None = None,
                      should_cancel=None, edges: np.ndarray | None = None, jobs: int = 1,
                      compactness=None) -> Refinement:
    """Refine the landmarks (N, L, ...) of shapes `meshes` (normalised frame) by descending
    the population objective (module docstring; `settings.refinement`). edges: the landmark
    graph of the smooth displacement fields (None: plain gradient steps). jobs: processes
    sharing the per-shape work (shards.py). progress: fractions by accepted iterations;
    should_cancel: checked every iteration (errors.Cancelled). compactness: a callable
    (start `LandmarkState` → a term with `CompactnessTerm`'s evaluate / realign / scales /
    rotations) in place of the settings' compactness term (bench/refine_objectives.py
    measures candidate objectives this way); None: `CompactnessTerm` from the settings."""
    report = progress or no_progress
    cancel = CancelCheck(should_cancel, "correspondence")
    shards = Shards(meshes, np.asarray(points), np.asarray(face_index), np.asarray(barycentric), settings.refinement.sigma,
                    jobs)
    try:
        return _descend(shards, settings, edges, report, cancel, compactness)
    finally:
        shards.close()


def population_objective(start: ShardAnswer, settings: CorrespondenceSettings, make_compactness=None):
    """The compactness term anchored at the `start` landmarks (`CompactnessTerm` from the
    settings, or `make_compactness(start.state)`) and `evaluate(answer)` → (E, ∂E/∂X): E =
    w_c C + w_s S̄ of a shards' answer (objective.py)."""
    weights = (settings.refinement.compactness, settings.refinement.spread)
    if make_compactness is None:
        compactness = CompactnessTerm(start.state, settings.refinement.regulariser, settings.refinement.alignment,
                                      settings.refinement.normals)
    else:
        compactness = make_compactness(start.state)

    def evaluate(answer: ShardAnswer):
        value_c, grad_c = compactness.evaluate(answer.state) if weights[0] else (0.0, 0.0)
        return combined(weights, value_c, grad_c, answer.spread, answer.spread_gradient)

    return compactness, evaluate


def _descend(shards: Shards, settings: CorrespondenceSettings, edges, report: Progress, cancel,
             make_compactness=None) -> Refinement:
    """The iterations of `refine_population` (module docstring)."""
    weights = (settings.refinement.compactness, settings.refinement.spread)
    answer = shards.propose(None)
    compactness, evaluate = population_objective(answer, settings, make_compactness)
    value, gradient = evaluate(answer)
    state = answer.state
    trace, rejected = [value.as_row()], 0
    cap = settings.refinement.max_move * shards.spacing
    basis = None if edges is None else smooth_basis(edges, state.points.shape[1], settings.refinement.smooth_fields)
    tau = None
    for iteration in range(settings.refinement.iterations):
        cancel()
        direction = _tangent(gradient, state.face_normals)
        if basis is not None:  # only smooth displacement fields: the whole region slides together
            direction = _tangent(np.einsum("lk,mkd->mld", basis, np.einsum("lk,mld->mkd", basis, direction)),
                                 state.face_normals)
        if tau is None:  # first step: RMS move = refinement.step × the mean spacing
            rms = float(np.sqrt(np.mean(np.sum(direction**2, axis=2))))
            if rms == 0.0:
                break
            tau = settings.refinement.step * float(shards.spacing.mean()) / rms
        for _ in range(MAX_BACKTRACKS + 1):
            candidate = shards.propose(_capped(-tau * direction, cap))
            new_value, new_gradient = evaluate(candidate)
            if new_value.total < value.total:
                break
            rejected += 1
            tau *= 0.5
        else:
            break  # no step lowers E: a (local) minimum at this resolution
        shards.accept()
        decrease = value.total - new_value.total
        value, gradient, state = new_value, new_gradient, candidate.state
        if settings.refinement.alignment != "none" and weights[0] and (iteration + 1) % REALIGN_EVERY == 0:
            old = compactness.scales, compactness.rotations
            compactness.realign(state.points)  # kept only if it lowers E as well
            realigned = evaluate(candidate)
            if realigned[0].total < value.total:
                value, gradient = realigned
            else:
                compactness.scales, compactness.rotations = old
        trace.append(value.as_row())
        tau *= GROW
        report((iteration + 1) / max(settings.refinement.iterations, 1),
               f"refining (iteration {iteration + 1}, objective {value.total:.4f})")
        if decrease <= settings.refinement.tolerance * max(abs(value.total), 1.0):
            break
    points, face_index, barycentric = shards.current()
    return Refinement(points, face_index, barycentric, np.array(trace), rejected)
