"""Which axis of a shape is its up, by the symmetries the collection's shapes share about
their up axes: evidence for "up" that needs no nearest shapes in the right pose,
so a group of similar shapes lying on their side together (PSB cups 26, 27, 29, teapots
367, 379) is stood up, while a bowl among jugs, whose jugs would rather see it on its
side, stays upright.

For a direction d through the surface centroid of a shape's samples P (unit total
variance, `posesearch`), two self-Chamfer costs (`geometry.chamfer`), divided by the
shape's sampling noise ν (the Chamfer distance between two independent samplings of its
surface, the cost of an exact symmetry), in logs:

    rot(d) = log( mean_θ C(Rot_d(θ) P, P) / ν ),  θ ∈ 60°, 90°, 120°, 180°
    mir(d) = log( C(H_d P, P) / ν ),               H_d = I − 2 d dᵀ (mirror across d's plane)

A vase, cup or bowl turns into itself about its up axis (rot small) and not across its
middle (mir large); a fish or an airplane mirrors across a plane that contains its up
axis or is normal to it, each class its own way. The axis descriptor of a pose (rows u,
h1, h2 of its rotation: up and the two horizontals) is

    D = (rot(u), mir(u), min_h rot(h), min_h mir(h), max_h rot(h), max_h mir(h)),

free of the turn about up. The collection's up profile is the median and the MAD
(1.4826 × median absolute deviation, at least `floor`) of D over the shapes in their
pose, twice: the second time over the shapes whose up scores best of their three axes
(a two-pass estimate from the confidently posed majority). The score of a candidate up
axis of a shape is the RMS of D's robust z-scores: small when that axis looks like the
collection's up axes. Calibration (bench/orientation.py): shapes of consistent procedural
classes score their up axis at most 1.6 and every other axis at least 2; PSB cups lying
on their side score their up 1.3-1.4 and their own axis 0.2-0.7; PSB bowls among jugs
score their up 0.4-1.6 and a horizontal axis at least 1.7.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.optimize import minimize
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from ..geometry.chamfer import chamfer_distance
from ..meshes.mesh import Mesh
from ..base.progress import Progress, no_progress
from .moments import surface_moments
from .posesearch import PoseSearch
from .rotations import TILTS

__all__ = ["AxisSymmetry", "ROTATION_ANGLES", "tilt_to_z"]

#: turns about an axis whose mean self-Chamfer cost measures rotational symmetry (degrees)
ROTATION_ANGLES = (60.0, 90.0, 120.0, 180.0)
#: the largest tilt of up `best_up` searches (degrees); larger turns are changes of axis
MAX_TILT = 60.0


class AxisSymmetry:
    """Symmetry costs of every shape of a `PoseSearch` about any direction of its base
    frame (module docstring), and the scores of candidate up axes against the
    collection's up profile."""

    def __init__(self, search: PoseSearch, noise: Sequence[float], floor: float):
        self.search = search
        self.noise = np.asarray(noise, dtype=np.float64)
        self.floor = floor
        self._costs: dict[tuple[int, bytes], np.ndarray] = {}
        self.centre = np.zeros(6)
        self.spread = np.ones(6)
        self.fitted = False  # an up profile was estimated (`fit_profile`)

    @classmethod
    def of(cls, search: PoseSearch, meshes: Sequence[Mesh], base: Sequence[np.ndarray], seed: int,
           floor: float, progress: Progress | None = None) -> "AxisSymmetry":
        """The sampling noise ν of every shape: its samples against a second, independent
        sampling (generator seeded by (seed, i, 1)) in the same frame; `progress` per shape."""
        noise, report = [], progress or no_progress
        for i, (mesh, rotation) in enumerate(zip(meshes, base)):
            _, mean, cov = surface_moments(mesh)
            samples = search.samples[i]
            other = mesh.sample_surface(len(samples), np.random.default_rng([seed, i, 1])).points
            other = (other - mean) @ rotation.T / np.sqrt(np.trace(cov))
            noise.append(max(chamfer_distance(other, samples, None, cKDTree(other), search.trees[i]), 1e-300))
            report((i + 1) / len(meshes), f"sampling noise of shape {i + 1} of {len(meshes)}")
        return cls(search, noise, floor)

    def axis_costs(self, j: int, direction: np.ndarray) -> np.ndarray:
        """(rot(d), mir(d)) of shape j about the unit direction d of its base frame."""
        direction = np.asarray(direction, dtype=np.float64)
        key = (j, np.abs(direction).tobytes() if np.count_nonzero(direction) == 1 else direction.tobytes())
        if key not in self._costs:
            points, tree = self.search.samples[j], self.search.trees[j]
            turns = Rotation.from_rotvec(np.radians(ROTATION_ANGLES)[:, None] * direction[None, :]).as_matrix()
            rot = np.mean([chamfer_distance(points, points, turn, tree, tree) for turn in turns])
            mirror = np.eye(3) - 2.0 * np.outer(direction, direction)
            mir = chamfer_distance(points, points, mirror, tree, tree)
            self._costs[key] = np.log(np.maximum([rot, mir], 1e-300) / self.noise[j])
        return self._costs[key]

    def descriptor(self, j: int, rotation: np.ndarray) -> np.ndarray:
        """D of shape j turned by `rotation` (up: the base direction turned to z)."""
        up = self.axis_costs(j, rotation[2])
        horizontal = np.stack([self.axis_costs(j, rotation[0]), self.axis_costs(j, rotation[1])])
        return np.concatenate([up, horizontal.min(axis=0), horizontal.max(axis=0)])

    def fit_profile(self, rotations: Sequence[np.ndarray], members: Sequence[int]) -> None:
        """The collection's up profile: two passes of median and MAD of D over `members`
        in their `rotations`, the second over those whose up scores best of their axes."""
        members = list(members)
        for _ in range(2):
            descriptors = np.array([self.descriptor(j, rotations[j]) for j in members])
            self.centre = np.median(descriptors, axis=0)
            mad = 1.4826 * np.median(np.abs(descriptors - self.centre), axis=0)
            self.spread = np.maximum(mad, self.floor)
            self.fitted = True
            confident = [j for j in members if np.argmin(self.axis_scores(j, rotations[j])) == 0]
            if len(confident) < max(3, len(members) // 2):
                break
            members = confident

    def score(self, j: int, rotation: np.ndarray) -> float:
        """RMS robust z-score of D of shape j in `rotation` against the up profile."""
        return float(np.sqrt(np.mean(((self.descriptor(j, rotation) - self.centre) / self.spread) ** 2)))

    def axis_scores(self, j: int, rotation: np.ndarray) -> np.ndarray:
        """Scores of shape j's three axes in `rotation` as up: its up, then its x and y
        (each turned to z by a quarter turn)."""
        return np.array([self.score(j, rotation), self.score(j, TILTS[2] @ rotation),
                         self.score(j, TILTS[4] @ rotation)])

    def best_up(self, j: int, rotation: np.ndarray, directions: int) -> tuple[np.ndarray, float]:
        """(tilt, score): the turn T, smallest for its direction, that stands shape j
        (turned by `rotation`) on the direction within `MAX_TILT` of its up scoring best
        as up, and that score: a Fibonacci grid of `directions` on that cap, then a
        Nelder-Mead refinement (to about 1°) of the best direction's two angles. Larger
        turns are changes of axis (`axis_scores`)."""
        cap = np.radians(MAX_TILT)

        def pose(angles: np.ndarray) -> np.ndarray:
            polar, azimuth = min(abs(float(angles[0])), cap), float(angles[1])
            return tilt_to_z(np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth),
                                       np.cos(polar)]))

        k = np.arange(directions) + 0.5
        grid = np.stack([np.arccos(1.0 - k / directions * (1.0 - np.cos(cap))), np.pi * (1.0 + 5.0 ** 0.5) * k],
                        axis=1)
        scores = [self.score(j, pose(angles) @ rotation) for angles in grid]
        start = grid[int(np.argmin(scores))]
        result = minimize(lambda a: self.score(j, pose(a) @ rotation), start, method="Nelder-Mead",
                          options={"xatol": 0.02, "fatol": 1e-3, "maxiter": 40})
        if result.fun < min(scores):
            return pose(result.x), float(result.fun)
        return pose(start), float(min(scores))

    def allows_tilt(self, j: int, rotation: np.ndarray, start: np.ndarray) -> bool:
        """Whether turning shape j from `start` to `rotation` may change its up direction:
        always when the up stays (to within 60°) or no profile was fitted, else only if
        the new up scores no worse than the old (a bowl among jugs is not laid on its
        side because the jugs fit it better that way)."""
        if not self.fitted or (rotation @ start.T)[2, 2] > 0.5 or (rotation @ start.T)[2, 2] < -0.5:
            return True
        return self.score(j, rotation) <= self.score(j, start)


def tilt_to_z(direction: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the unit `direction` to +z (Rodrigues; a half turn
    about x for −z)."""
    direction = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    axis = np.cross(direction, [0.0, 0.0, 1.0])
    sine, cosine = np.linalg.norm(axis), direction[2]
    if sine < 1e-12:
        return np.eye(3) if cosine > 0 else np.diag([1.0, -1.0, -1.0])
    return Rotation.from_rotvec(axis / sine * np.arctan2(sine, cosine)).as_matrix()
