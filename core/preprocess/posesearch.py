"""How well shapes of a collection fit each other in given poses, and the rotation of one
shape that fits given others best (the measurements behind `consensus`).

Every shape is represented by surface samples in its base pose (the input frame turned by
the up rotation), centred at the exact surface centroid and scaled to unit total
variance, so the cost of a pose is free of position and size. The cost of shape j in
rotation R against reference shapes i in rotations R_i is the mean symmetric Chamfer
distance (`geometry.chamfer`) over the references:

    f_j(R) = mean_i C(R P_j, R_i P_i) = mean_i C(R_iᵀ R P_j, P_i),

so both KD-trees are built once per shape, and every pair cost C(R P_j, P_i) is computed
once: it is remembered by (j, i, R) (the same pair in the same relative rotation recurs
between the votes, the decisions and the pose check: PSB Vase, 16 000 Chamfer distances
without it). The rotation search (`best_rotation`) tries the
24 axis rotations, then every turn about z on a grid for the most promising up
directions, then refines the best turn by a bounded scalar search; an exact axis rotation
is kept when it is within `snap` of the refined cost (a file written on another axis is
turned by exactly 90°, not 89.6°).

Nearest shapes are those with the smallest cost over the 24 axis rotations (screened on a
quarter of the samples, the 4 best at full cost: the same distances on PSB and the
procedural sets, a third of the time; above `neighbours.EXACT_SHAPES` shapes only for
the pairs a pose-aware descriptor proposes), so a shape in
a wrong pose still finds the shapes it resembles (a bowl finds bowls, not jugs: with a
rotation-invariant descriptor of radii and spreads, PSB bowls found jugs and were laid on
their sides to fit them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree

from ..geometry.chamfer import chamfer_distance, chamfer_distances
from ..meshes.mesh import Mesh
from ..base.progress import Progress, no_progress, sub_range
from .moments import surface_moments
from .neighbours import EXACT_SHAPES, CandidateDistances, complete_nearest
from .rotations import AXIS_ROTATIONS, TILTS, turn_rotations, yaw_rotation

__all__ = ["PoseSearch", "Fit", "NearestInPool"]

#: the distance matrix screens the 24 axis rotations of a pair on every SCREEN_FRACTION-th
#: share of the samples (they are independent draws, so the first ones are a uniform
#: subsample) and takes the full cost of the SCREEN_KEEP best only
SCREEN_FRACTION, SCREEN_KEEP = 4, 4

@dataclass(frozen=True)
class Fit:
    """A rotation of one shape and its cost against the references it was fitted to."""

    rotation: np.ndarray
    cost: float


class PoseSearch:
    """Surface samples of a collection in base pose, their trees and descriptors."""

    def __init__(self, samples: Sequence[np.ndarray], exact_shapes: int = EXACT_SHAPES,
                 progress: Progress | None = None):
        self.samples = [np.asarray(s, dtype=np.float64) for s in samples]
        self.trees = [cKDTree(s) for s in self.samples]
        self._pair_costs: dict[tuple[int, int, bytes], float] = {}
        self._coarse = [s[:max(len(s) // SCREEN_FRACTION, 1)] for s in self.samples]
        self._coarse_trees = [cKDTree(c) for c in self._coarse]
        self._exact_shapes = exact_shapes
        #: the rotations the distances are minimised over: the 24 axis rotations, or
        #: after `compare_turned` also the turns about up between them
        self.distance_rotations = AXIS_ROTATIONS
        self._compare(progress)

    def _compare(self, progress: Progress | None) -> None:
        """The rotation-minimised cost between every pair, min over `distance_rotations`
        (above `exact_shapes` shapes: of the pairs computed, an estimate elsewhere;
        module `neighbours`)."""
        n = len(self.samples)
        self.candidates: CandidateDistances | None = None
        if n > self._exact_shapes:
            self.candidates = CandidateDistances(self.trees, self.axis_distance, progress=progress,
                                                 rotations=self.distance_rotations)
            self.distance = self.candidates.distance
            return
        self.distance = np.zeros((n, n))
        report = progress or no_progress
        for j in range(n):
            for i in range(j + 1, n):
                self.distance[i, j] = self.distance[j, i] = self.axis_distance(j, i)
            report((j + 1) * (2 * n - j - 2) / max(n * (n - 1), 1), f"comparing shape {j + 1} of {n}")

    def compare_turned(self, yaw_step: float, progress: Progress | None = None) -> None:
        """Nearest shapes from now on are those alike at any turn about up (on a grid of
        `yaw_step` degrees, `rotations.turn_rotations`), not only at an axis rotation:
        for a collection whose inputs share no pose (every shape turned about up at
        random, PSB airplanes: at axis rotations a shape's nearest shapes are chance ones,
        and 2-4 of 20 fitted to chance shapes took a wrong turn)."""
        self.distance_rotations = turn_rotations(yaw_step)
        self._compare(progress)

    def axis_distance(self, j: int, i: int) -> float:
        """min over the rotations R of `distance_rotations` of C(R P_j, P_i): screened on
        the coarse samples, the SCREEN_KEEP best at full cost (module docstring)."""
        coarse, trees, rotations = self._coarse, self._coarse_trees, self.distance_rotations
        screened = np.argsort([chamfer_distance(coarse[j], coarse[i], r, trees[j], trees[i]) for r in rotations],
                              kind="stable")[:SCREEN_KEEP]
        return min(self.cost(j, rotations[r], [(i, np.eye(3))]) for r in screened)

    @classmethod
    def of(cls, meshes: Sequence[Mesh], base: Sequence[np.ndarray], points: int, seed: int,
           progress: Progress | None = None) -> "PoseSearch":
        """`points` samples of every shape (generator seed + i) in its base rotation;
        `progress` follows the sampling (its first tenth) and the comparison of the shapes."""
        samples = []
        report = progress or no_progress
        for i, (mesh, rotation) in enumerate(zip(meshes, base)):
            _, mean, cov = surface_moments(mesh)
            pts = mesh.sample_surface(points, np.random.default_rng(seed + i)).points
            samples.append((pts - mean) @ rotation.T / np.sqrt(np.trace(cov)))
            report(0.1 * (i + 1) / len(meshes), f"sampling shape {i + 1} of {len(meshes)}")
        return cls(samples, progress=sub_range(progress, 0.1, 1.0))

    def __len__(self) -> int:
        return len(self.samples)

    def nearest(self, j: int, pool: Sequence[int], count: int) -> list[int]:
        """The `count` shapes of `pool` (j excluded) most like shape j in any axis pose."""
        if self.candidates is not None:
            return complete_nearest(self.candidates, j, pool, count)
        pool = [int(i) for i in pool if i != j]
        return [pool[k] for k in np.argsort(self.distance[j, pool], kind="stable")[:count]]

    def is_exact(self, j: int, i: int) -> bool:
        """Whether `distance[j, i]` is the exact cost (always, up to `exact_shapes` shapes)."""
        return self.candidates is None or bool(self.candidates.known[j, i])

    def make_exact(self, j: int, i: int) -> None:
        """Replace the estimate `distance[j, i]` by the exact cost."""
        if not self.is_exact(j, i):
            self.candidates.set(j, i, self.axis_distance(min(j, i), max(j, i)))

    def cost(self, j: int, rotation: np.ndarray, references: Sequence[tuple[int, np.ndarray]]) -> float:
        """f_j(rotation): mean Chamfer distance of shape j turned by `rotation` to each
        reference shape i turned by its R_i (module docstring)."""
        return float(np.mean([self.pair_cost(j, i, r_i.T @ rotation) for i, r_i in references]))

    def pair_cost(self, j: int, i: int, relative: np.ndarray) -> float:
        """C(relative P_j, P_i), remembered (module docstring)."""
        key = (j, i, relative.tobytes())
        value = self._pair_costs.get(key)
        if value is None:
            value = self._pair_costs[key] = chamfer_distance(self.samples[j], self.samples[i], relative,
                                                             self.trees[j], self.trees[i])
        return value

    def coarse_pair_costs(self, j: int, i: int, relatives: np.ndarray) -> np.ndarray:
        """C(R P_j, P_i) for each R of `relatives` (k, 3, 3) on the coarse samples (a
        quarter of them): the collection-wide comparisons of `consensus` ask it of many
        pairs and turns at once."""
        return chamfer_distances(self._coarse[j], self._coarse[i], relatives, self._coarse_trees[j],
                                 self._coarse_trees[i])

    def best_rotation(self, j: int, references: Sequence[tuple[int, np.ndarray]], yaw_step: float,
                      tilts: int, refine: bool, snap: float, start: np.ndarray | None = None) -> tuple[Fit, Fit]:
        """The rotations of shape j that fit the references best, (upright, any): the 24
        axis rotations, then turns about z every `yaw_step` degrees for the up direction
        kept and the `tilts` best others, then (refine) a bounded search within one grid
        step of each best turn. An axis rotation within `snap` (relative) of a best cost
        is preferred to it. `start`: a rotation the candidates follow (its up is "kept";
        none: the base pose)."""
        axis_costs = np.array([self.cost(j, _after(r, start), references) for r in AXIS_ROTATIONS])
        by_tilt = axis_costs.reshape(6, 4)
        fits = {int(d): self.best_turn(j, references, int(d), yaw_step, refine, snap, start, by_tilt[d])
                for d in {0, *np.argsort(by_tilt.min(axis=1), kind="stable")[:tilts]}}
        return fits[0], min(fits.values(), key=lambda f: f.cost)

    def best_turn(self, j: int, references: Sequence[tuple[int, np.ndarray]], tilt: int, yaw_step: float,
                  refine: bool, snap: float, start: np.ndarray | None = None,
                  quarter_costs: np.ndarray | None = None) -> Fit:
        """The best rotation of shape j with up direction `tilt` (index into TILTS, after
        `start`): every turn about z on the grid, refined, or the axis rotation of that up
        within `snap` of it (`quarter_costs`: its four costs, when known)."""
        if quarter_costs is None:
            quarter_costs = [self.cost(j, _after(r, start), references) for r in AXIS_ROTATIONS[4 * tilt:4 * tilt + 4]]
        fit = self.best_yaw(j, references, _after(TILTS[tilt], start), yaw_step, refine)
        k = int(np.argmin(quarter_costs))
        if quarter_costs[k] <= (1.0 + snap) * fit.cost:
            fit = Fit(_after(AXIS_ROTATIONS[4 * tilt + k], start), float(quarter_costs[k]))
        return fit

    def best_yaw(self, j: int, references: Sequence[tuple[int, np.ndarray]], tilt: np.ndarray,
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


class NearestInPool:
    """The distance of every shape outside a growing pool to its nearest shape in the pool,
    kept as shapes join (consensus settles the shape closest to the settled ones next:
    asking `PoseSearch.nearest` of every unsettled shape after every join took N²
    queries over a pool of up to N, with an exact cost for every pair that a query's
    estimates put first). `closest` is the row minimum of the all-pairs matrix
    over the pool (ties: the lowest row, the earliest pool shape); an entry resting on an
    estimate is made exact only when its row would come next, and the row is ranked
    again, so the answer is the all-pairs one wherever the estimates lie below the exact
    costs, as `neighbours` scales them to be."""

    def __init__(self, search: PoseSearch, pool: Sequence[int], outside: Sequence[int]):
        self.search = search
        n = len(search)
        self.pool = [int(i) for i in pool]
        self.outside = np.zeros(n, dtype=bool)
        self.outside[[int(r) for r in outside]] = True
        self.best = np.full(n, np.inf)
        self.nearest = np.full(n, -1)
        rows = np.flatnonzero(self.outside)
        if len(rows) and self.pool:
            block = search.distance[np.ix_(rows, self.pool)]
            first = np.argmin(block, axis=1)
            self.best[rows] = block[np.arange(len(rows)), first]
            self.nearest[rows] = np.asarray(self.pool)[first]

    def join(self, j: int) -> None:
        """Shape j leaves the outside (if it was there) and joins the pool."""
        self.leave(j)
        self.pool.append(int(j))
        column = self.search.distance[:, j]
        nearer = self.outside & (column < self.best)
        self.best[nearer] = column[nearer]
        self.nearest[nearer] = j

    def leave(self, j: int) -> None:
        """Shape j no longer waits outside (it was settled without joining the pool)."""
        self.outside[j] = False
        self.best[j] = np.inf

    def closest(self) -> int:
        """The outside shape whose nearest pool shape is closest, by exact cost."""
        while True:
            r = int(np.argmin(np.where(self.outside, self.best, np.inf)))
            i = int(self.nearest[r])
            if self.search.is_exact(r, i):
                return r
            self.search.make_exact(r, i)
            row = self.search.distance[r, self.pool]
            first = int(np.argmin(row))
            self.best[r], self.nearest[r] = row[first], self.pool[first]


def _after(rotation: np.ndarray, start: np.ndarray | None) -> np.ndarray:
    """`rotation` applied after `start` (none: the base pose)."""
    return rotation if start is None else rotation @ start
