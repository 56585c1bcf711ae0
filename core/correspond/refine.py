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
   and the step tried again (up to `MAX_BACKTRACKS` times): E decreases monotonically.

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
from .objective import PopulationObjective
from .settings import REFINE_METHODS, CorrespondenceSettings

__all__ = ["Refinement", "refine_population", "REFINE_METHODS", "GROW", "MAX_BACKTRACKS"]

#: τ grows by this factor after an accepted step
GROW = 1.5
#: halvings of τ tried before an iteration gives up
MAX_BACKTRACKS = 8
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


def _tangent(gradient: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """g − (g · n) n per landmark."""
    return gradient - np.einsum("mld,mld->ml", gradient, normals)[..., None] * normals


def _capped(step: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """Every landmark's move shortened to at most `cap` (per shape)."""
    length = np.linalg.norm(step, axis=2)
    return step * np.minimum(1.0, cap[:, None] / np.maximum(length, np.finfo(float).tiny))[..., None]


def refine_population(meshes: Sequence[Mesh], points: np.ndarray, face_index: np.ndarray, barycentric: np.ndarray,
                      settings: CorrespondenceSettings, progress: Progress | None = None,
                      should_cancel=None) -> Refinement:
    """Refine the landmarks (N, L, ...) of shapes `meshes` (normalised frame) by descending
    the population objective (module docstring; settings `refine_*`). progress: fractions
    by accepted iterations; should_cancel: checked every iteration (errors.Cancelled)."""
    report = progress or no_progress
    cancel = CancelCheck(should_cancel, "correspondence")
    shapes = _Shapes(meshes, points, face_index, barycentric)
    objective = PopulationObjective(shapes.points, shapes.normals(), [mesh.area() for mesh in meshes], settings.refine_compactness,
                                    settings.refine_spread, settings.refine_regulariser, settings.refine_sigma,
                                    settings.refine_alignment)
    value, gradient = objective.evaluate(shapes.points, shapes.normals())
    trace, rejected = [value.as_row()], 0
    cap = settings.refine_max_move * shapes.spacing
    tau = None
    for iteration in range(settings.refine_iterations):
        cancel()
        direction = _tangent(gradient, shapes.normals())
        if tau is None:  # first step: RMS move = refine_step × the mean spacing
            rms = float(np.sqrt(np.mean(np.sum(direction**2, axis=2))))
            if rms == 0.0:
                break
            tau = settings.refine_step * float(shapes.spacing.mean()) / rms
        for _ in range(MAX_BACKTRACKS + 1):
            candidate = shapes.moved(_capped(-tau * direction, cap))
            new_value, new_gradient = objective.evaluate(candidate[0], shapes.normals(candidate[1]))
            if new_value.total < value.total:
                break
            rejected += 1
            tau *= 0.5
        else:
            break  # no step lowers E: a (local) minimum at this resolution
        decrease = value.total - new_value.total
        shapes.points, shapes.face_index, shapes.barycentric = candidate
        value, gradient = new_value, new_gradient
        trace.append(value.as_row())
        tau *= GROW
        report((iteration + 1) / settings.refine_iterations,
               f"refining (iteration {iteration + 1}, objective {value.total:.4f})")
        if decrease <= settings.refine_tolerance * max(abs(value.total), 1.0):
            break
    return Refinement(shapes.points, shapes.face_index, shapes.barycentric, np.array(trace), rejected)
