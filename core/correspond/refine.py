"""Groupwise refinement after non-rigid ICP (**beyond** the thesis): every landmark slides
on its own shape's surface to lower the population objective of objective.py
(compactness of the landmark population + a spread term per shape; Davies et al. 2002,
Cates et al. 2007).

One iteration (projected gradient descent with backtracking):

1. E and ∂E/∂x of every landmark (objective.py; N × N dual for the compactness);
2. the gradient projected onto the landmark's tangent plane (its face normal n:
   g − (g · n) n), a step −τ g with every landmark's move capped at `max_move` × the
   shape's landmark spacing √(area / L);
3. each moved landmark mapped back onto its surface by the closest point whose face
   normal is compatible (n_new · n_old >= 0: never through a thin wall), giving its new
   face index and barycentric coordinates (a landmark with no compatible face nearby
   stays put); every shape's closest-point structure is built once and tracks its
   landmarks between iterations (geometry.TargetSurface.tracker), so the cost per
   iteration is O(N L log L) plus the closest-point queries, whatever the mesh size;
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

from ..geometry import TargetSurface
from ..mesh import Mesh
from ..progress import CancelCheck, Progress, no_progress
from .objective import LandmarkState, PopulationObjective
from .settings import REFINE_METHODS, CorrespondenceSettings

__all__ = ["Refinement", "refine_population", "landmark_state", "interpolated_normals", "REFINE_METHODS", "GROW", "MAX_BACKTRACKS"]

#: τ grows by this factor after an accepted step
GROW = 1.5
#: halvings of τ tried before an iteration gives up
MAX_BACKTRACKS = 8
#: every this many accepted steps the shapes' similarities are estimated again (kept if E drops)
REALIGN_EVERY = 10
#: a moved landmark may map onto faces whose normal is at most 90° from its old face's
_MIN_NORMAL_COS = 0.0


@dataclass(frozen=True)
class Refinement:
    """The refined landmarks of every shape and how the objective went."""

    points: np.ndarray  # (N, L, 3) normalised frame
    face_index: np.ndarray  # (N, L)
    barycentric: np.ndarray  # (N, L, 3)
    trace: np.ndarray  # (T, 3) E, compactness, spread: at the start and after every accepted step
    rejected: int  # step attempts rejected because E would have risen


class _Shapes:
    """The active shapes' surfaces (built once), their landmarks and the moves onto them."""

    def __init__(self, meshes: Sequence[Mesh], points, face_index, barycentric):
        self.surfaces = [TargetSurface(mesh.vertices, mesh.faces) for mesh in meshes]
        self.trackers = [surface.tracker() for surface in self.surfaces]
        self.points = np.array(points, dtype=np.float64)
        self.face_index = np.array(face_index, dtype=np.int64)
        self.barycentric = np.array(barycentric, dtype=np.float64)
        n_landmarks = self.points.shape[1]
        self.spacing = np.array([np.sqrt(mesh.area() / n_landmarks) for mesh in meshes])
        self.vertex_normals = [mesh.vertex_normals() for mesh in meshes]

    def state(self, points=None, face_index=None, barycentric=None) -> LandmarkState:
        """The objective's view of landmarks (default: the current ones)."""
        points = self.points if points is None else points
        face_index = self.face_index if face_index is None else face_index
        barycentric = self.barycentric if barycentric is None else barycentric
        smooth = [interpolated_normals(s.triangles[f], v[s.faces[f]], b)
                  for s, v, f, b in zip(self.surfaces, self.vertex_normals, face_index, barycentric)]
        return LandmarkState(points, self.normals(face_index), np.stack([n for n, _ in smooth]),
                             np.stack([j for _, j in smooth]))

    def normals(self, face_index: np.ndarray | None = None) -> np.ndarray:
        faces = self.face_index if face_index is None else face_index
        return np.stack([s.face_normals[f] for s, f in zip(self.surfaces, faces)])

    def moved(self, step: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The landmarks moved by `step` (N, L, 3) and mapped back onto their surfaces."""
        points, faces, barys = self.points.copy(), self.face_index.copy(), self.barycentric.copy()
        normals = self.normals()
        for m, tracker in enumerate(self.trackers):
            found = tracker.closest(self.points[m] + step[m], normals[m], _MIN_NORMAL_COS)
            ok = np.isfinite(found.distance)
            points[m, ok], faces[m, ok], barys[m, ok] = found.points[ok], found.face_index[ok], found.barycentric[ok]
        return points, faces, barys


def interpolated_normals(triangles: np.ndarray, corner_normals: np.ndarray, barycentric: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Smooth normals n = ñ / |ñ|, ñ = Σ_k b_k n_k (Phong), at points with barycentrics b on
    triangles (n, 3, 3) with corner normals (n, 3, 3), and their Jacobians ∂n/∂x (n, 3, 3)
    for x moving along the triangle: with e1 = b − a, e2 = c − a and G their Gram matrix,
    (dv, dw) = G⁻¹ (e1 · dx, e2 · dx), dñ = (n_b − n_a) dv + (n_c − n_a) dw, and
    dn = (I − n nᵀ) dñ / |ñ| (a move off the plane changes nothing)."""
    raw = np.einsum("nk,nkd->nd", barycentric, corner_normals)
    length = np.maximum(np.linalg.norm(raw, axis=1), np.finfo(float).tiny)
    normals = raw / length[:, None]
    edges = np.stack([triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]], axis=1)  # (n, 2, 3)
    gram = np.einsum("nid,njd->nij", edges, edges)
    determinant = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] ** 2
    safe = np.where(np.abs(determinant) > 0, determinant, 1.0)
    inverse = np.stack([np.stack([gram[:, 1, 1], -gram[:, 0, 1]], 1), np.stack([-gram[:, 0, 1], gram[:, 0, 0]], 1)],
                       1) / safe[:, None, None]
    inverse[np.abs(determinant) == 0] = 0.0  # a degenerate face: its normal does not move
    turn = np.stack([corner_normals[:, 1] - corner_normals[:, 0], corner_normals[:, 2] - corner_normals[:, 0]],
                    axis=2)  # (n, 3, 2)
    raw_jacobian = turn @ inverse @ edges  # (n, 3, 3)
    projector = np.eye(3) - normals[:, :, None] * normals[:, None, :]
    return normals, projector @ raw_jacobian / length[:, None, None]


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
    return _Shapes(meshes, points, face_index, barycentric).state()


