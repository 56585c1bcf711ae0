"""One registration: the template's landmarks deformed onto one target surface by
non-rigid ICP with stiffness relaxation (thesis §4.2, Alg. 3; Amberg et al. 2007).

Per iteration: forward matches v_n(i) (closest, normal-compatible target point of every
template point), backward matches m(j) (closest template point of every target
landmark, weighted by λ), optional known pairs (`Anchors`), one affine-graph solve (4.31,
core/geometry/affine_graph.py), move the points. At the end every point is placed on the
target surface (or snapped to a vertex). With `matching="features"` (beyond the thesis,
features.py) both kinds of match are nearest points in a joint space of position and
surface features instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import (AffineSolver, SurfacePoints, TargetSurface, apply_affines, data_blocks, nearest_facing_alike,
                        stiffness_energy, transform_normals)
from ..progress import CancelCheck
from .features import FeatureMatcher, kept_matches, point_features, uses_between, uses_features
from .settings import CorrespondenceSettings

__all__ = ["Anchors", "Registration", "fit_residual", "register"]


@dataclass(frozen=True)
class Registration:
    """One template → target registration (Alg. 3), in the frame of the given points."""

    placed: SurfacePoints  # final template points on the target (surface or vertex)
    normals: np.ndarray  # (L, 3) target normals at the placed points
    deformed: np.ndarray  # (L, 3) template points after the last ICP step, before placement
    residual: float  # √(E_D / Σ weights) of the final matches, in the frame's units
    iterations: int
    energies: np.ndarray  # objective after every iteration
    deformed_normals: np.ndarray | None = None  # (L, 3) template normals after the last step (None: no normals)
    between: np.ndarray | None = None  # (L,) the target's positions between turning lines at the placed points (features.py)
    regions: np.ndarray | None = None  # (L,) the target's region at the placed points (features.merged_regions)


def _distance_weights(distance: np.ndarray) -> np.ndarray:
    """(4.12–4.13): s = 1 / (1 + d), normalised by the largest s; 0 where d is inf."""
    s = np.where(np.isfinite(distance), 1.0 / (1.0 + distance), 0.0)
    return s / s.max() if s.max() > 0 else s


def _match_weights(distance: np.ndarray, settings: CorrespondenceSettings) -> np.ndarray:
    """w of every match: (4.12–4.13) with `distance_weights`, otherwise 1 (0 where unmatched: d = inf)."""
    return _distance_weights(distance) if settings.distance_weights else np.isfinite(distance).astype(float)


def _forward_matches(target: TargetSurface, points: np.ndarray, normals: np.ndarray | None,
                     settings: CorrespondenceSettings, finder=None) -> tuple[SurfacePoints, np.ndarray]:
    """v_n(i) of (4.11): closest target point of every template point (the closest point
    with a compatible normal when `normal_max_angle` is set), and its weight w_i.
    `finder`: an object with the `closest` method of `target` (e.g. its `tracker()`)."""
    finder = target if finder is None else finder
    if settings.snap_to_vertices:
        matches = target.closest_vertices(points)
        if settings.normal_max_angle is not None and normals is not None:
            incompatible = _cos(settings) > np.einsum("nd,nd->n", target.face_normals[matches.face_index], normals)
            matches.distance[incompatible] = np.inf
    elif settings.normal_max_angle is not None and normals is not None:
        matches = finder.closest(points, normals, _cos(settings))
    else:
        matches = finder.closest(points)
    unmatched = ~np.isfinite(matches.distance)
    matches.points[unmatched] = points[unmatched]  # any finite goal: its weight is 0
    return matches, _match_weights(matches.distance, settings)


def _backward_matches(points: np.ndarray, normals: np.ndarray | None, target_landmarks: np.ndarray,
                      target_normals: np.ndarray | None, settings: CorrespondenceSettings
                      ) -> tuple[np.ndarray, np.ndarray]:
    """m(j) of (4.11): the template point closest to every target landmark u_j (the
    closest with a compatible normal when `normal_max_angle` is set, searched among the
    8 nearest), and its weight w'_j (before λ)."""
    if settings.normal_max_angle is None or normals is None or target_normals is None:
        distance, nearest = cKDTree(points).query(target_landmarks)
    else:
        nearest, distance = nearest_facing_alike(points, normals, target_landmarks, target_normals, _cos(settings))
    return nearest, _match_weights(distance, settings)


def _cos(settings: CorrespondenceSettings) -> float:
    return float(np.cos(np.radians(settings.normal_max_angle)))


