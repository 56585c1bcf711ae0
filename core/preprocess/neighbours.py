"""Nearest shapes of a large collection without the Chamfer cost of every pair.

`PoseSearch`'s distance between two shapes is their smallest Chamfer cost over the 24 axis
rotations: 24 screened costs and 4 full ones per pair, so a collection of N shapes took
N²/2 of them (200 vases: 20 000 pairs, most of Prepare's 958 s). Above `EXACT_SHAPES`
shapes the pairs are proposed instead by a cheap pose-aware descriptor and only proposed
pairs get the exact cost:

* descriptor: the distance field of a shape's samples at a fixed cubic grid of probe
  points, d_P(q) = min(min_p ‖q − p‖, `FIELD_CUTOFF`), for the shape in each of the 24
  axis rotations (d_{RP}(q) = d_P(Rᵀq): the probes turned back, one KD-tree query). Two
  shapes whose surfaces are close have close distance fields (|d_A(q) − d_B(q)| is at
  most their Hausdorff distance), and unlike radii and spreads it sees the pose (a bowl
  on its side is not a bowl upright).
* estimate: e(j, i) = c · min_R mean_q (d_{RP_j}(q) − d_{P_i}(q))², the squared field
  difference of the best axis rotation, scaled by c, `ESTIMATE_MARGIN` times the
  smallest ratio of exact cost to field difference among the proposed pairs, so that it
  lies below the exact cost (on 120 mixed vases and barrels in random poses: every pair
  not computed, by 1.11x or more): for every pair, a few matrix products over the
  descriptors.
* candidates: each shape's `CANDIDATES` pairs of smallest estimate get the exact cost
  (120 shapes: 1234 of 7140 pairs, 4.1 s against 51 s for all of them).

`PoseSearch.distance` then holds the exact cost of the pairs computed and the estimate of
the others; `PoseSearch.nearest` considers the pairs already computed and the `REACH` · k
others of smallest estimate, computes the exact cost of every pair it would return that
has only an estimate, and ranks again, until its answer rests on exact costs only
(`complete_nearest`). Where the estimates lie below the exact costs, as they are scaled
to, and rank the nearest shapes among the first REACH · k, that answer is the one of the
all-pairs matrix: tests/core/test_large_collections.py checks it on a procedural
collection; 100 vases in random poses got the same pose decisions, reasons and flags as
with every pair (`bench/prepare_scale.py`: 2153 of 4950 pairs computed; consensus's
order of settling asks for the nearest settled shape of every waiting one through
`posesearch.NearestInPool`, which makes an estimate exact only for the row that would
come next). Up to `EXACT_SHAPES` shapes every pair is computed as before (the
orientation benchmark's and PSB's collections: same decisions).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..base.progress import Progress, no_progress
from .rotations import AXIS_ROTATIONS

__all__ = ["EXACT_SHAPES", "CANDIDATES", "CandidateDistances", "complete_nearest", "field_descriptors"]

#: collections up to this size compute the exact distance of every pair
EXACT_SHAPES = 64
#: pairs of smallest estimate per shape that get the exact distance up front
CANDIDATES = 8
#: probe points per axis of the descriptor's cubic grid, and its half-width (the samples
#: are centred and of unit total variance: an RMS radius of 1)
PROBE_STEPS, PROBE_RADIUS = 10, 1.5
#: the fields are cut off at this distance (far from both surfaces a probe tells little,
#: and without the cut-off it outweighs those near them)
FIELD_CUTOFF = 0.3
#: the estimate's scale: this quantile of the proposed pairs' ratios (exact / field
#: difference), times the margin (pairs beyond the candidates vary more)
ESTIMATE_QUANTILE, ESTIMATE_MARGIN = 0.0, 0.75
#: a query for the k nearest shapes considers, besides the pairs already computed, the
#: REACH · k of smallest estimate (bounded work per query: in a class whose shapes differ
#: hardly more than their sampling noise, the estimates of half the pool fall below the
#: nearest exact cost)
REACH = 4


def probe_grid(steps: int = PROBE_STEPS, radius: float = PROBE_RADIUS) -> np.ndarray:
    """(steps³, 3) points of a cubic grid centred at the origin (symmetric under the 24
    axis rotations)."""
    axis = np.linspace(-radius, radius, steps)
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def field_descriptors(trees: Sequence[cKDTree], probes: np.ndarray, cutoff: float = FIELD_CUTOFF,
                      rotations: np.ndarray = AXIS_ROTATIONS) -> np.ndarray:
    """(N, R, P) distance fields min(d_{R P_j}(q), cutoff) of every shape j (its samples'
    KD-tree) in every rotation R (the axis rotations; the first is the identity) at the
    probe points q: the distances of Rᵀq to the samples."""
    turned_back = np.stack([probes @ r for r in rotations])  # rows Rᵀq
    return np.stack([tree.query(turned_back.reshape(-1, 3), distance_upper_bound=cutoff)[0]
                     .clip(max=cutoff).reshape(len(rotations), -1) for tree in trees])


def field_differences(descriptors: np.ndarray) -> np.ndarray:
    """(N, N) min_R mean_q (d_{R P_j}(q) − d_{P_i}(q))², symmetrised (the smaller of the
    two directions), zero diagonal."""
    n, rotations, probes = descriptors.shape
    upright = descriptors[:, 0]  # AXIS_ROTATIONS[0] is the identity
    upright_norms = (upright ** 2).sum(axis=1)
    out = np.empty((n, n))
    for j in range(n):
        turned = descriptors[j]
        squares = (turned ** 2).sum(axis=1)[:, None] + upright_norms[None, :] - 2.0 * turned @ upright.T
        out[j] = np.maximum(squares.min(axis=0), 0.0) / probes
    out = np.minimum(out, out.T)
    np.fill_diagonal(out, 0.0)
    return out


class CandidateDistances:
    """The distance matrix of a large collection: exact for the pairs computed, the
    scaled estimate elsewhere (module docstring); `known` marks the exact entries.
    `progress` follows the exact costs of the proposed pairs; `rotations` are those the
    distance `exact` minimises over (the descriptors are compared over the same)."""

    def __init__(self, trees: Sequence[cKDTree], exact: Callable[[int, int], float],
                 candidates: int = CANDIDATES, quantile: float = ESTIMATE_QUANTILE,
                 margin: float = ESTIMATE_MARGIN, progress: Progress | None = None,
                 rotations: np.ndarray = AXIS_ROTATIONS):
        self.exact = exact
        n = len(trees)
        differences = field_differences(field_descriptors(trees, probe_grid(), rotations=rotations))
        self.known = np.eye(n, dtype=bool)
        self.distance = np.zeros((n, n))
        pairs = set()
        for j in range(n):
            order = np.argsort(differences[j], kind="stable")
            pairs.update((min(j, int(i)), max(j, int(i))) for i in order[order != j][:candidates])
        report = progress or no_progress
        for done, (j, i) in enumerate(sorted(pairs)):
            self.set(j, i, exact(j, i))
            if done % n == n - 1 or done == len(pairs) - 1:
                report((done + 1) / len(pairs), f"comparing {done + 1} of {len(pairs)} proposed pairs of shapes")
        rows, cols = np.nonzero(self.known & ~np.eye(n, dtype=bool))
        ratios = self.distance[rows, cols] / np.maximum(differences[rows, cols], 1e-300)
        self.scale = margin * float(np.quantile(ratios, quantile)) if len(ratios) else 1.0
        self.estimate = self.scale * differences
        self.distance = np.where(self.known, self.distance, self.estimate)

    def set(self, j: int, i: int, value: float) -> None:
        self.distance[i, j] = self.distance[j, i] = value
        self.known[i, j] = self.known[j, i] = True


def complete_nearest(candidates: CandidateDistances, j: int, pool: Sequence[int], count: int,
                     reach: int = REACH) -> list[int]:
    """The `count` shapes of `pool` (j excluded) nearest shape j by exact distance, among
    the pool's shapes whose distance to j is known and its `reach` · count others of
    smallest estimate (module docstring): pairs of those with only an estimate among the
    answer are computed, and they are ranked again."""
    pool = np.array([int(i) for i in pool if i != j], dtype=int)
    known = candidates.known[j, pool]
    if not known.all():
        unknown = np.flatnonzero(~known)
        nearest_unknown = unknown[np.argsort(candidates.estimate[j, pool[unknown]], kind="stable")[:reach * count]]
        pool = pool[np.sort(np.concatenate([np.flatnonzero(known), nearest_unknown]))]
    while True:
        chosen = pool[np.argsort(candidates.distance[j, pool], kind="stable")[:count]]
        unknown = chosen[~candidates.known[j, chosen]]
        if len(unknown) == 0:
            return [int(i) for i in chosen]
        for i in unknown:
            candidates.set(j, int(i), candidates.exact(min(j, int(i)), max(j, int(i))))
