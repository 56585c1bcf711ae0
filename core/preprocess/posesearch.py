"""How well shapes of a collection fit each other in given poses, and the rotation of one
shape that fits given others best (the measurements behind `consensus`).

Every shape is represented by surface samples in its base pose (the input frame turned by
the up rotation), centred at the exact surface centroid and scaled to unit total
variance, so the cost of a pose is free of position and size. The cost of shape j in
rotation R against reference shapes i in rotations R_i is the mean symmetric Chamfer
distance (`geometry.chamfer`) over the references:

    f_j(R) = mean_i C(R P_j, R_i P_i) = mean_i C(R_iᵀ R P_j, P_i),

so both KD-trees are built once per shape. The rotation search (`best_rotation`) tries the
24 axis rotations, then every turn about z on a grid for the most promising up
directions, then refines the best turn by a bounded scalar search; an exact axis rotation
is kept when it is within `snap` of the refined cost (a file written on another axis is
turned by exactly 90°, not 89.6°).

Nearest shapes are found by a rotation-invariant descriptor (quantiles of the distance of
the samples to the centroid and the square roots of the sorted covariance eigenvalues),
so a shape in a wrong pose still finds the shapes it resembles.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree

from ..geometry.chamfer import chamfer_distance
from ..mesh import Mesh
from .moments import surface_moments
from .rotations import AXIS_ROTATIONS, TILTS, yaw_rotation

__all__ = ["PoseSearch", "Fit"]

_DESCRIPTOR_QUANTILES = np.linspace(0.05, 0.95, 10)


@dataclass(frozen=True)
class Fit:
    """A rotation of one shape and its cost against the references it was fitted to."""

    rotation: np.ndarray
    cost: float


class PoseSearch:
    """Surface samples of a collection in base pose, their trees and descriptors."""

    def __init__(self, samples: Sequence[np.ndarray], descriptors: np.ndarray):
        self.samples = [np.asarray(s, dtype=np.float64) for s in samples]
        self.trees = [cKDTree(s) for s in self.samples]
        self.descriptors = np.asarray(descriptors, dtype=np.float64)

    @classmethod
    def of(cls, meshes: Sequence[Mesh], base: Sequence[np.ndarray], points: int, seed: int) -> "PoseSearch":
        """`points` samples of every shape (generator seed + i) in its base rotation."""
        samples, descriptors = [], []
        for i, (mesh, rotation) in enumerate(zip(meshes, base)):
            _, mean, cov = surface_moments(mesh)
            size = np.sqrt(np.trace(cov))
            pts = mesh.sample_surface(points, np.random.default_rng(seed + i)).points
            samples.append((pts - mean) @ rotation.T / size)
            radii = np.linalg.norm(samples[-1], axis=1)
            spread = np.sqrt(np.clip(np.linalg.eigvalsh(cov), 0.0, None)) / size
            descriptors.append(np.concatenate([np.quantile(radii, _DESCRIPTOR_QUANTILES), spread]))
        return cls(samples, np.asarray(descriptors))

    def __len__(self) -> int:
        return len(self.samples)

    def nearest(self, j: int, pool: Sequence[int], count: int) -> list[int]:
        """The `count` shapes of `pool` (j excluded) most like shape j by descriptor."""
        pool = [int(i) for i in pool if i != j]
        distance = np.linalg.norm(self.descriptors[pool] - self.descriptors[j], axis=1)
        return [pool[k] for k in np.argsort(distance, kind="stable")[:count]]

    def cost(self, j: int, rotation: np.ndarray, references: Sequence[tuple[int, np.ndarray]]) -> float:
        """f_j(rotation): mean Chamfer distance of shape j turned by `rotation` to each
        reference shape i turned by its R_i (module docstring)."""
        return float(np.mean([
            chamfer_distance(self.samples[j], self.samples[i], r_i.T @ rotation, self.trees[j], self.trees[i])
            for i, r_i in references]))

    def best_rotation(self, j: int, references: Sequence[tuple[int, np.ndarray]], yaw_step: float,
                      tilts: int, refine: bool, snap: float) -> Fit:
        """The rotation of shape j that fits the references best: the 24 axis rotations,
        then turns about z every `yaw_step` degrees for the `tilts` best up directions,
        then (refine) a bounded search within one grid step of the best turn. An axis
        rotation within `snap` (relative) of the best cost is preferred."""
        axis_costs = np.array([self.cost(j, r, references) for r in AXIS_ROTATIONS])
        best_axis = int(np.argmin(axis_costs))
        fit = Fit(AXIS_ROTATIONS[best_axis], float(axis_costs[best_axis]))
        for d in np.argsort(axis_costs.reshape(6, 4).min(axis=1), kind="stable")[:tilts]:
            fit = min(fit, self._best_yaw(j, references, TILTS[d], yaw_step, refine), key=lambda f: f.cost)
        if axis_costs[best_axis] <= (1.0 + snap) * fit.cost:
            return Fit(AXIS_ROTATIONS[best_axis], float(axis_costs[best_axis]))
        return fit

    def _best_yaw(self, j: int, references: Sequence[tuple[int, np.ndarray]], tilt: np.ndarray,
                  yaw_step: float, refine: bool) -> Fit:
        """Best turn about z after `tilt`: a grid every yaw_step degrees, then (refine) a
        bounded scalar search (to 0.2°) within one step of the best grid angle."""
        def f(angle: float) -> float:
            return self.cost(j, yaw_rotation(angle) @ tilt, references)

        grid = np.arange(0.0, 360.0, yaw_step)
        values = np.array([f(a) for a in grid])
        angle, value = float(grid[np.argmin(values)]), float(values.min())
        if refine:
            result = minimize_scalar(f, bounds=(angle - yaw_step, angle + yaw_step), method="bounded",
                                     options={"xatol": 0.2})
            if result.fun < value:
                angle, value = float(result.x), float(result.fun)
        return Fit(yaw_rotation(angle) @ tilt, value)
