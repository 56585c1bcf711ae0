"""The data term E_D of one registration (thesis §4.2.2, eq. 4.11), one piece per term:

    E_D = Σ_i w_i ‖A_i x_i − v_n(i)‖²  +  λ Σ_j w'_j ‖A_m(j) x_m(j) − u_j‖²  (+ known pairs)
          `ForwardTerm`                    `BidirectionalTerm`                `AnchorTerm`

Every term has one method, `pulls(points, normals, features)`: given where the template is
now, the template points it pulls (`Pulls.rows`), where to (`goals`) and how hard
(`weights`) — the rows of W X and C in the stacked system ‖B A − C‖²_F (4.31) that
registration.py solves. The forward and bidirectional terms find their matches through a
`Matches` strategy: `ClosestMatches` (the thesis: closest, normal-compatible points) or
`FeatureMatches` (**beyond** the thesis, `data_term.matching="features"`: nearest in a joint
space of position and surface features, features.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import SurfacePoints, TargetSurface, nearest_facing_alike
from .features import FeatureMatcher, kept_matches
from .settings import DataTermSettings

__all__ = ["Anchors", "Pulls", "DataTerm", "ForwardTerm", "BidirectionalTerm", "AnchorTerm", "Matches",
           "ClosestMatches", "FeatureMatches", "closest_target_points", "match_weights"]


@dataclass(frozen=True)
class Pulls:
    """What one data term asks of the next solve: template point `rows[k]` is pulled
    towards `goals[k]` with weight `weights[k]` (one term of Σ w ‖A_i x_i − goal‖²)."""

    rows: np.ndarray  # (P,) template point indices
    goals: np.ndarray  # (P, 3) positions, in the registration frame
    weights: np.ndarray  # (P,) weights (0: the pair does not count)

    @staticmethod
    def stacked(pulls: list[Pulls]) -> Pulls:
        """All terms' pulls as one system, in the order given."""
        return Pulls(np.concatenate([p.rows for p in pulls]), np.concatenate([p.goals for p in pulls]),
                     np.concatenate([p.weights for p in pulls]))


class DataTerm(Protocol):
    """One term of the data term (module docstring)."""

    def pulls(self, points: np.ndarray, normals: np.ndarray | None, features: np.ndarray | None) -> Pulls:
        """The term's pulls for the template's current points (L, 3), their normals (L, 3;
        None: registered without normals) and features (feature matches only; else None)."""


