"""Step 2 of the consensus orientation, top and bottom (`tops_and_bottoms`): a shape is
turned over only when the collection agrees on top and bottom and the shape clearly does not:
- its hollow (`hollow.Hollows`) opens the other way up from at least
  `hollows.agreement` of the shapes whose hollows tell (at least three), and turning
  it costs at most `hollows.cost` times its pose; or
- at least `costs.agreement` of its references fit it better turned over (by
  `costs.margin`), by `ends.flip_margin` at the median (`ends.flip_support` when its
  odd moments say the same as strongly), while the collection's shapes agree with each
  other (the median shape is asked to turn over by at most 1 − `costs.agreement` of
  its references). A taper, bulge or lean that varies across the class makes shapes
  ask each other to turn over; then the costs decide nothing.
Weaker evidence is a flag "may be upside down": its hollow alone (the cost objecting),
its odd-moment signature (`signature.Signatures`: its top and bottom match the bottom
and top of most of its references, the collection's shapes agreeing with each other),
or at least half of its references asking for it by `costs.margin`, 0.4 more than the
collection's median shape does. A shape stood on another axis in step 1 whose end
nothing told there and nothing tells clearly here takes the end weak evidence leans
to (else the file convention's) and is flagged, the other end suggested. The floor
as in step 1: a shape resting on it as given is flagged, not turned over; one resting
on it only after a half turn about its origin is turned over unless the costs
clearly keep it (then flagged).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ...base.progress import Progress
from ..rotations import describe_rotation
from .settings import ConsensusSettings, HollowSettings
from .state import ConsensusState, HALF_TURN_X, HALF_TURN_Y, LANDS, PoseDecision, RESTING, convention_height, step_progress


@dataclass(frozen=True)
class _EndVotes:
    """Step 2's evidence, per shape j: its references (settled shapes), the standing costs
    against each (rows of six), their cost ratios (its pose / turned over), which of them
    ask it to turn over by the costs (`asked`) and by the odd moments (`opposed`), and
    which way its hollow opens (`openings`, up component)."""

    references: dict[int, list[int]]
    costs: dict[int, np.ndarray]
    ratios: dict[int, np.ndarray]
    asked: dict[int, np.ndarray]
    opposed: dict[int, np.ndarray]
    openings: np.ndarray

    @classmethod
    def of(cls, state: ConsensusState, poses: Sequence[np.ndarray], report: Progress) -> "_EndVotes":
        n, settings = state.n, state.settings
        pool = [j for j in range(n) if not state.stood[j].flag]  # a shape maybe on its side is no reference
        references, ratios, costs = {}, {}, {}
        for j in range(n):
            report((j + 1) / n, f"{j + 1} of {n}")
            references[j] = state.costs.references(j, pool)
            costs[j] = np.array([state.costs.standing_costs(j, poses[j], i, poses[i])
                                 for i in references[j]]).reshape(-1, 6)
            ratios[j] = costs[j][:, 0] / np.maximum(costs[j][:, 1], 1e-300)
        asked = {j: ratios[j] > settings.costs.margin for j in range(n)}
        # the odd-moment signature's votes: a reference whose top and bottom match its bottom and top
        signatures, coherence = state.evidence.signatures, settings.signature.coherence
        opposed = {j: np.array([signatures.up_agreement(j, poses[j], [(i, poses[i])]) < -coherence
                                for i in references[j]], dtype=bool) for j in range(n)}
        hollows = state.evidence.hollows
        openings = np.array([hollows.vertical(j, poses[j]) for j in range(n)]) if hollows is not None else np.zeros(n)
        return cls(references, costs, ratios, asked, opposed, openings)


def tops_and_bottoms(state: ConsensusState) -> None:
    """Step 2: turn-overs on evidence that holds over the collection (module docstring),
    into `state.ends`. A shape resting as given on the floor its collection's files share
    (`state.resting`) is flagged, not turned over, unless step 1 stood it on another axis."""
    poses = [d.rotation for d in state.stood]
    votes = _EndVotes.of(state, poses, step_progress(state.report, 0.35, 0.15, "tops and bottoms: "))
    state.ends = [_end_decision(state, j, poses, votes) for j in range(state.n)]


def _end_decision(state: ConsensusState, j: int, poses: Sequence[np.ndarray], votes: _EndVotes) -> PoseDecision:
    """Shape j (in its `poses`, after step 1) turned over, flagged "may be upside down",
    or left as it is (step 2 of the module docstring)."""
    stood, frozen = state.stood[j], state.frozen[j]
    if not len(votes.ratios[j]):
        return PoseDecision(poses[j])
    ends = _EndEvidence.of(j, votes, state.settings)
    # a file saved upside down: its floor is its other end (not a shape stood up in step 1:
    # its end was chosen there, by the floor where the floor tells)
    lands = not stood.changed and state.floor_turns[j] == 1
    landing = lands and not ends.clear_keep  # the costs clearly keeping it: a flag
    turning = ((ends.clear_flip or landing) and not frozen) or (stood.end_guessed and not ends.clear_keep)
    if not (turning or ends.some_flip or lands):
        return PoseDecision(poses[j])
    posed = [(i, poses[i]) for i in votes.references[j]]
    # turned over about x or about y: the same up, facing the other way; the cheaper one
    # (full-sample costs, asked only of a shape that is turned or flagged)
    flipped = min((HALF_TURN_X @ poses[j], HALF_TURN_Y @ poses[j]),
                  key=lambda r: state.search.cost(j, r, posed))
    resting = ends.clear_flip and not stood.changed and state.resting[j]
    if (ends.clear_flip or landing) and not frozen and not resting:
        why = "; ".join(w for w in (ends.flip_reason, LANDS if landing else "") if w)
        return PoseDecision(flipped, f"{describe_rotation(flipped @ poses[j].T)}: {why}")
    if stood.end_guessed and j in state.convention_files:
        return _convention_end(state, poses[j], flipped)
    if stood.end_guessed and not ends.clear_keep:
        return _guessed_end(poses[j], flipped, ends)
    doubted = f"{LANDS}, but its references fit it better as given" if lands and not landing else ""
    why = "; ".join(w for w in (ends.flip_reason, LANDS if landing else doubted, RESTING if resting else "") if w)
    return PoseDecision(poses[j], flag=f"may be upside down: {why}", flag_rotation=flipped)


def _convention_end(state: ConsensusState, pose: np.ndarray, flipped: np.ndarray) -> PoseDecision:
    """A shape stood on the other common convention's up line in a collection that
    evidently mixes the conventions (`_mixed_conventions`), its end told by nothing clear:
    the end that convention puts up (its file's +y among z-up files), not flagged. Weak
    evidence against it (odd moments, a minority of references) does not outweigh files
    that share a convention; clear evidence turned it over before this point."""
    if convention_height(pose, state.convention) > 0.99:
        return PoseDecision(pose)
    return PoseDecision(flipped, f"{describe_rotation(flipped @ pose.T)}: the end the other common file "
                                 f"convention puts up, as {len(state.convention_files)} files of the collection "
                                 f"are saved")


def _guessed_end(pose: np.ndarray, flipped: np.ndarray, ends: "_EndEvidence") -> PoseDecision:
    """A shape stood on another axis whose end nothing clearly tells: the end weak evidence
    leans to (else the file convention's), flagged with the other end as the suggestion."""
    if ends.weak_flip and not ends.some_keep:
        return PoseDecision(flipped, f"{describe_rotation(flipped @ pose.T)}: its other end up, on weak evidence "
                                     f"({ends.flip_reason})", flag="may be upside down: stood on another axis of its "
                                     f"file, its end chosen on weak evidence ({ends.flip_reason})", flag_rotation=pose)
    why = ("on weak evidence (its top and bottom match most of its references')" if ends.some_keep else
           "by the other file convention: nothing in the collection tells its top from its bottom")
    return PoseDecision(pose, flag=f"may be upside down: stood on another axis of its file, its end chosen {why}",
                        flag_rotation=flipped)


@dataclass(frozen=True)
class _EndEvidence:
    """What the collection says of one shape's top and bottom (step 2 of the module
    docstring): whether it clearly is upside down (`clear_flip`), whether the evidence
    says it may be (`some_flip`: a flag), whether anything at all leans that way
    (`weak_flip`: enough to choose the end of a shape stood up anyway) or says it is not
    (`some_keep`), and the words for it."""

    clear_flip: bool
    some_flip: bool
    weak_flip: bool
    some_keep: bool
    clear_keep: bool
    flip_reason: str

    @classmethod
    def of(cls, j: int, votes: _EndVotes, settings: ConsensusSettings) -> "_EndEvidence":
        costs_settings, ends = settings.costs, settings.ends
        ratios, openings = votes.ratios[j], votes.openings
        agreeing = 1.0 - costs_settings.agreement  # the most a collection agreeing with itself asks
        asked, opposed = float(np.mean(votes.asked[j])), float(np.mean(votes.opposed[j]))
        cost_background = _background(votes.asked, votes.references, j)
        moment_background = _background(votes.opposed, votes.references, j)
        median = float(np.median(ratios))
        hollow = _hollow_disagrees(openings, j, settings.hollows)
        hollow_keeps = _hollow_agrees(openings, j, settings.hollows)
        moments_flip = opposed > 0.5 and moment_background <= agreeing
        moments_strong = opposed >= costs_settings.agreement and moment_background <= agreeing
        cost_strong = (asked >= costs_settings.agreement and cost_background <= agreeing and not hollow_keeps
                       and (median >= ends.flip_margin or (moments_strong and median >= ends.flip_support)))
        cost_flip = asked >= 0.5 and median > costs_settings.margin and asked - cost_background >= 0.4
        costs = votes.costs[j]
        cost_allows = np.median(costs[:, 1]) <= settings.hollows.cost * np.median(costs[:, 0])
        share = f"{int(round(asked * len(ratios)))} of {len(ratios)} shapes fit it better turned over"
        moments = f"its top and bottom match the bottom and top of {opposed:.0%} of its {len(ratios)} references"
        if hollow:
            reason = hollow
        elif cost_strong:
            reason = f"{share} ({median:.1f}× at the median), the collection agreeing on top and bottom" + (
                f", and {moments}" if moments_strong else "")
        elif cost_flip:
            reason = (f"{share} ({median:.1f}× at the median), but top and bottom vary across the collection (the "
                      f"median shape is asked to turn over by {cost_background:.0%} of its references)")
        elif moments_flip:
            reason = moments
        else:
            reason = ""
        # a flag needs most references (the odd moments: a minority of the other taper is
        # as opposed as a third of the files upside down, so only a clear majority flags)
        flags = bool(hollow) or cost_strong or cost_flip or moments_strong
        clear_keep = hollow_keeps or (median <= 1.0 / costs_settings.margin and cost_background <= agreeing)
        keeps = clear_keep or (opposed < 0.5 and moment_background <= agreeing and not cost_flip)
        return cls(bool(hollow and cost_allows) or cost_strong, flags, bool(reason), keeps and not hollow,
                   clear_keep and not hollow, reason)


def _background(votes: dict[int, np.ndarray], references: dict[int, list[int]], j: int) -> float:
    """How much the collection's shapes ask each other to turn over: among the shapes
    other than j that most of their references do not ask (the collection's majority),
    the median share of their references in that majority that ask them. Near 0 when
    the majority agrees on top and bottom (a few shapes turned over do not raise it);
    near a half when a feature that varies across the class (a taper) decides the votes."""
    majority = {k for k in votes if k != j and len(votes[k]) and np.mean(votes[k]) <= 0.5}
    shares = []
    for k in majority:
        inside = [v for i, v in zip(references[k], votes[k]) if i in majority]
        if inside:
            shares.append(np.mean(inside))
    return float(np.median(shares)) if shares else 1.0


def _hollow_signs(openings: np.ndarray, j: int, settings: HollowSettings) -> int:
    """+1 / −1 when the hollows of the other shapes that tell (at least three) open that
    way up in at least `hollows.agreement` of them; 0 when they do not agree. Which way a
    hollow opens does not vary across a class as a taper does (a cup opens at its top), so
    a clear majority is the collection's even with a third of its files upside down."""
    others = np.delete(openings, j)
    telling = others[np.abs(others) > settings.opening]
    if len(telling) < 3:
        return 0
    up = float(np.mean(telling > 0))
    return 1 if up >= settings.agreement else -1 if 1.0 - up >= settings.agreement else 0


def _hollow_disagrees(openings: np.ndarray, j: int, settings: HollowSettings) -> str:
    """Why shape j's hollow says it is upside down ('' when it does not)."""
    sign = _hollow_signs(openings, j, settings)
    own = openings[j]
    if sign == 0 or abs(own) <= settings.opening or np.sign(own) == sign:
        return ""
    return (f"its hollow opens {'upwards' if own > 0 else 'downwards'} ({own:+.2f}), the collection's "
            f"{'upwards' if sign > 0 else 'downwards'}")


def _hollow_agrees(openings: np.ndarray, j: int, settings: HollowSettings) -> bool:
    sign = _hollow_signs(openings, j, settings)
    return sign != 0 and abs(openings[j]) > settings.opening and np.sign(openings[j]) == sign

