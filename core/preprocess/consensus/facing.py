"""Steps 3 and 4 of the consensus orientation, facing and outliers.

3. Facing (`facings`): turns about up only, by the Chamfer cost (`_CostFacing`: where the
inputs share a facing, a turn of more than `facing.angle` that at least
`costs.agreement` of its `costs.references` settled shapes fit `costs.margin` times
better; half of them: a flag "may face another way") and by the facing signature
(`_SignatureFacing`, `signature.Signatures`, exact odd moments: a shared facing
differing by more than `facing.angle`), with `_settle`'s majority: the poses most
shapes share are the collection's and are never changed. Inputs turned about up at
random share no facing (at most `facing.shared_facing` of the votes agree): one
shape's facing is then the collection's, and the others are turned to it (beyond the
thesis).

4. Last (`outlier_flags`), a shape fitting its nearest shapes `outlier_factor` times
worse than the median shape does is flagged (an unusual shape, or a pose no turn
fixes).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..posesearch import NearestInPool, PoseSearch
from ..rotations import describe_rotation, rotation_angle, yaw_rotation
from .state import ConsensusState, PoseDecision, combined, reference_names, step_progress


def facings(state: ConsensusState) -> None:
    """Step 3: turns about up only (module docstring), into `state.faced`: first by the
    Chamfer cost (`_CostFacing`), then by the facing signature (`_SignatureFacing`), each
    settled by `_settle`. With `may_turn` False nobody is turned here."""
    if not state.may_turn:
        state.faced = [PoseDecision(d.rotation) for d in state.ends]
        return
    # a shape that may lie on its side is left as given (a turn about its up means
    # nothing); one that may be upside down still lines its facing up (rule b)
    frozen = [f or bool(d.flag) for f, d in zip(state.frozen, state.stood)]
    settled = [not d.flag for d in state.ends]
    first = _settle(state, _CostFacing(state, [d.rotation for d in state.ends], settled), frozen)
    second = _settle(state, _SignatureFacing(state, [d.rotation for d in first],
                                             [s and not d.changed for s, d in zip(settled, first)]), frozen)
    state.faced = [combined(a, b) for a, b in zip(first, second)]


class _CostFacing:
    """Step 3's test by the Chamfer cost, for `_settle`: shape j agrees with shape i when
    it fits i in its pose (`start`) within `costs.margin` of its best turn about up; a
    shape is decided against the collection's settled shapes (`eligible`), or, when the
    inputs share no pose, against its nearest shapes by `facing.unshared_margin`."""

    what = "pose"
    progress, span = 0.5, 0.18  # the share of Prepare's progress it reports in

    def __init__(self, state: ConsensusState, start: Sequence[np.ndarray], eligible: Sequence[bool]):
        self.state, self.start, self.eligible = state, start, eligible
        self.shared_votes = state.settings.facing.shared_pose

    def _upright_fit(self, j: int, references: list[tuple[int, np.ndarray]]):
        facing = self.state.settings.facing
        upright, _ = self.state.search.best_rotation(j, references, facing.yaw_step, 0, True, facing.snap,
                                                     self.start[j])
        return upright

    def agree(self, j: int, i: int) -> bool:
        reference = [(i, self.start[i])]
        margin = self.state.settings.costs.margin
        return self.state.search.cost(j, self.start[j], reference) <= margin * self._upright_fit(j, reference).cost

    def share_none(self) -> bool:
        """The inputs share no pose: from now on the search compares shapes at any turn
        about up, and a shape turned is a reference like one kept (True)."""
        self.state.search.compare_turned(self.state.settings.facing.yaw_step)
        return True

    def decide(self, j: int, references: list[tuple[int, np.ndarray]], why: str = "") -> PoseDecision:
        """Shape j turned about up, flagged or kept; `why`: the inputs share no pose."""
        state, search, start = self.state, self.state.search, self.start
        settings = state.settings
        least = settings.facing.unshared_margin if why else settings.costs.margin
        if not why:  # the inputs share a facing: a turn needs the collection, not three nearest shapes
            references = [(i, start[i]) for i in search.nearest(j, [i for i in range(state.n) if self.eligible[i]],
                                                                 settings.costs.references)]
        fit = self._upright_fit(j, references)
        ratio = search.cost(j, start[j], references) / max(fit.cost, 1e-300)
        each = sum(search.cost(j, start[j], [r]) > least * search.cost(j, fit.rotation, [r]) for r in references)
        turn = fit.rotation @ start[j].T
        if why:
            if ratio <= least:
                return PoseDecision(start[j])
            return PoseDecision(fit.rotation, f"{describe_rotation(turn)}: its {len(references)} nearest shapes "
                                              f"({reference_names(state.names, references)}) fit {ratio:.1f}× better ({why})")
        share = f"{each} of {len(references)} shapes fit it {ratio:.1f}× better turned about up"
        if ratio <= least or 2 * each <= len(references) or rotation_angle(turn) <= settings.facing.angle:
            return PoseDecision(start[j])
        if each >= settings.costs.agreement * len(references):
            return PoseDecision(fit.rotation, f"{describe_rotation(turn)}: {share}, the collection facing one way")
        return PoseDecision(start[j], flag=f"may face another way: {share}", flag_rotation=fit.rotation)


class _SignatureFacing:
    """Step 3's test by the facing signature, for `_settle`: shape j agrees with shape i
    when the signature turns it by at most `facing.angle` towards i (no turn); a turn
    must cost at most `facing.tolerance` more by the Chamfer cost."""

    what = "facing"
    progress, span = 0.68, 0.18

    def __init__(self, state: ConsensusState, start: Sequence[np.ndarray], eligible: Sequence[bool]):
        self.state, self.start, self.eligible = state, start, eligible
        self.shared_votes = state.settings.facing.shared_facing

    def agree(self, j: int, i: int) -> bool:
        return not self.decide(j, [(i, self.start[i])]).changed

    def share_none(self) -> bool:
        """The inputs share no facing: a turned shape stays no reference (False)."""
        return False

    def decide(self, j: int, references: list[tuple[int, np.ndarray]], why: str = "") -> PoseDecision:
        """Shape j turned about up to its references' facing, or kept; `why`: the inputs
        share no facing (then a turn of more than `facing.unshared_angle` is enough)."""
        state, facing, rotation = self.state, self.state.settings.facing, self.start[j]
        angle, coherence = state.evidence.signatures.facing_turn(j, rotation, references)
        least = facing.unshared_angle if why else facing.angle
        cost = state.search.cost(j, rotation, references)
        candidate = yaw_rotation(angle) @ rotation
        if (coherence <= state.settings.signature.coherence or abs(angle) <= least
                or state.search.cost(j, candidate, references) > (1.0 + facing.tolerance) * cost):
            return PoseDecision(rotation)
        return PoseDecision(candidate, f"{describe_rotation(candidate @ rotation.T)}: its facing like its "
                                       f"{len(references)} nearest shapes ({reference_names(state.names, references)})"
                                       + (f" ({why})" if why else ""))


def outlier_flags(state: ConsensusState) -> None:
    """Step 4: the steps' decisions combined (`combined`) into `state.decisions`; a shape
    not flagged yet that fits its nearest shapes (final poses) over `outlier_factor`
    times worse than the median shape does is flagged, with no turn."""
    decisions = [combined(*stages) for stages in zip(state.stood, state.ends, state.faced)]
    state.decisions = decisions
    n, search = state.n, state.search
    if n < 3:
        return
    report = step_progress(state.report, 0.86, 0.02, "checking the poses: ")
    k = min(state.settings.facing.neighbours, n - 1)
    rotations = [d.rotation for d in decisions]
    costs = []
    for j in range(n):
        report((j + 1) / n, f"{j + 1} of {n}")
        costs.append(search.cost(j, rotations[j], [(i, rotations[i]) for i in search.nearest(j, range(n), k)]))
    costs = np.array(costs)
    median = float(np.median(costs))
    state.decisions = []
    for d, cost in zip(decisions, costs):
        if not d.flag and cost > state.settings.outlier_factor * median:
            d = PoseDecision(d.rotation, d.reason, d.steps,
                             f"fits its {k} nearest shapes {cost / median:.1f}× worse than the collection's median "
                             "shape does (an unusual shape, or a pose no turn fixes)")
        state.decisions.append(d)


def _settle(state: ConsensusState, test: _CostFacing | _SignatureFacing, keep: Sequence[bool]) -> list[PoseDecision]:
    """Step 3 with one `test`: votes of every shape with its k nearest shapes
    (`test.agree`), the majority group (of `test.eligible` shapes) keeps its poses
    (`test.start`), everyone else is decided (`test.decide`) against its k nearest
    settled shapes, closest to the settled ones first; `keep` shapes never move. When at
    most `test.shared_votes` of the votes agree, the inputs share no pose that this test
    could keep (the majority is a chance group): the medoid of the voters alone keeps its
    pose, and everyone else is decided given why, for its reason. When the test then
    trusts turned shapes (`test.share_none`: the cost test makes the search compare
    shapes at any turn) a shape it turns is a reference for the shapes after it like one
    it keeps (no input pose is more to trust than a turned one), so the collection
    follows the medoid from nearest shape to nearest shape."""
    search, n, report = state.search, state.n, state.report
    k = min(state.settings.facing.neighbours, n - 1)
    voters = [j for j in range(n) if test.eligible[j]]
    votes, nearest = _facing_votes(state, test, voters, k)
    majority = _majority(search, votes, nearest, voters)
    agreeing = sum(votes.values())
    unshared = bool(votes) and agreeing <= test.shared_votes * len(votes)
    trust_turned = unshared and test.share_none()
    why = ""
    if unshared:
        majority = [_medoid(search, voters)]
        why = f"no input {test.what} is shared: {agreeing} of {len(votes)} pairs of nearest shapes agree"
    decisions = {j: PoseDecision(test.start[j]) for j in majority}
    references_pool = list(decisions)  # shapes whose pose is trusted: kept ones only from the majority
    decisions.update({j: PoseDecision(test.start[j]) for j in range(n) if keep[j] and j not in decisions})
    # the next shape is the one closest to its nearest trusted shape (kept up to date as
    # the pool grows, not asked of every shape after every decision, which is quadratic in a large collection)
    waiting = NearestInPool(search, references_pool, [r for r in range(n) if r not in decisions])
    while len(decisions) < n:
        j = waiting.closest()
        references = [(i, decisions[i].rotation) for i in search.nearest(j, references_pool, k)]
        decisions[j] = test.decide(j, references, why)
        if trust_turned or not decisions[j].changed:  # a turned shape's pose is a guess: no reference
            references_pool.append(j)
            waiting.join(j)
        else:
            waiting.leave(j)
        report(test.progress + 0.5 * test.span + 0.5 * test.span * len(decisions) / n,
               f"orienting {len(decisions)} of {n}")
    return [decisions[j] for j in range(n)]


def _facing_votes(state: ConsensusState, test: _CostFacing | _SignatureFacing, voters: Sequence[int],
                  k: int) -> tuple[dict[tuple[int, int], bool], dict[int, list[int]]]:
    """Whether each voter and each of its k nearest voters agree (`test.agree`, each pair
    asked once), and those nearest voters."""
    search, n = state.search, state.n
    votes: dict[tuple[int, int], bool] = {}
    # each voter's nearest voters, asked once: above neighbours.EXACT_SHAPES a later query
    # can rank a pair whose exact cost another query computed since (its estimate was
    # above it), and the majority must count the pairs voted on (1000 vases: a KeyError)
    nearest: dict[int, list[int]] = {}
    for j in voters:  # a shape turned before has no vote, nor is it counted as a neighbour
        nearest[j] = search.nearest(j, voters, k)
        for i in nearest[j]:
            pair = (min(i, j), max(i, j))
            if pair not in votes:
                votes[pair] = test.agree(*pair)
        state.report(test.progress + 0.5 * test.span * (j + 1) / n, f"comparing {j + 1} of {n}")
    return votes, nearest


def _majority(search: PoseSearch, agree: dict[tuple[int, int], bool], nearest: dict[int, list[int]],
              voters: Sequence[int]) -> list[int]:
    """Step 2: the largest group of `voters` that agree with most of their `nearest` voters,
    connected by agreeing pairs (when no shape agrees, the medoid of the voters, or of
    all shapes when there are none, alone)."""
    n = len(search)
    votes = np.zeros(n)
    for j in voters:
        votes[j] = np.mean([agree[(min(i, j), max(i, j))] for i in nearest[j]] or [0.0])
    members = np.flatnonzero(votes > 0.5)
    if len(members) == 0:
        return [_medoid(search, voters)]
    edges = np.array([pair for pair, ok in agree.items() if ok and votes[pair[0]] > 0.5 and votes[pair[1]] > 0.5],
                     dtype=int).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    biggest = int(np.argmax(np.bincount(label[members])))
    return [int(j) for j in members if label[j] == biggest]


def _medoid(search: PoseSearch, pool: Sequence[int]) -> int:
    """The shape of `pool` (empty: of all shapes) with the smallest summed distance to all shapes."""
    pool = np.asarray(pool if len(pool) else range(len(search)), dtype=int)
    return int(pool[np.argmin(search.distance[pool].sum(axis=1))])

