"""Consensus orientation of a collection (thesis §3.4; step 3 of `prepare_collection`).

Every shape chooses one of its 24 candidate poses (`rotations.candidate_poses`) so that
the collection agrees, in named steps (`consensus_rotations`):

1. Candidate poses and surface samples of every shape; costs are symmetric Chamfer
   distances (`geometry.chamfer`) between samples centred at the surface centroid and
   scaled to unit total variance (`PoseCosts`).
2. A reference: the medoid of up to `medoid_candidates` shapes under the
   rotation-minimised Chamfer distance (`choose_reference`).
3. Every shape takes the candidate closest to the reference in its chosen pose, keeping
   its own pose when that is within `margin` (`prefer_own_pose`). Majority rule: the input
   orientation most shapes share wins. If the most common choice (up direction first, then
   the quarter turn among those) is not candidate 0, the reference was the odd one out
   (e.g. written upside down); it is replaced by the shape of that majority group closest
   to it, in its own PCA pose, and the matching is repeated, at most `max_rounds` times
   (`match_reference`).
4. Neighbours: a varied class (bowls and tall jugs in one "Vase" folder) fools a single
   reference: a bowl on its side resembles a jug more than an upright bowl does. So the
   pose of step 3 is only a proposal: starting from everyone's own pose, each shape takes
   its proposed pose when that lowers its cost to its `neighbours` nearest panel shapes
   (all shapes up to `panel`, in their current poses), a changed pose paying
   1 + `neighbour_margin`; sweeps repeat until nothing moves, at most `max_sweeps`
   (`agree_with_neighbours`). A bowl then stays with the upright bowls. Known limit: a
   group of `neighbours` or more shapes that share one wrong pose keeps it (they are each
   other's neighbours), e.g. two PSB teapots written z-up among y-up vases, two of four
   lying PSB dolphins.
5. Facing: each shape takes the half turn about z its nearest panel shapes prefer by more
   than `margin`. Below that (a spout moves the cost by well under 1 %, less than
   sampling noise) the half turn is decided by its odd-part signature (exact surface
   moments ∫x P_b(z), ∫y P_b(z)) against the rest of the collection (`choose_facing`,
   `agree_on_facing`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.chamfer import chamfer_distance
from ..mesh import Mesh
from .moments import surface_moments
from .rotations import candidate_poses, half_turn

__all__ = ["ConsensusSettings", "PoseCosts", "consensus_rotations"]


@dataclass(frozen=True)
class ConsensusSettings:
    """The constants of the consensus orientation (steps in the module docstring)."""

    #: surface samples per shape for the Chamfer comparison
    points: int = 1500
    #: shapes considered for the reference (medoid), evenly spaced over the input order
    medoid_candidates: int = 12
    #: rounds of "match everyone to the reference, let the majority pick a new reference"
    max_rounds: int = 3
    #: relative Chamfer margin a candidate must beat the shape's own pose by, and a half
    #: turn must beat the current facing by
    margin: float = 0.05
    #: nearest panel shapes a shape is compared with in the neighbour and facing steps
    neighbours: int = 2
    #: up to this many shapes every shape is in the panel, else the medoid candidates
    panel: int = 40
    #: relative penalty a changed pose pays in the neighbour step
    neighbour_margin: float = 0.15
    #: sweeps of the neighbour step at most
    max_sweeps: int = 5
    #: Legendre polynomials in height in the facing signature
    facing_order: int = 5
    #: sweeps of the facing-signature agreement at most
    facing_sweeps: int = 10


class PoseCosts:
    """Symmetric Chamfer costs between shapes in candidate poses (step 1).

    samples[i]: surface points of shape i in its input frame, centred at the surface
    centroid, unit total variance; poses[i]: its (24, 3, 3) candidate poses."""

    def __init__(self, samples: Sequence[np.ndarray], poses: Sequence[np.ndarray]):
        self.samples = list(samples)
        self.poses = list(poses)
        self.trees = [cKDTree(s) for s in self.samples]

    @classmethod
    def of(cls, meshes: Sequence[Mesh], up: np.ndarray, points: int, seed: int) -> "PoseCosts":
        """Candidate poses and `points` normalised surface samples (seed + i) of every shape."""
        samples = []
        for i, mesh in enumerate(meshes):
            _, mean, cov = surface_moments(mesh)
            pts = mesh.sample_surface(points, np.random.default_rng(seed + i)).points
            samples.append((pts - mean) / np.sqrt(np.trace(cov)))
        return cls(samples, [candidate_poses(m, up) for m in meshes])

    def __len__(self) -> int:
        return len(self.samples)

    def candidates(self, j: int, i: int, pose_i: np.ndarray) -> np.ndarray:
        """Cost of each candidate pose of shape j against shape i in pose_i."""
        reference = self.samples[i] @ pose_i.T
        reference_tree = cKDTree(reference)
        return np.array([chamfer_distance(self.samples[j], reference, pose, self.trees[j], reference_tree)
                         for pose in self.poses[j]])

    def pair(self, j: int, pose_j: np.ndarray, i: int, pose_i: np.ndarray) -> float:
        """Cost of shape j in pose_j against shape i in pose_i."""
        return chamfer_distance(self.samples[j], self.samples[i] @ pose_i.T, pose_j, tree_a=self.trees[j])

    def near(self, j: int, pose_j: np.ndarray, state: np.ndarray, panel: Sequence[int], neighbours: int) -> float:
        """Mean cost of shape j in pose_j to its `neighbours` cheapest panel shapes, each in
        its candidate state[i]."""
        costs = sorted(self.pair(j, pose_j, i, self.poses[i][state[i]]) for i in panel if i != j)
        return float(np.mean(costs[:neighbours]))


def consensus_rotations(meshes: Sequence[Mesh], pca_rotations: Sequence[np.ndarray], seed: int,
                        report: Callable[[float, str], None], up: np.ndarray,
                        settings: ConsensusSettings = ConsensusSettings()) -> tuple[list[np.ndarray], list[bool]]:
    """Orient every shape like the collection (the steps of the module docstring).

    Returns each shape's rotation (its PCA rotation when it keeps candidate 0) and whether
    it changed."""
    n = len(meshes)
    costs = PoseCosts.of(meshes, up, settings.points, seed)
    candidates = medoid_candidates(n, settings.medoid_candidates)
    reference = choose_reference(costs, candidates)
    report(0.4, f"reference shape {meshes[reference].name}")
    proposal = match_reference(costs, reference, settings, report, [m.name for m in meshes])
    panel = list(range(n)) if n <= settings.panel else [int(i) for i in candidates]
    choice = agree_with_neighbours(costs, proposal, panel, settings)
    facing, ambiguous = choose_facing(costs, choice, panel, settings)
    choice = agree_on_facing(facing, meshes, costs.poses, ambiguous, settings)
    rotations = [pca_rotations[j] if choice[j] == 0 else costs.poses[j][choice[j]] for j in range(n)]
    return rotations, [bool(c != 0) for c in choice]


def medoid_candidates(n: int, count: int) -> np.ndarray:
    """Up to `count` shape indices evenly spaced over range(n)."""
    return np.unique(np.linspace(0, n - 1, min(n, count)).round().astype(int))


def choose_reference(costs: PoseCosts, candidates: np.ndarray) -> int:
    """Step 2: the candidate with the smallest summed cost to the others, each other shape
    in its best candidate pose against this one in its PCA pose."""
    dist = np.zeros((len(candidates), len(candidates)))
    for a in range(len(candidates)):
        for b in range(a + 1, len(candidates)):
            dist[a, b] = dist[b, a] = costs.candidates(candidates[b], candidates[a], costs.poses[candidates[a]][0]).min()
    return int(candidates[int(np.argmin(dist.sum(axis=1)))])


def match_reference(costs: PoseCosts, reference: int, settings: ConsensusSettings,
                    report: Callable[[float, str], None], names: Sequence[str]) -> np.ndarray:
    """Step 3: every shape's candidate closest to the reference, with the majority rule
    replacing a reference that was the odd one out. Returns the proposed candidates."""
    n = len(costs)
    choice = np.zeros(n, dtype=int)
    cost_to_ref = np.zeros(n)
    for round_ in range(settings.max_rounds):
        for j in range(n):
            if j == reference:
                choice[j], cost_to_ref[j] = 0, 0.0
                continue
            c = costs.candidates(j, reference, costs.poses[reference][0])
            choice[j] = prefer_own_pose(c, settings.margin)
            cost_to_ref[j] = c[choice[j]]
            report(0.4 + 0.4 * (round_ * n + j + 1) / (settings.max_rounds * n), f"orienting {names[j]}")
        tilt = choice // 4
        top_tilt = _mode(tilt)
        turns = choice[tilt == top_tilt] % 4
        top = 4 * top_tilt + _mode(turns)
        if top == 0:
            break
        group = np.flatnonzero(choice == top)
        reference = int(group[np.argmin(cost_to_ref[group])])
        report(0.4, f"reference shape {names[reference]} (majority orientation)")
    return choice


def agree_with_neighbours(costs: PoseCosts, proposal: np.ndarray, panel: Sequence[int],
                          settings: ConsensusSettings) -> np.ndarray:
    """Step 4: starting from everyone's own pose, a shape switches between its own and its
    proposed pose when that lowers its cost to its nearest panel shapes (a changed pose
    paying 1 + neighbour_margin)."""
    choice = np.zeros(len(costs), dtype=int)
    for _ in range(settings.max_sweeps):
        moved = False
        for j in np.flatnonzero(proposal != 0):
            other = proposal[j] if choice[j] == 0 else 0
            current = costs.near(j, costs.poses[j][choice[j]], choice, panel, settings.neighbours)
            alternative = costs.near(j, costs.poses[j][other], choice, panel, settings.neighbours)
            if (alternative * (1.0 + settings.neighbour_margin * (other != 0))
                    < current * (1.0 + settings.neighbour_margin * (choice[j] != 0))):
                choice[j] = other
                moved = True
        if not moved:
            break
    return choice


def choose_facing(costs: PoseCosts, choice: np.ndarray, panel: Sequence[int],
                  settings: ConsensusSettings) -> tuple[np.ndarray, np.ndarray]:
    """Step 5, by the neighbours: each shape's candidate after the half turn about z its
    nearest panel shapes prefer by more than `margin`, and which shapes they leave
    undecided (neither facing wins by the margin)."""
    n = len(costs)
    facing = choice.copy()
    ambiguous = np.zeros(n, dtype=bool)
    for j in range(n):
        keep = costs.near(j, costs.poses[j][choice[j]], choice, panel, settings.neighbours)
        turn = costs.near(j, costs.poses[j][half_turn(choice[j])], choice, panel, settings.neighbours)
        if turn * (1.0 + settings.margin) < keep:
            facing[j] = half_turn(choice[j])
        elif turn <= keep * (1.0 + settings.margin):
            ambiguous[j] = True
    return facing, ambiguous


def _triangle_quadrature() -> tuple[np.ndarray, np.ndarray]:
    """Collapsed 4×4 Gauss rule on the unit triangle: (xi, eta) points and weights summing
    to 1 (fraction of the triangle's area); exact for polynomials up to degree 6."""
    g, w = np.polynomial.legendre.leggauss(4)
    g, w = (g + 1.0) / 2.0, w / 2.0
    u, v = np.meshgrid(g, g, indexing="ij")
    weights = 2.0 * (np.outer(w, w) * (1.0 - u)).ravel()
    return np.stack([u.ravel(), (v * (1.0 - u)).ravel()], axis=1), weights


_QUAD_POINTS, _QUAD_WEIGHTS = _triangle_quadrature()


def facing_signature(mesh: Mesh, rotation: np.ndarray, order: int) -> np.ndarray:
    """Odd part of a posed shape under a half turn about z, exact (no sampling noise):
    ∫ x P_b(ẑ) dA and ∫ y P_b(ẑ) dA over the surface for Legendre P_0..P_{order-1}
    in the height ẑ ∈ [−1, 1], centred at the surface centroid, unit total variance.
    A half turn about z negates it; a shape symmetric under that turn has zero."""
    area, mean, cov = surface_moments(mesh)
    tri = (mesh.triangles - mean) @ rotation.T / np.sqrt(np.trace(cov))
    pts = (tri[:, None, 0]
           + _QUAD_POINTS[None, :, :1] * (tri[:, None, 1] - tri[:, None, 0])
           + _QUAD_POINTS[None, :, 1:] * (tri[:, None, 2] - tri[:, None, 0])).reshape(-1, 3)
    weights = (mesh.face_areas()[:, None] * _QUAD_WEIGHTS[None, :]).ravel() / area
    lo, hi = tri[..., 2].min(), tri[..., 2].max()
    height = 2.0 * (pts[:, 2] - lo) / max(hi - lo, 1e-12) - 1.0
    basis = np.polynomial.legendre.legvander(height, order - 1)  # (n, order)
    return np.concatenate([(weights * pts[:, 0]) @ basis, (weights * pts[:, 1]) @ basis])


def agree_on_facing(choice: np.ndarray, meshes: Sequence[Mesh], poses: Sequence[np.ndarray], movable: np.ndarray,
                    settings: ConsensusSettings) -> np.ndarray:
    """Step 5, by the signature: flip the `movable` shapes by a half turn about z while that
    makes their facing signature agree better with the sum of everyone else's."""
    choice = choice.copy()
    n = len(choice)
    signature = np.stack([facing_signature(meshes[j], poses[j][choice[j]], settings.facing_order)
                          for j in range(n)])
    for _ in range(settings.facing_sweeps):
        flipped = False
        for j in np.flatnonzero(movable):
            others = signature.sum(axis=0) - signature[j]
            if float(signature[j] @ others) < 0.0:
                choice[j] = half_turn(choice[j])
                signature[j] = -signature[j]
                flipped = True
        if not flipped:
            break
    return choice


def prefer_own_pose(cost: np.ndarray, margin: float) -> int:
    """Index of the chosen candidate: the cheapest, unless the shape's own pose (candidate
    0), or else the same up direction with no quarter turn, is within `margin` of it.
    Chamfer differences below that are sampling noise and shape variation (a vase's spout
    moves the cost by well under 1 %), where the sign rule is the better judge."""
    best = int(np.argmin(cost))
    limit = (1.0 + margin) * cost[best]
    if cost[0] <= limit:
        return 0
    same_up = 4 * (best // 4)
    return same_up if cost[same_up] <= limit else best


def _mode(values: np.ndarray) -> int:
    """Most common value; ties go to the smallest (candidate 0 = keep the input's pose)."""
    counts = np.bincount(values)
    return int(np.argmax(counts))