class Matches(Protocol):
    """How matches are found for the forward and the bidirectional term."""

    def forward(self, points: np.ndarray, normals: np.ndarray | None,
                features: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """v_n(i) of every template point (L, 3) and its weight w_i (L,)."""

    def backward(self, points: np.ndarray, normals: np.ndarray | None,
                 features: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """m(j), the template point of every target landmark (T,), and its weight w'_j
        before λ (T,)."""


# ---------------------------------------------------------------------------- the terms
class ForwardTerm:
    """Σ_i w_i ‖A_i x_i − v_n(i)‖²: every template point pulled to its match on the target."""

    def __init__(self, matches: Matches):
        self.matches = matches

    def pulls(self, points: np.ndarray, normals: np.ndarray | None, features: np.ndarray | None) -> Pulls:
        goals, weights = self.matches.forward(points, normals, features)
        return Pulls(np.arange(len(points)), goals, weights)


class BidirectionalTerm:
    """λ Σ_j w'_j ‖A_m(j) x_m(j) − u_j‖²: every target landmark u_j pulls its match m(j)
    among the template points, so the template covers the whole target (Fig. 4.6)."""

    def __init__(self, matches: Matches, target_landmarks: np.ndarray, weight: float):
        self.matches = matches
        self.target_landmarks = target_landmarks
        self.weight = weight  # λ

    def pulls(self, points: np.ndarray, normals: np.ndarray | None, features: np.ndarray | None) -> Pulls:
        nearest, weights = self.matches.backward(points, normals, features)
        return Pulls(nearest, self.target_landmarks, self.weight * weights)


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


class AnchorTerm:
    """Σ_k weight ‖A_i x_i − p_k‖² of the known pairs (`Anchors`)."""

    def __init__(self, anchors: Anchors):
        self.anchors = anchors

    def pulls(self, points: np.ndarray, normals: np.ndarray | None, features: np.ndarray | None) -> Pulls:
        anchors = self.anchors
        return Pulls(anchors.indices, anchors.positions, np.full(len(anchors.indices), anchors.weight))


# ---------------------------------------------------------------------------- the matches
class ClosestMatches:
    """The thesis's matches: closest points, normal-compatible when `normal_max_angle` is
    set (§4.2.2). `finder`: an object with the `closest` method of `target` (its
    `tracker()`, which keeps candidate faces between iterations)."""

    def __init__(self, target: TargetSurface, finder, target_landmarks: np.ndarray,
                 target_landmark_normals: np.ndarray | None, settings: DataTermSettings):
        self.target = target
        self.finder = finder
        self.target_landmarks = target_landmarks
        self.target_landmark_normals = target_landmark_normals
        self.settings = settings

    def forward(self, points: np.ndarray, normals: np.ndarray | None,
                features: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        matches, weights = closest_target_points(self.target, points, normals, self.settings, self.finder)
        return matches.points, weights

    def backward(self, points: np.ndarray, normals: np.ndarray | None,
                 features: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The template point closest to every target landmark (the closest with a
        compatible normal when `normal_max_angle` is set, searched among the 8 nearest)."""
        settings, landmark_normals = self.settings, self.target_landmark_normals
        if settings.normal_max_angle is None or normals is None or landmark_normals is None:
            distance, nearest = cKDTree(points).query(self.target_landmarks)
        else:
            nearest, distance = nearest_facing_alike(points, normals, self.target_landmarks, landmark_normals,
                                                     _min_cos(settings))
        return nearest, match_weights(distance, settings)


class FeatureMatches:
    """Feature-space matches (features.py `FeatureMatcher`, **beyond** the thesis): the
    template points marked `plain` (L,) bool compare position and normal only
    (features.merged_regions); forward matches beyond the trimming distance get weight 0
    (features.kept_matches)."""

    def __init__(self, matcher: FeatureMatcher, plain: np.ndarray | None, settings: DataTermSettings):
        self.matcher = matcher
        self.plain = plain
        self.settings = settings

    def forward(self, points: np.ndarray, normals: np.ndarray | None,
                features: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        goals, distance = self.matcher.forward(points, features, self.plain)
        return goals, match_weights(distance, self.settings) * kept_matches(distance)

    def backward(self, points: np.ndarray, normals: np.ndarray | None,
                 features: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        nearest, distance = self.matcher.backward(points, features, self.plain)
        return nearest, match_weights(distance, self.settings)


def closest_target_points(target: TargetSurface, points: np.ndarray, normals: np.ndarray | None,
                          settings: DataTermSettings, finder=None) -> tuple[SurfacePoints, np.ndarray]:
    """v_n(i) of (4.11): closest target point of every template point (the closest point
    with a compatible normal when `normal_max_angle` is set; the nearest vertex with
    `snap_to_vertices`), and its weight w_i. `finder`: an object with the `closest` method
    of `target` (e.g. its `tracker()`). An unmatched point (none compatible) keeps its own
    position as goal, with weight 0 and distance inf."""
    finder = target if finder is None else finder
    if settings.snap_to_vertices:
        matches = target.closest_vertices(points)
        if settings.normal_max_angle is not None and normals is not None:
            incompatible = _min_cos(settings) > np.einsum("nd,nd->n", target.face_normals[matches.face_index], normals)
            matches.distance[incompatible] = np.inf
    elif settings.normal_max_angle is not None and normals is not None:
        matches = finder.closest(points, normals, _min_cos(settings))
    else:
        matches = finder.closest(points)
    unmatched = ~np.isfinite(matches.distance)
    matches.points[unmatched] = points[unmatched]  # any finite goal: its weight is 0
    return matches, match_weights(matches.distance, settings)


def match_weights(distance: np.ndarray, settings: DataTermSettings) -> np.ndarray:
    """w of every match: (4.12–4.13) with `distance_weights`, otherwise 1 (0 where unmatched: d = inf)."""
    return _distance_weights(distance) if settings.distance_weights else np.isfinite(distance).astype(float)


def _distance_weights(distance: np.ndarray) -> np.ndarray:
    """(4.12–4.13): s = 1 / (1 + d), normalised by the largest s; 0 where d is inf."""
    s = np.where(np.isfinite(distance), 1.0 / (1.0 + distance), 0.0)
    return s / s.max() if s.max() > 0 else s


def _min_cos(settings: DataTermSettings) -> float:
    """cos of `normal_max_angle`: the least cosine between the normals of a match."""
    return float(np.cos(np.radians(settings.normal_max_angle)))
