"""Consensus orientation of a collection (thesis §3.4; step 3 of `prepare_collection`):
a shape's pose changes only on evidence much stronger than sampling noise that the
collection disagrees with it.

Every shape starts in its base pose, its input pose with the given up axis turned to +z
(no yaw: when the inputs already agree, nobody is turned, rotation exactly identity).
Two stages decide, each by the same three steps (`_settle`):

A. Chamfer cost (`posesearch.PoseSearch`): a shape is turned when the best rotation (24
   axis rotations, any turn about z) fits its nearest shapes more than `margin` times
   better than its pose, f(I) / f(R) > margin, on average and for most of them one by
   one; a change of the up direction must also beat the best upright pose by
   `tilt_margin` (PSB Vase: bowls among jugs fit them 2-4× better on their side). Calibration (bench/orientation.py, 600
   samples, 3 neighbours): over upright procedural vases and barrels at many seeds the
   ratio of a consistent shape stays below 1.07 (1.14 for a single pair); a vase upside
   down or any shape on its side scores 1.6 to 10. The Chamfer cost hardly sees a spout
   or a knob (a vase turned 180° about z: ratio 1.00-1.05), hence stage B.
B. Signatures (`signature.Signatures`, exact odd surface moments): a shape is flipped
   when its top-bottom signature anti-correlates with its nearest shapes' (correlation
   < −`up_agreement`), and turned about z by the angle its facing signature differs by,
   when the facing is shared (coherence > `coherence`) and the angle exceeds
   `facing_angle` (`refine_angle` for a shape turned anyway). Calibration: consistent
   vases and barrels differ in facing from their nearest shapes by up to 16° (coarse
   vases, 20 seeds; coherence ≥ 0.95, top-bottom correlation ≥ 0.95); flipped ones score ≤ −0.95, and a 37° turn is measured as
   35-39°. The signatures decide only what the cost cannot see: a turn they ask for is
   made only if it raises the cost by at most `tolerance` (on PSB fish the top-bottom
   signature alone flipped upright fish).

The three steps of a stage:

1. Votes: every shape against each of its `neighbours` nearest shapes (smallest cost over
   the 24 axis rotations). The pair agrees when the stage would not turn one to match
   the other.
2. The collection's pose: shapes agreeing with more than half of their neighbours form
   groups (connected by agreeing pairs); the largest group is the majority, whose poses
   are the collection's (nobody in it is ever turned). Without any agreeing shape the
   medoid is the majority of one. In stage B only shapes stage A left
   alone can be in the majority (a turned shape has no input facing to keep).
3. Everyone else, closest to the majority first, is decided against its nearest shapes
   already settled and not turned (a turned shape's pose is a guess), then settled. `keep` shapes are never turned
   and are no reference unless they are in the majority.

Each pose change comes with its reason ("turned 180° about x: its 3 nearest shapes
(a, b, c) fit 2.4× better"). Known limit: a group of shapes sharing one wrong pose that
is as large as the majority, or that only has itself as nearest shapes, keeps that pose;
`pose_outliers` flags shapes whose final pose still disagrees with their nearest shapes
or fits them much worse than the collection's median.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .posesearch import PoseSearch
from .rotations import describe_rotation, yaw_rotation
from .signature import Signatures

__all__ = ["ConsensusSettings", "PoseDecision", "consensus_rotations", "pose_outliers"]


@dataclass(frozen=True)
class ConsensusSettings:
    """The constants of the consensus orientation (module docstring)."""

    #: surface samples per shape for the Chamfer costs
    points: int = 600
    #: nearest shapes a shape is compared with
    neighbours: int = 3
    #: cost ratio (base pose / best rotation) above which a pose is changed or flagged
    margin: float = 1.5
    #: cost ratio (best upright pose / best pose) above which the up direction is changed
    tilt_margin: float = 2.5
    #: grid step of the turn about z, degrees
    yaw_step: float = 15.0
    #: up directions whose turns about z are searched on the grid
    tilts: int = 2
    #: relative cost within which an exact axis rotation beats a refined turn
    snap: float = 0.03
    #: relative Chamfer cost increase a turn by the signatures may cost at most
    tolerance: float = 0.1
    #: signature coherence above which top/bottom and facing are compared (0..1)
    coherence: float = 0.5
    #: top-bottom signature correlation below minus this flips a shape (0..1)
    up_agreement: float = 0.9
    #: facing difference (degrees) above which a shape is turned about z
    facing_angle: float = 30.0
    #: the same for a shape turned anyway (the signature's facing refines the cost's turn)
    refine_angle: float = 5.0
    #: Legendre polynomials in height in the facing signature
    facing_order: int = 5
    #: a shape fitting its nearest shapes this many times worse than the median is flagged
    outlier_factor: float = 3.0


@dataclass(frozen=True)
class PoseDecision:
    """The rotation consensus applied to one shape (after its up rotation) and why."""

    rotation: np.ndarray
    reason: str = ""  # empty when the shape kept its base pose

    @property
    def changed(self) -> bool:
        return bool(self.reason)


def consensus_rotations(search: PoseSearch, signatures: Signatures, names: Sequence[str], keep: Sequence[bool],
                        settings: ConsensusSettings, report: Callable[[float, str], None]) -> list[PoseDecision]:
    """The pose decision of every shape (the steps of the module docstring): first by the
    Chamfer cost (up direction, large turns), then by the signatures (top and bottom,
    facing at any angle)."""
    n = len(search)
    k = min(settings.neighbours, n - 1)
    identity = np.eye(3)

    def by_cost_agree(j: int, i: int) -> bool:
        reference = [(i, identity)]
        _, fit = search.best_rotation(j, reference, settings.yaw_step, settings.tilts, False, 0.0)
        return search.cost(j, identity, reference) <= settings.margin * fit.cost

    def by_cost(j: int, references: list[tuple[int, np.ndarray]]) -> PoseDecision:
        upright, fit = search.best_rotation(j, references, settings.yaw_step, settings.tilts, True, settings.snap)
        if upright.cost <= settings.tilt_margin * fit.cost:  # a change of up needs its own evidence
            fit = upright
        ratio = search.cost(j, identity, references) / max(fit.cost, 1e-300)
        # most references must ask for the turn one by one (a bowl among jugs: the jugs
        # prefer it on its side, the other bowls upright)
        each = sum(search.cost(j, identity, [r]) > settings.margin * search.cost(j, fit.rotation, [r])
                   for r in references)
        if ratio <= settings.margin or 2 * each <= len(references):
            return PoseDecision(identity)
        return PoseDecision(fit.rotation, f"{describe_rotation(fit.rotation)}: its {len(references)} nearest "
                                          f"shapes ({_names(names, references)}) fit {ratio:.1f}× better")

    first = _settle(search, k, keep, [identity] * n, by_cost_agree, by_cost, report, 0.2, [True] * n)
    turned = [d.rotation for d in first]

    def by_signature_agree(j: int, i: int) -> bool:
        return not by_signature(j, [(i, turned[i])], turned[j]).changed

    def by_signature(j: int, references: list[tuple[int, np.ndarray]], start=None) -> PoseDecision:
        start = turned[j] if start is None else start
        rotation, why = start, []
        cost = search.cost(j, start, references)

        def cost_allows(turned_rotation: np.ndarray) -> bool:
            # the signatures decide what the cost cannot see; they never overrule it
            return search.cost(j, turned_rotation, references) <= (1.0 + settings.tolerance) * cost

        if (signatures.up_agreement(j, rotation, references) < -settings.up_agreement
                and cost_allows(_HALF_TURN_X @ rotation)):
            rotation = _HALF_TURN_X @ rotation
            why.append("its top and bottom")
        turning = bool(why) or first[j].changed
        angle, coherence = signatures.facing_turn(j, rotation, references)
        if (coherence > settings.coherence and abs(angle) > (settings.refine_angle if turning else settings.facing_angle)
                and cost_allows(yaw_rotation(angle) @ rotation)):
            rotation = yaw_rotation(angle) @ rotation
            why.append("its facing")
        if not why:
            return PoseDecision(start)
        return PoseDecision(rotation, f"{describe_rotation(rotation @ start.T)}: {' and '.join(why)} like its "
                                      f"{len(references)} nearest shapes ({_names(names, references)})")

    # a shape the cost turned has no input facing to keep: it never joins the majority
    second = _settle(search, k, keep, turned, by_signature_agree, by_signature, report, 0.5,
                     [not d.changed for d in first])
    return [_combined(a, b) for a, b in zip(first, second)]


_HALF_TURN_X = np.diag([1.0, -1.0, -1.0])


def _names(names: Sequence[str], references: Sequence[tuple[int, np.ndarray]]) -> str:
    return ", ".join(names[i] for i, _ in references)


def _combined(first: PoseDecision, second: PoseDecision) -> PoseDecision:
    """One decision for both stages: the second's rotation (it starts from the first's)."""
    reasons = "; then ".join(r for r in (first.reason, second.reason) if r)
    if first.reason and second.reason:
        reasons = f"{describe_rotation(second.rotation)} in all ({reasons})"
    return PoseDecision(second.rotation if second.reason else first.rotation, reasons)


def _settle(search: PoseSearch, k: int, keep: Sequence[bool], start: Sequence[np.ndarray],
            agree: Callable[[int, int], bool], decide: Callable[[int, list], PoseDecision],
            report: Callable[[float, str], None], progress: float, eligible: Sequence[bool]) -> list[PoseDecision]:
    """Steps 1–3 with one test: votes of every shape with its k nearest shapes (`agree`),
    the majority group (of `eligible` shapes) keeps its poses, everyone else is decided
    (`decide`) against its k nearest settled shapes, closest to the settled ones first;
    `keep` shapes never move."""
    n = len(search)
    votes: dict[tuple[int, int], bool] = {}
    for j in range(n):
        for i in search.nearest(j, range(n), k):
            pair = (min(i, j), max(i, j))
            if pair not in votes:
                votes[pair] = eligible[pair[0]] and eligible[pair[1]] and agree(*pair)
        report(progress + 0.15 * (j + 1) / n, f"comparing {j + 1} of {n}")
    decisions = {j: PoseDecision(start[j]) for j in _majority(search, votes, k, eligible)}
    references_pool = list(decisions)  # shapes whose pose is trusted: kept ones only from the majority
    decisions.update({j: PoseDecision(start[j]) for j in range(n) if keep[j] and j not in decisions})
    while len(decisions) < n:
        j = min((r for r in range(n) if r not in decisions),
                key=lambda r: search.distance[r, references_pool].min())
        references = [(i, decisions[i].rotation) for i in search.nearest(j, references_pool, k)]
        decisions[j] = decide(j, references)
        if not decisions[j].changed:  # a turned shape's pose is a guess: no reference
            references_pool.append(j)
        report(progress + 0.15 + 0.15 * len(decisions) / n, f"orienting {len(decisions)} of {n}")
    return [decisions[j] for j in range(n)]


def _majority(search: PoseSearch, agree: dict[tuple[int, int], bool], k: int,
              eligible: Sequence[bool]) -> list[int]:
    """Step 2: the largest group of shapes that agree with most of their nearest shapes,
    connected by agreeing pairs (when no shape agrees, the medoid of the
    eligible shapes, or of all when none is, alone)."""
    n = len(search)
    votes = np.array([np.mean([agree[(min(i, j), max(i, j))] for i in search.nearest(j, range(n), k)])
                      for j in range(n)])
    members = np.flatnonzero(votes > 0.5)
    if len(members) == 0:
        pool = np.flatnonzero(eligible) if any(eligible) else np.arange(n)
        return [int(pool[np.argmin(search.distance[pool].sum(axis=1))])]
    edges = np.array([pair for pair, ok in agree.items() if ok and votes[pair[0]] > 0.5 and votes[pair[1]] > 0.5],
                     dtype=int).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    biggest = int(np.argmax(np.bincount(label[members])))
    return [int(j) for j in members if label[j] == biggest]


def pose_outliers(search: PoseSearch, signatures: Signatures, rotations: Sequence[np.ndarray],
                  keep: Sequence[bool], settings: ConsensusSettings) -> list[str]:
    """Why each shape's final pose looks wrong ('' when it does not), against its nearest
    shapes in their final poses (rotations relative to the base pose): a rotation would
    fit them more than `margin` times better, its top and bottom or its facing disagree
    with theirs (signatures, the thresholds of the consensus), or it fits them over
    `outlier_factor` times worse than the collection's median shape does."""
    n = len(search)
    k = min(settings.neighbours, n - 1)
    trusted = [i for i in range(n) if not keep[i]] if sum(not x for x in keep) > k else list(range(n))
    references = [[(i, rotations[i]) for i in search.nearest(j, trusted, k)] for j in range(n)]
    costs = np.array([search.cost(j, rotations[j], references[j]) for j in range(n)])
    median = float(np.median(costs))
    kept = [" (its pose is kept by request)" if k_ else "" for k_ in keep]
    reasons = []
    for j in range(n):
        upright, fit = search.best_rotation(j, references[j], settings.yaw_step, settings.tilts, False,
                                            settings.snap)
        if upright.cost <= settings.tilt_margin * fit.cost:
            fit = upright
        ratio = costs[j] / max(fit.cost, 1e-300)
        angle, coherence = signatures.facing_turn(j, rotations[j], references[j])
        if ratio > settings.margin:
            relative = fit.rotation @ rotations[j].T
            pose = "upside down" if relative[2, 2] < -0.5 else "on its side" if relative[2, 2] < 0.5 else "turned"
            reasons.append(f"{pose} relative to its {k} nearest shapes: {describe_rotation(relative)} it would "
                           f"fit them {ratio:.1f}× better{kept[j]}")
        elif (signatures.up_agreement(j, rotations[j], references[j]) < -settings.up_agreement
              and search.cost(j, _HALF_TURN_X @ rotations[j], references[j]) <= (1.0 + settings.tolerance) * costs[j]):
            reasons.append(f"upside down relative to its {k} nearest shapes (its top and bottom "
                           f"match their bottom and top){kept[j]}")
        elif (coherence > settings.coherence and abs(angle) > settings.facing_angle
              and search.cost(j, yaw_rotation(angle) @ rotations[j], references[j])
              <= (1.0 + settings.tolerance) * costs[j]):
            reasons.append(f"faces {abs(angle):.0f}° away from its {k} nearest shapes{kept[j]}")
        elif costs[j] > settings.outlier_factor * median:
            reasons.append(f"fits its {k} nearest shapes {costs[j] / median:.1f}× worse than the collection's "
                           "median shape does (an unusual shape, or a pose no turn fixes)")
        else:
            reasons.append("")
    return reasons