@dataclass(frozen=True)
class Anchors:
    """Known correspondences: template point `indices[k]` belongs at `positions[k]` on the
    target. Each adds `weight` ‖A_i x_i − p_k‖² to the data term at every iteration (the
    landmark term of Amberg et al. 2007, as in trimesh's `nricp_amberg`), so a user's
    hand-placed pairs (or a benchmark's ground truth) steer the registration."""

    indices: np.ndarray  # (K,) template point indices
    positions: np.ndarray  # (K, 3) target positions, in the registration frame
    weight: float = 10.0

    def __post_init__(self):
        indices = np.asarray(self.indices)
        positions = np.asarray(self.positions, dtype=np.float64)
        if indices.ndim != 1 or positions.shape != (len(indices), 3) or not np.isfinite(positions).all():
            raise ValueError(f"anchors need K indices and K finite 3-D positions, got {indices.shape} and {positions.shape}")
        if not self.weight > 0:
            raise ValueError(f"anchor weight must be > 0, got {self.weight}")


def register(
    template: np.ndarray,
    edges: np.ndarray,
    target: TargetSurface,
    target_landmarks: np.ndarray,
    settings: CorrespondenceSettings = CorrespondenceSettings(),
    template_normals: np.ndarray | None = None,
    target_landmark_normals: np.ndarray | None = None,
    on_iteration: Callable[[int], None] | None = None,
    should_cancel=None,
    anchors: Anchors | None = None,
    initial_points: np.ndarray | None = None,
    initial_normals: np.ndarray | None = None,
    template_between: np.ndarray | None = None,
    plain_points: np.ndarray | None = None,
) -> Registration:
    """Iterative stiffness relaxation (Alg. 3) of `template` (L, 3) onto `target`.

    All coordinates in one frame (see `correspond` for the frame used). Per iteration:
    closest target points v_n(i) of the current template points, closest current template
    point m(j) of each target landmark u_j, (known pairs from `anchors`,) one sparse solve
    (4.31), move the points. With `update_template` the next solve starts from the moved
    points (the thesis's Alg. 3); otherwise from the original template (Amberg et al.).
    `initial_points` (L, 3): a warm start, where the template points begin (e.g. an earlier
    registration's `deformed`); the affines still act on `template`. `initial_normals`
    (L, 3): the template's normals at that start (the earlier registration's `normals`),
    which feature-space matches compare from the first iteration on. `template_between`
    (L,): the template points' positions between turning lines (turning.py; groupwise: the
    template shape's own), compared by feature matches when `feature_between` > 0; with
    feature matches and `feature_between` > 0 the result reports the target's positions at
    its placed points (`Registration.between`), given a template's or not; with
    feature matches it reports the target's regions there (`Registration.regions`).
    `plain_points` (L,) bool: template points feature matches compare by position and
    normal only (features.merged_regions). Raises Cancelled
    between iterations once `should_cancel` (None, a callable or an Event-like object;
    core/progress.py) says so."""
    base = np.asarray(template, dtype=np.float64)
    if anchors is not None and (np.asarray(anchors.indices) >= len(base)).any():
        raise ValueError(f"anchor indices must be < {len(base)} (the template's point count)")
    base_normals = None if template_normals is None else np.asarray(template_normals, dtype=np.float64)
    points, normals = base.copy(), base_normals
    if initial_points is not None:
        initial_points = np.asarray(initial_points, dtype=np.float64)
        if initial_points.shape != base.shape or not np.isfinite(initial_points).all():
            raise ValueError(f"initial_points must be finite with the template's shape {base.shape}, "
                             f"got {initial_points.shape}")
        points = initial_points.copy()
    warm_normals = None
    if initial_normals is not None:
        warm_normals = np.asarray(initial_normals, dtype=np.float64)
        if base_normals is None or warm_normals.shape != base.shape or not np.isfinite(warm_normals).all():
            raise ValueError(f"initial_normals must be finite with the template's shape {base.shape}, beside "
                             f"template_normals, got {warm_normals.shape}")
        normals = warm_normals
    n_points = len(points)
    cancel = CancelCheck(should_cancel, "correspondence")
    solver = AffineSolver(edges, n_points, settings.gamma)
    finder = target.tracker()  # closest points with candidate faces kept between iterations
    lam = settings.bidirectional_weight
    energies: list[float] = []
    previous = np.inf
    iteration = 0
    features = None
    matcher = None
    between = None
    if uses_features(settings) and base_normals is not None:
        if template_between is not None and uses_between(settings):
            between = np.asarray(template_between, dtype=np.float64)
            if between.shape != (n_points,) or not np.isfinite(between).all():
                raise ValueError(f"template_between must be finite with one value per template point ({n_points}), "
                                 f"got {between.shape}")
        if plain_points is not None:
            plain_points = np.asarray(plain_points)
            if plain_points.shape != (n_points,) or plain_points.dtype != bool:
                raise ValueError(f"plain_points must be one bool per template point ({n_points}), got "
                                 f"{plain_points.shape} {plain_points.dtype}")
        matcher = FeatureMatcher(target, target_landmarks, target_landmark_normals, n_points, settings,
                                 with_between=between is not None)
        features = point_features(normals, settings, between)
    for alpha_index, alpha in enumerate(settings.alphas):
        if features is not None and alpha_index == 1 and warm_normals is None:  # the template's features as the stiffest α fitted them
            features = point_features(normals, settings, between)
        for _ in range(settings.max_iterations_per_alpha):
            cancel()
            if features is None:
                forward, weights = _forward_matches(target, points, normals, settings, finder)
                goals = forward.points
            else:
                goals, distance = matcher.forward(points, features, plain_points)
                weights = _match_weights(distance, settings) * kept_matches(distance)
            rows = np.arange(n_points)
            if lam > 0:
                if features is None:
                    nearest, w_back = _backward_matches(points, normals, target_landmarks,
                                                        target_landmark_normals, settings)
                else:
                    nearest, distance = matcher.backward(points, features, plain_points)
                    w_back = _match_weights(distance, settings)
                rows = np.r_[rows, nearest]
                goals = np.vstack([goals, target_landmarks])
                weights = np.r_[weights, lam * w_back]
            if anchors is not None:
                rows = np.r_[rows, anchors.indices]
                goals = np.vstack([goals, anchors.positions])
                weights = np.r_[weights, np.full(len(anchors.indices), anchors.weight)]
            if settings.update_template:  # Alg. 3: affines act on the current points
                base, base_normals = points, normals
            blocks, rhs = data_blocks(base, rows, goals, weights, n_points)
            affines = solver.solve(alpha, blocks, rhs, settings.ridge)
            moved = apply_affines(affines, base)
            data = float((weights * ((moved[rows] - goals) ** 2).sum(axis=1)).sum())
            energy = data + alpha**2 * stiffness_energy(affines, edges, settings.gamma)
            energies.append(energy)
            if normals is not None:
                normals = transform_normals(affines, base_normals)
            points = moved
            iteration += 1
            if on_iteration is not None:
                on_iteration(iteration)
            # relative change, with a floor far below any real fit (frame units: unit RMS radius)
            converged = np.isfinite(previous) and (
                abs(previous - energy) <= settings.tolerance * previous + 1e-12 * len(rows))
            previous = energy
            if iteration >= settings.max_iterations or converged:
                break
        if iteration >= settings.max_iterations:
            break
    placed = _place(target, points, normals, settings, finder)
    residual = fit_residual(placed, target_landmarks)
    placed_normals = target.face_normals[placed.face_index]
    target_between = None if matcher is None else matcher.positions_at(placed.points, placed_normals)
    target_regions = None if matcher is None else matcher.regions_at(placed.points, placed_normals)
    return Registration(placed, placed_normals, points, residual, iteration, np.asarray(energies), normals,
                        target_between, target_regions)


def _place(target: TargetSurface, points: np.ndarray, normals: np.ndarray | None,
           settings: CorrespondenceSettings, finder=None) -> SurfacePoints:
    """Final placement of the template points on the target (Alg. 3, line 11): the closest
    surface point (compatible, if normals are used and one exists), or the nearest vertex."""
    matches, _ = _forward_matches(target, points, normals, settings, finder)
    missing = ~np.isfinite(matches.distance)
    if missing.any():
        plain = target.closest_vertices(points[missing]) if settings.snap_to_vertices else target.closest(points[missing])
        for array, value in zip((matches.points, matches.face_index, matches.barycentric, matches.distance),
                                (plain.points, plain.face_index, plain.barycentric, plain.distance)):
            array[missing] = value
    return matches


def fit_residual(placed: SurfacePoints, target_landmarks: np.ndarray) -> float:
    """RMS of the bidirectional data term at the end (unit weights): template points to the
    surface before placement, and target landmarks to the nearest placed point (coverage;
    counted even when λ = 0 so a template covering half the target is never hidden)."""
    coverage, _ = cKDTree(placed.points).query(target_landmarks)
    squares = np.r_[placed.distance**2, coverage**2]
    return float(np.sqrt(squares.mean()))