def _realigned(objective: PopulationObjective, shapes: _Shapes, value, gradient):
    """Every shape's similarity estimated again from the current landmarks, kept only if
    it lowers E (so E still decreases monotonically)."""
    old = objective.scales, objective.rotations
    objective.realign(shapes.points)
    new_value, new_gradient = objective.evaluate(shapes.state())
    if new_value.total < value.total:
        return new_value, new_gradient
    objective.scales, objective.rotations = old
    return value, gradient


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
                      should_cancel=None, edges: np.ndarray | None = None) -> Refinement:
    """Refine the landmarks (N, L, ...) of shapes `meshes` (normalised frame) by descending
    the population objective (module docstring; settings `refine_*`). progress: fractions
    by accepted iterations; should_cancel: checked every iteration (errors.Cancelled)."""
    report = progress or no_progress
    cancel = CancelCheck(should_cancel, "correspondence")
    shapes = _Shapes(meshes, points, face_index, barycentric)
    objective = PopulationObjective(shapes.state(), [mesh.area() for mesh in meshes], settings.refine_compactness,
                                    settings.refine_spread, settings.refine_regulariser, settings.refine_sigma,
                                    settings.refine_alignment, settings.refine_normals)
    value, gradient = objective.evaluate(shapes.state())
    trace, rejected = [value.as_row()], 0
    cap = settings.refine_max_move * shapes.spacing
    basis = None if edges is None else smooth_basis(edges, shapes.points.shape[1], settings.refine_smooth_fields)
    tau = None
    for iteration in range(settings.refine_iterations):
        cancel()
        direction = _tangent(gradient, shapes.normals())
        if basis is not None:  # only smooth displacement fields: the whole region slides together
            direction = _tangent(np.einsum("lk,mkd->mld", basis, np.einsum("lk,mld->mkd", basis, direction)),
                                 shapes.normals())
        if tau is None:  # first step: RMS move = refine_step × the mean spacing
            rms = float(np.sqrt(np.mean(np.sum(direction**2, axis=2))))
            if rms == 0.0:
                break
            tau = settings.refine_step * float(shapes.spacing.mean()) / rms
        for _ in range(MAX_BACKTRACKS + 1):
            candidate = shapes.moved(_capped(-tau * direction, cap))
            new_value, new_gradient = objective.evaluate(shapes.state(*candidate))
            if new_value.total < value.total:
                break
            rejected += 1
            tau *= 0.5
        else:
            break  # no step lowers E: a (local) minimum at this resolution
        decrease = value.total - new_value.total
        shapes.points, shapes.face_index, shapes.barycentric = candidate
        value, gradient = new_value, new_gradient
        if settings.refine_alignment == "similarity" and (iteration + 1) % REALIGN_EVERY == 0:
            value, gradient = _realigned(objective, shapes, value, gradient)
        trace.append(value.as_row())
        tau *= GROW
        report((iteration + 1) / settings.refine_iterations,
               f"refining (iteration {iteration + 1}, objective {value.total:.4f})")
        if decrease <= settings.refine_tolerance * max(abs(value.total), 1.0):
            break
    return Refinement(shapes.points, shapes.face_index, shapes.barycentric, np.array(trace), rejected)
