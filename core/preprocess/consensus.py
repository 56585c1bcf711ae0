"""Consensus orientation of a collection (thesis §3.4; step 3 of `prepare_collection`):
a shape's pose changes only on evidence much stronger than sampling noise that the
collection disagrees with it.

Every shape starts in its base pose, its input pose with the given up axis turned to +z
(no yaw: when the inputs already agree, nobody is turned, rotation exactly identity).
Three stages decide:

0. Up by symmetry (`up_by_symmetry`, `symmetry.AxisSymmetry`): the symmetries the
   collection's shapes share about their up axes (rotational about up, mirror across
   planes through or across it) are its up profile; a shape stands on its x or y axis,
   or on a direction tilted 20-60° from its up, when that axis scores clearly more like
   the profile than its up does (by `symmetry_gap` and the factor `symmetry_ratio`),
   and its nearest shapes whose up already scores best fit it no worse that way. This
   needs no nearest shape in the right pose: PSB cups lying on their side together (26,
   27, 29) and teapots written z-up (367, 379) are stood up, a cup tilted in its file
   (36) straightened. Calibration (bench/orientation.py): consistent procedural vases
   and barrels and Blender mugs score their up at most 1.6 and other axes at least 2;
   PSB cups on their side their up 1.8-2.3 and their own axis 0.5-1.5.
A. Chamfer cost (`posesearch.PoseSearch`): a shape is turned when the best rotation (24
   axis rotations, any turn about z) fits its nearest shapes more than `margin` times
   better than its pose, f(I) / f(R) > margin, on average and for most of them one by
   one; a change of the up direction must also beat the best upright pose by
   `tilt_margin` and score no worse by symmetry (`AxisSymmetry.allows_tilt`: PSB bowls
   among jugs fit them 2-4× better on their side, but their up is their axis of
   symmetry). Calibration (600 samples, 3 neighbours): over upright procedural vases and
   barrels at many seeds the ratio of a consistent shape stays below 1.07 (1.14 for a
   single pair); a vase upside down or any shape on its side scores 1.6 to 10. The
   Chamfer cost hardly sees a spout or a knob (a vase turned 180° about z: ratio
   1.00-1.05), hence stage B.
B. Signatures (`signature.Signatures`, exact odd surface moments): a shape is flipped
   when its top-bottom signature anti-correlates with its nearest shapes' (correlation
   < −`up_agreement`), and turned about z by the angle its facing signature differs by,
   when the facing is shared (coherence > `coherence`) and the angle exceeds
   `facing_angle` (`refine_angle` for a shape turned anyway). Calibration: consistent
   vases and barrels differ in facing from their nearest shapes by up to 16° (coarse
   vases, 20 seeds; coherence ≥ 0.95, top-bottom correlation ≥ 0.95); flipped ones
   score ≤ −0.95, and a 37° turn is measured as 35-39°. The signatures decide only what
   the cost cannot see: a turn they ask for is made only if it raises the cost by at
   most `tolerance` (on PSB fish the top-bottom signature alone flipped upright fish).
   Hollows (`hollow.Hollows`, inside/outside aware): a shape whose hollow opens the other
   way up from every nearest shape's (each by more than `hollow_floor`) is flipped, unless
   the flip costs more than `hollow_cost` times its pose (then `pose_outliers` flags it):
   upside down, a mug tapering the other way looks like its upright neighbours to the
   cost and the odd moments; only its open top and closed bottom tell.

   Unshared facing (beyond the thesis, issue 13): inputs turned about up at random share
   no facing for the majority to keep. When at most `shared_facing` of stage B's votes
   agree (chance level for random turns: 1/6 of the pairs within ±30°; measured 0.09-0.27
   on procedural vases and barrels in random poses, 0.52-1.0 on the PSB classes), the
   medoid alone keeps its pose and every other shape is turned by the facing difference
   its signature measures above `unshared_angle`, not `facing_angle`: shapes that happened
   to lie within 30° of each other kept those differences (6 procedural vases, seed 1:
   true turns 0, 6.8 and 15.8° apart, a rigid turn the correspondence then keeps; the
   Chamfer cost is flat in yaw there, within 1-2 % over ±30°). The facing signature of
   these vases, exact moments, measures their turn to 0.01°.

   Unshared pose (the same for stage A; beyond the thesis): when at most `shared_pose` of
   the Chamfer votes agree (PSB classes as filed 0.77-1.0; every file of PSB Airplane or
   Fish turned about up at random 0.09-0.33), no input pose is shared. The search then
   compares shapes at any turn about up (`PoseSearch.compare_turned`: at the 24 axis
   rotations alone the nearest shapes of a turned airplane are chance ones, and fitted to
   chance shapes 2-4 of 20 took a wrong turn, half a turn where the Chamfer cost of the
   right shapes tells it 2-10× apart), the medoid keeps its pose, and every other shape,
   nearest to the settled ones first, takes the rotation that fits its nearest settled
   shapes best when it fits them `unshared_margin` times better; a shape settled so,
   turned or not, is a reference for the next ones (no input pose is more to trust).
   Near-round shapes (PSB cups and vases, procedural vases) fit each other as well at
   any turn, agree in stage A whatever their turns, and are left to stage B.

Stages A and B each take the same three steps (`_settle`):

1. Votes: every shape not turned by an earlier stage against each of its `neighbours`
   nearest such shapes (smallest cost over the 24 axis rotations). The pair agrees when
   the stage would not turn one to match the other.
2. The collection's pose: shapes agreeing with more than half of their neighbours form
   groups (connected by agreeing pairs); the largest group is the majority, whose poses
   are the collection's (nobody in it is ever turned). Without any agreeing shape the
   medoid is the majority of one, as it is in stage B when the facing is unshared
   (above). A turned shape has no vote and is in no majority (it has no input pose to
   keep).
3. Everyone else, closest to the majority first, is decided against its nearest shapes
   already settled and not turned (a turned shape's pose is a guess), then settled.
   `keep` shapes are never turned and are no reference unless they are in the majority.

Last, the pose check (`pose_checks`, the one `pose_outliers` flags with) of the settled
poses against every shape's nearest shapes in their final poses: a shape not kept that a
rotation fits them `margin` times better, or whose facing they share, is turned
(`restore_flagged`). The stages decide a shape against references settled before it,
and a shape in a wrong pose can be one: PSB cup 31 faces away from the cups (a weakly
shared facing) but agreed with two neighbours one by one, so it kept its pose, and cup
26, stood up by symmetry, took its facing from it; in their final poses both fit their
nearest shapes 1.3× and 2.1× better turned 180°.

Each pose change comes with its reason ("turned 180° about x: its 3 nearest shapes
(a, b, c) fit 2.4× better"); a shape turned and turned back (to within 1°) keeps its
input pose. Known limit: a group of shapes sharing one wrong facing that is as large as
the majority, or that only has itself as nearest shapes, keeps that facing;
`pose_outliers` flags shapes whose final pose still disagrees with their nearest shapes
or the collection's up by symmetry, or fits them much worse than the collection's median.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..progress import Progress, no_progress, sub_range
from .hollow import Hollows
from .posesearch import Fit, NearestInPool, PoseSearch
from .rotations import describe_rotation, yaw_rotation
from .signature import Signatures
from .symmetry import AxisSymmetry

__all__ = ["ConsensusSettings", "PoseCheck", "PoseDecision", "consensus_rotations", "pose_checks", "pose_outliers",
           "restore_flagged"]


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
    #: share of the facing votes (pairs of nearest shapes whose facings agree to
    #: `facing_angle`) at or below which the collection shares no input facing (random
    #: turns about up agree by chance, 1/6 of the pairs: 0.09-0.27 measured on procedural
    #: vases and barrels; PSB classes 0.52-1.0)
    shared_facing: float = 0.4
    #: facing difference (degrees) above which a shape is turned when the collection
    #: shares no input facing (the facing of one shape is the collection's, to this angle)
    unshared_angle: float = 0.5
    #: share of the Chamfer votes (pairs of nearest shapes that fit each other within
    #: `margin` as they are) at or below which the collection shares no input pose (PSB
    #: classes as filed 0.77-1.0; every file turned about up at random: Airplane and Fish
    #: 0.09-0.33, near-round Cup and Vase 0.6-0.8, whose turns stage B's facing then decides)
    shared_pose: float = 0.4
    #: cost ratio (its pose / best rotation) above which a shape is turned when the
    #: collection shares no input pose
    unshared_margin: float = 1.1
    #: Chamfer improvement with which a weakly shared facing still flags a shape
    facing_support: float = 1.2
    #: Legendre polynomials in height in the facing signature
    facing_order: int = 5
    #: a shape fitting its nearest shapes this many times worse than the median is flagged
    outlier_factor: float = 3.0
    #: shapes needed for the symmetry stage (the collection's up profile is a median)
    symmetry_shapes: int = 5
    #: lowest spread (log units) of a symmetry feature in the up profile
    symmetry_floor: float = 0.3
    #: score difference (its up − another axis) above which a shape stands on that axis
    symmetry_gap: float = 0.4
    #: ... and the factor by which the other axis must score better
    symmetry_ratio: float = 1.3
    #: an up scoring above this is searched for a tilt (and flagged when tilted)
    symmetry_flag: float = 2.0
    #: a tilt (degrees) of the best-scoring up direction above which it is stood on or flagged
    symmetry_tilt: float = 20.0
    #: directions of the tilt search's grid (upper half sphere)
    symmetry_directions: int = 40
    #: voxel grid cells along a shape's longest side for its hollows (`hollow.Hollows`)
    hollow_grid: int = 40
    #: up component of a hollow's opening vector above which it tells top from bottom
    hollow_floor: float = 0.1
    #: cost ratio (flipped / its pose) up to which a shape whose hollow opens the other
    #: way up from its nearest shapes' is flipped (above it: flagged only)
    hollow_cost: float = 1.5


@dataclass(frozen=True)
class PoseDecision:
    """The rotation consensus applied to one shape (after its up rotation) and why."""

    rotation: np.ndarray
    reason: str = ""  # empty when the shape kept its base pose
    #: the reasons of the single turns a combined decision is made of (`_combined`), so a
    #: decision combined again lists its turns once instead of nesting "in all (...)"
    steps: tuple[str, ...] = ()

    @property
    def changed(self) -> bool:
        return bool(self.reason)


def consensus_rotations(search: PoseSearch, signatures: Signatures, names: Sequence[str], keep: Sequence[bool],
                        settings: ConsensusSettings, report: Callable[[float, str], None],
                        symmetry: AxisSymmetry | None = None, hollows: Hollows | None = None) -> list[PoseDecision]:
    """The pose decision of every shape (the steps of the module docstring): first the up
    axis by the collection's symmetries (`symmetry`, none: skipped), then by the Chamfer
    cost (up direction, large turns), then by the signatures and the hollows (top and
    bottom, facing at any angle; `hollows`, none: skipped)."""
    n = len(search)
    k = min(settings.neighbours, n - 1)
    identity = np.eye(3)
    stood = up_by_symmetry(search, symmetry, names, keep, settings, lambda f, m: report(0.2, m)) \
        if symmetry is not None else [PoseDecision(identity)] * n
    start = [d.rotation for d in stood]
    report(0.2, "up axes by symmetry")

    def by_cost_agree(j: int, i: int) -> bool:
        reference = [(i, start[i])]
        _, fit = search.best_rotation(j, reference, settings.yaw_step, settings.tilts, False, 0.0, _or_none(start[j]))
        return search.cost(j, start[j], reference) <= settings.margin * fit.cost

    def turned_by_cost(j: int, fit: Fit, ratio: float, references: list[tuple[int, np.ndarray]],
                       why: str = "") -> PoseDecision:
        return PoseDecision(fit.rotation, f"{describe_rotation(fit.rotation @ start[j].T)}: its {len(references)} "
                                          f"nearest shapes ({_names(names, references)}) fit {ratio:.1f}× better"
                                          + (f" ({why})" if why else ""))

    def by_cost(j: int, references: list[tuple[int, np.ndarray]]) -> PoseDecision:
        fit = _best_pose(search, symmetry, settings, j, references, start[j], refine=True)
        ratio = search.cost(j, start[j], references) / max(fit.cost, 1e-300)
        # most references must ask for the turn one by one (a bowl among jugs: the jugs
        # prefer it on its side, the other bowls upright)
        each = sum(search.cost(j, start[j], [r]) > settings.margin * search.cost(j, fit.rotation, [r])
                   for r in references)
        if ratio <= settings.margin or 2 * each <= len(references):
            return PoseDecision(start[j])
        return turned_by_cost(j, fit, ratio, references)

    def by_cost_unshared(j: int, references: list[tuple[int, np.ndarray]], unshared: str) -> PoseDecision:
        # no input pose to keep: the best fit to the shapes settled nearest, when it is
        # worth a turn (a near-round shape fits its references as well at any turn)
        fit = _best_pose(search, symmetry, settings, j, references, start[j], refine=True)
        ratio = search.cost(j, start[j], references) / max(fit.cost, 1e-300)
        if ratio <= settings.unshared_margin:
            return PoseDecision(start[j])
        return turned_by_cost(j, fit, ratio, references, unshared)

    # inputs turned about up at random share no pose for a majority to keep: one shape's
    # pose is the collection's and the others follow it shape by shape, nearest first
    first = _settle(search, k, keep, start, by_cost_agree, by_cost, report, 0.2, [not d.changed for d in stood],
                    by_cost_unshared, settings.shared_pose, "pose",
                    unshared_search=lambda: search.compare_turned(settings.yaw_step))
    turned = [d.rotation for d in first]

    def by_signature_agree(j: int, i: int) -> bool:
        return not by_signature(j, [(i, turned[i])], turned[j]).changed

    def by_signature(j: int, references: list[tuple[int, np.ndarray]], start=None,
                     unshared: str = "") -> PoseDecision:
        start = turned[j] if start is None else start
        rotation, why = start, []
        cost = search.cost(j, start, references)

        def cost_allows(turned_rotation: np.ndarray) -> bool:
            # the signatures decide what the cost cannot see; they never overrule it
            return search.cost(j, turned_rotation, references) <= (1.0 + settings.tolerance) * cost

        if (signatures.up_agreement(j, rotation, references) < -settings.up_agreement
                and cost_allows(_HALF_TURN_X @ rotation)
                and not _opens_upside_down(hollows, j, _HALF_TURN_X @ rotation, references, settings)):
            rotation = _HALF_TURN_X @ rotation
            why.append("its top and bottom")
        elif _opens_upside_down(hollows, j, rotation, references, settings):
            # the hollow sees what the cost cannot (which end is open): it flips unless
            # the cost objects as strongly as it would need to turn a shape itself
            flipped = min((half @ rotation for half in _HALF_TURNS), key=lambda r: search.cost(j, r, references))
            if search.cost(j, flipped, references) <= settings.hollow_cost * cost:
                rotation = flipped
                why.append("which way its hollow opens")
        turning = bool(why) or first[j].changed or stood[j].changed
        angle, coherence = signatures.facing_turn(j, rotation, references)
        least = settings.unshared_angle if unshared else settings.refine_angle if turning else settings.facing_angle
        if coherence > settings.coherence and abs(angle) > least and cost_allows(yaw_rotation(angle) @ rotation):
            rotation = yaw_rotation(angle) @ rotation
            why.append("its facing")
        if not why:
            return PoseDecision(start)
        return PoseDecision(rotation, f"{describe_rotation(rotation @ start.T)}: {' and '.join(why)} like its "
                                      f"{len(references)} nearest shapes ({_names(names, references)})"
                                      + (f" ({unshared})" if unshared else ""))

    # a shape the cost turned has no input facing to keep: it never joins the majority
    # inputs turned about up at random share no facing: the one of a single shape is the
    # collection's, and every other shape is turned to it by what its signature measures
    second = _settle(search, k, keep, turned, by_signature_agree, by_signature, report, 0.5,
                     [not (a.changed or b.changed) for a, b in zip(stood, first)],
                     lambda j, references, why: by_signature(j, references, unshared=why), settings.shared_facing,
                     "facing")
    decisions = [_combined(*stages) for stages in zip(stood, first, second)]
    report(0.85, "checking the poses")
    return restore_flagged(search, signatures, names, keep, settings, decisions, symmetry, hollows,
                           sub_range(report, 0.85, 0.88, "checking the poses: "))


_HALF_TURN_X = np.diag([1.0, -1.0, -1.0])
_HALF_TURNS = (_HALF_TURN_X, np.diag([-1.0, 1.0, -1.0]))


def _opens_upside_down(hollows: Hollows | None, j: int, rotation: np.ndarray,
                       references: list[tuple[int, np.ndarray]], settings: ConsensusSettings) -> bool:
    """Whether shape j's hollow opens the other way up from every reference's (no hollows: no)."""
    return hollows is not None and hollows.upside_down(j, rotation, references, settings.hollow_floor) is not None


def _faces_away(turned_cost: float, cost: float, coherence: float, settings: ConsensusSettings) -> bool:
    """Whether a shape whose facing signature differs from its nearest shapes' (by more
    than facing_angle) is flagged: a shared facing (coherence above `coherence`) the turn
    costs at most `tolerance` more, or a weaker one (above half of it) the turn fits
    `facing_support` times better (PSB cup 31, handle 180° off: coherence 0.32, the turn
    fits 1.3× better)."""
    return ((coherence > settings.coherence and turned_cost <= (1.0 + settings.tolerance) * cost)
            or (coherence > settings.coherence / 2 and settings.facing_support * turned_cost < cost))


def _best_pose(search: PoseSearch, symmetry: AxisSymmetry | None, settings: ConsensusSettings, j: int,
               references: list[tuple[int, np.ndarray]], start: np.ndarray, refine: bool) -> Fit:
    """The rotation of shape j (now turned by `start`) that fits the references best
    (`PoseSearch.best_rotation`, refined or on the grid), keeping its up unless a change
    of up fits `tilt_margin` times better than the best upright pose and the new up has
    no worse symmetry: a change of up needs its own evidence."""
    upright, fit = search.best_rotation(j, references, settings.yaw_step, settings.tilts, refine,
                                        settings.snap, _or_none(start))
    if upright.cost <= settings.tilt_margin * fit.cost or not _symmetry_allows(symmetry, j, fit, start):
        return upright
    return fit


def _symmetry_allows(symmetry: AxisSymmetry | None, j: int, fit: Fit, start: np.ndarray) -> bool:
    """Whether the symmetry stage lets shape j turn from `start` to `fit` (no stage: yes)."""
    return symmetry is None or symmetry.allows_tilt(j, fit.rotation, start)


def _or_none(rotation: np.ndarray) -> np.ndarray | None:
    """None for the base pose (the search's candidates unchanged), else the rotation."""
    return None if np.array_equal(rotation, np.eye(3)) else rotation


def up_by_symmetry(search: PoseSearch, symmetry: AxisSymmetry, names: Sequence[str], keep: Sequence[bool],
                   settings: ConsensusSettings, report: Progress | None = None) -> list[PoseDecision]:
    """Stage 0: the up axis of each shape by the symmetries its collection's shapes share
    about their up axes (`symmetry`, `standing_pose`), against its nearest shapes whose
    up already scores best of their axes. Fewer than `symmetry_shapes` shapes, or kept
    ones: no change."""
    n = len(search)
    identity = np.eye(3)
    if n < settings.symmetry_shapes:
        return [PoseDecision(identity)] * n
    symmetry.fit_profile([identity] * n, range(n))
    scores = np.array([symmetry.axis_scores(j, identity) for j in range(n)])
    trusted = [j for j in range(n) if np.argmin(scores[j]) == 0]
    decisions, report = [], report or no_progress
    for j in range(n):
        report((j + 1) / n, f"up axes by symmetry: {j + 1} of {n}")
        pool = [i for i in trusted if i != j]
        references = [(i, identity) for i in search.nearest(j, pool or range(n), settings.neighbours)]
        standing = None if keep[j] else standing_pose(search, symmetry, j, identity, references, settings)
        if standing is None:
            decisions.append(PoseDecision(identity))
            continue
        fit, where, _ = standing
        decisions.append(PoseDecision(fit.rotation, (
            f"{describe_rotation(fit.rotation)}: stood on {where}; end and turn as its {len(references)} nearest "
            f"upright shapes ({_names(names, references)})")))
    return decisions


def standing_pose(search: PoseSearch, symmetry: AxisSymmetry, j: int, rotation: np.ndarray,
                  references: list[tuple[int, np.ndarray]],
                  settings: ConsensusSettings) -> tuple[Fit, str, bool] | None:
    """(pose, words, tilted) standing shape j, now turned by `rotation`, on another axis, when that
    axis scores more like the collection's up than its up does, by `symmetry_gap` and
    the factor `symmetry_ratio` (`AxisSymmetry.axis_scores`): its x or y axis, or, when
    its up scores above `symmetry_flag` and is not clearly (`symmetry_ratio`) its best
    axis, the best direction within 60° of its up
    (`AxisSymmetry.best_up`) if more than `symmetry_tilt` degrees away (a shape tilted in
    its file). Which end is up and the turn about it fit the references best (Chamfer
    cost), and they must fit it no worse than its pose does. None: no such axis."""
    scores = symmetry.axis_scores(j, rotation)
    other = 1 + int(np.argmin(scores[1:]))

    def clearly_better(score: float) -> bool:
        return scores[0] - score > settings.symmetry_gap and scores[0] > settings.symmetry_ratio * score

    if clearly_better(scores[other]):
        axis, score, tilted = "xy"[other - 1], scores[other], False
        where = f"its {axis} axis"
        fits = [search.best_turn(j, references, d, settings.yaw_step, True, settings.snap, rotation)
                for d in ((2, 3) if axis == "x" else (4, 5))]  # TILTS: ±x / ±y up
    elif scores[0] > settings.symmetry_flag and scores[0] * settings.symmetry_ratio > scores[other]:
        tilt, score = symmetry.best_up(j, rotation, settings.symmetry_directions)
        degrees = float(np.degrees(np.arccos(np.clip(tilt[2, 2], -1.0, 1.0))))
        if degrees <= settings.symmetry_tilt or not clearly_better(score):
            return None
        where, tilted = f"an axis {degrees:.0f}° from its up", True
        fits = [search.best_yaw(j, references, end @ rotation, settings.yaw_step, True)
                for end in (tilt, _HALF_TURN_X @ tilt)]
    else:
        return None
    fit = min(fits, key=lambda f: f.cost)
    if fit.cost > search.cost(j, rotation, references):
        return None
    return fit, (f"{where}, whose symmetries are those the collection's shapes have about their up axes "
                 f"(score {score:.1f} against {scores[0]:.1f} for its up; 0 = the collection's typical up)"), tilted


def _way(vertical: float) -> str:
    return "upwards" if vertical > 0 else "downwards"


def _names(names: Sequence[str], references: Sequence[tuple[int, np.ndarray]]) -> str:
    return ", ".join(names[i] for i, _ in references)


def _combined(*stages: PoseDecision) -> PoseDecision:
    """One decision for the stages: the last one's rotation (each starts from the one
    before), the reasons of those that turned the shape."""
    reasons = [step for d in stages if d.reason for step in (d.steps or (d.reason,))]
    if reasons and np.trace(stages[-1].rotation) > 1.0 + 2.0 * np.cos(np.radians(1.0)):
        return PoseDecision(np.eye(3))  # turned there and back (to within 1°): its input pose
    reason = "; then ".join(reasons)
    if len(reasons) > 1:
        reason = f"{describe_rotation(stages[-1].rotation)} in all ({reason})"
    return PoseDecision(stages[-1].rotation, reason, tuple(reasons))


def _settle(search: PoseSearch, k: int, keep: Sequence[bool], start: Sequence[np.ndarray],
            agree: Callable[[int, int], bool], decide: Callable[[int, list], PoseDecision],
            report: Callable[[float, str], None], progress: float, eligible: Sequence[bool],
            decide_unshared: Callable[[int, list, str], PoseDecision] | None = None,
            shared_votes: float = 0.0, what: str = "pose",
            unshared_search: Callable[[], None] | None = None) -> list[PoseDecision]:
    """Steps 1–3 with one test: votes of every shape with its k nearest shapes (`agree`),
    the majority group (of `eligible` shapes) keeps its poses, everyone else is decided
    (`decide`) against its k nearest settled shapes, closest to the settled ones first;
    `keep` shapes never move. When at most `shared_votes` of the votes agree, the inputs
    share no pose that this test could keep (the majority is a chance group): the medoid
    of the voters alone keeps its pose, and everyone else is decided by `decide_unshared`
    (given why, for its reason). With `unshared_search` (called first: it makes the
    search compare shapes at any turn) a shape it turns is then a reference for the
    shapes after it like one it keeps (no input pose is more to trust than a turned one),
    so the collection follows the medoid from nearest shape to nearest shape."""
    n = len(search)
    voters = [j for j in range(n) if eligible[j]]
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
                votes[pair] = agree(*pair)
        report(progress + 0.15 * (j + 1) / n, f"comparing {j + 1} of {n}")
    majority = _majority(search, votes, nearest, voters)
    agreeing = sum(votes.values())
    unshared = decide_unshared is not None and bool(votes) and agreeing <= shared_votes * len(votes)
    trust_turned = unshared and unshared_search is not None
    if trust_turned:
        unshared_search()
    if unshared:
        majority = [_medoid(search, voters)]
        why = f"no input {what} is shared: {agreeing} of {len(votes)} pairs of nearest shapes agree"
        decide = lambda j, references: decide_unshared(j, references, why)  # noqa: E731
    decisions = {j: PoseDecision(start[j]) for j in majority}
    references_pool = list(decisions)  # shapes whose pose is trusted: kept ones only from the majority
    decisions.update({j: PoseDecision(start[j]) for j in range(n) if keep[j] and j not in decisions})
    # the next shape is the one closest to its nearest trusted shape (kept up to date as
    # the pool grows, not asked of every shape after every decision: issue 15)
    waiting = NearestInPool(search, references_pool, [r for r in range(n) if r not in decisions])
    while len(decisions) < n:
        j = waiting.closest()
        references = [(i, decisions[i].rotation) for i in search.nearest(j, references_pool, k)]
        decisions[j] = decide(j, references)
        if trust_turned or not decisions[j].changed:  # a turned shape's pose is a guess: no reference
            references_pool.append(j)
            waiting.join(j)
        else:
            waiting.leave(j)
        report(progress + 0.15 + 0.15 * len(decisions) / n, f"orienting {len(decisions)} of {n}")
    return [decisions[j] for j in range(n)]


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


@dataclass(frozen=True)
class PoseCheck:
    """What the pose check says of one shape: why its pose looks wrong ('' when it does
    not) and, when the evidence is as strong as the stages ask for a turn (a rotation
    fitting its nearest shapes `margin` times better, or its facing), the rotation that
    puts it right, its evidence and those shapes."""

    reason: str
    rotation: np.ndarray | None = None
    evidence: str = ""
    references: tuple[int, ...] = ()


def pose_outliers(search: PoseSearch, signatures: Signatures, rotations: Sequence[np.ndarray],
                  keep: Sequence[bool], settings: ConsensusSettings,
                  symmetry: AxisSymmetry | None = None, hollows: Hollows | None = None,
                  report: Progress | None = None) -> list[str]:
    """Why each shape's final pose looks wrong ('' when it does not): `pose_checks`."""
    return [check.reason for check in pose_checks(search, signatures, rotations, keep, settings, symmetry, hollows,
                                                  report)]


def pose_checks(search: PoseSearch, signatures: Signatures, rotations: Sequence[np.ndarray],
                keep: Sequence[bool], settings: ConsensusSettings,
                symmetry: AxisSymmetry | None = None, hollows: Hollows | None = None,
                report: Progress | None = None) -> list[PoseCheck]:
    """Each shape's final pose checked against its nearest shapes in their final poses
    (rotations relative to the base pose): it looks wrong when a rotation would
    fit them more than `margin` times better (a change of up: also `tilt_margin` times
    better than keeping its up), its top and bottom, its hollow or its facing disagree with theirs
    (signatures and hollows, the thresholds of the consensus; a weakly shared facing counts when the
    turn also fits them `facing_support` times better, `_faces_away`), its up lacks the symmetry the
    collection's up axes share (`symmetry`: scores above `symmetry_flag` and not clearly
    best of its axes: tilted, or on its side with nobody to fit), or it fits them over
    `outlier_factor` times worse than the collection's median shape does. The first and
    the facing come with the rotation that puts the shape right (`restore_flagged`)."""
    n = len(search)
    k = min(settings.neighbours, n - 1)
    trusted = [i for i in range(n) if not keep[i]] if sum(not x for x in keep) > k else list(range(n))
    references = [[(i, rotations[i]) for i in search.nearest(j, trusted, k)] for j in range(n)]
    costs = np.array([search.cost(j, rotations[j], references[j]) for j in range(n)])
    median = float(np.median(costs))
    kept = [" (its pose is kept by request)" if k_ else "" for k_ in keep]
    symmetry_ready = symmetry is not None and n >= settings.symmetry_shapes
    if symmetry_ready:
        symmetry.fit_profile(rotations, range(n))
    checks, report = [], report or no_progress
    for j in range(n):
        report((j + 1) / n, f"{j + 1} of {n}")
        nearest = tuple(i for i, _ in references[j])
        fit = _best_pose(search, symmetry, settings, j, references[j], rotations[j], refine=False)
        ratio = costs[j] / max(fit.cost, 1e-300)
        angle, coherence = signatures.facing_turn(j, rotations[j], references[j])
        if ratio > settings.margin:
            relative = fit.rotation @ rotations[j].T
            pose = "upside down" if relative[2, 2] < -0.5 else "on its side" if relative[2, 2] < 0.5 else "turned"
            checks.append(PoseCheck(f"{pose} relative to its {k} nearest shapes: {describe_rotation(relative)} it "
                                    f"would fit them {ratio:.1f}× better{kept[j]}", fit.rotation,
                                    f"fit {ratio:.1f}× better", nearest))
        elif (signatures.up_agreement(j, rotations[j], references[j]) < -settings.up_agreement
              and search.cost(j, _HALF_TURN_X @ rotations[j], references[j]) <= (1.0 + settings.tolerance) * costs[j]):
            checks.append(PoseCheck(f"upside down relative to its {k} nearest shapes (its top and bottom "
                                    f"match their bottom and top){kept[j]}"))
        elif hollows is not None and (opening := hollows.upside_down(j, rotations[j], references[j],
                                                                     settings.hollow_floor)) is not None:
            own, theirs = opening
            checks.append(PoseCheck(f"upside down relative to its {k} nearest shapes: its hollow opens "
                                    f"{_way(own)} ({own:+.2f}), theirs {_way(theirs)} ({theirs:+.2f}; the up "
                                    f"component of the hollow's opening, 1 = a hull all hollow open upwards)"
                                    f"{kept[j]}"))
        elif abs(angle) > settings.facing_angle and _faces_away(
                search.cost(j, yaw_rotation(angle) @ rotations[j], references[j]), costs[j], coherence, settings):
            checks.append(PoseCheck(f"faces {abs(angle):.0f}° away from its {k} nearest shapes{kept[j]}",
                                    yaw_rotation(angle) @ rotations[j], "face that way", nearest))
        elif symmetry_ready and (standing := standing_pose(search, symmetry, j, rotations[j], references[j],
                                                            settings)) is not None:
            fit, where, tilted = standing
            checks.append(PoseCheck(f"{'tilted' if tilted else 'on its side'} relative to the collection's up axes: "
                                    f"{describe_rotation(fit.rotation @ rotations[j].T)} it would stand on {where}"
                                    f"{kept[j]}"))
        elif costs[j] > settings.outlier_factor * median:
            checks.append(PoseCheck(f"fits its {k} nearest shapes {costs[j] / median:.1f}× worse than the "
                                    "collection's median shape does (an unusual shape, or a pose no turn fixes)"))
        else:
            checks.append(PoseCheck(""))
    return checks


def restore_flagged(search: PoseSearch, signatures: Signatures, names: Sequence[str], keep: Sequence[bool],
                    settings: ConsensusSettings, decisions: Sequence[PoseDecision],
                    symmetry: AxisSymmetry | None = None, hollows: Hollows | None = None,
                    report: Progress | None = None) -> list[PoseDecision]:
    """The last step of the consensus: the pose check (`pose_checks`) of the settled poses,
    whose references are every shape's nearest shapes in their final poses, and the turn
    it asks for made on a shape not kept (a shape that was decided against references
    in a wrong pose themselves: PSB cup 31 faces away from its neighbours but agreed with
    two of them one by one, so it kept its pose and was a reference for cup 26)."""
    checks = pose_checks(search, signatures, [d.rotation for d in decisions], keep, settings, symmetry, hollows,
                         report)
    restored = list(decisions)
    for j, check in enumerate(checks):
        if check.rotation is None or keep[j]:
            continue
        relative = check.rotation @ decisions[j].rotation.T
        restored[j] = _combined(decisions[j], PoseDecision(check.rotation, (
            f"{describe_rotation(relative)}: its {len(check.references)} nearest shapes in their final poses "
            f"({', '.join(names[i] for i in check.references)}) {check.evidence}")))
    return restored
