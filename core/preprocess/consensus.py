"""Consensus orientation of a collection (thesis §3.4; step 3 of `prepare_collection`):
a policy a user can predict. The given up axis and every shape's pose as given are
trusted; Prepare turns a shape only

(a) by a file-convention turn: its own up is clearly another axis of its file (a quarter
    turn about x or y; a half turn when its top and bottom are clearly the other way
    round), or
(b) about the up axis, to line its facing up with the collection's where the shapes
    evidently face different ways,

each on evidence that holds over the collection, never on a feature that itself varies
across the class. A shape that may be upside down, on its side or facing away, but not
clearly so, is flagged with its reason and a suggested turn (`PoseDecision.flag`,
`flag_rotation`) and left as given; the user turns it with Turn Flagged
(`collection.PreparedCollection.turn_flagged`). Kept shapes (`keep`) are never turned,
only flagged.

The decisions are steps over one `ConsensusState` (what Prepare measured of each shape,
`ShapeEvidence`; the settings; each step's decisions), run in order by
`consensus_rotations`; the settings below are fields of `ConsensusSettings` by group.

Evidence over the collection (`StandingCosts`): every shape is compared with its
`costs.references` most similar shapes (all the others in a collection of up to
`costs.references` + 1), not with its three nearest: for each pair, the Chamfer cost of the
shape standing on each of its six axis directions (its best turn about up on a 30° grid,
coarse samples) against the other in its pose.

1. Up (`up_lines`): the shapes whose up line (z) fits most of their references best are
   the upright majority. A shape outside it is stood on another axis of its file only
   when at least `costs.agreement` of its upright references fit it better standing on
   that same axis line (by `costs.margin`), the median improvement is at least
   `costs.margin`, and the new up has no worse symmetry than its own
   (`symmetry.AxisSymmetry`: a bowl among jugs fits them better on its side, but its up
   is its axis of symmetry); or when that axis has the symmetries the collection's shapes
   share about their up clearly more than its up does (`symmetry.gap`,
   `symmetry.ratio`: a squat closed mug on its side fits upright mugs about as well as
   standing, but its axis of revolution lies flat) and the references fit it no worse
   standing on it. Which end of that line is up follows the costs when they tell the two
   ends apart by `ends.flip_margin`, else the other common file convention (a y-up file
   among z-up ones stands on its +y; a z-up file among y-up ones on its +z); step 2 then
   checks it like every shape. Weaker evidence (median improvement above `costs.margin`):
   flagged "may be on its side".
   The floor (`floors.FileFloors`, `floor.tolerance`): when most upright shapes' files
   put their lowest point at one height, a shape resting there as given is where its
   author put it: flagged, never stood on another axis (a rearing cat among standing ones
   fits them better lying); a shape resting there only after one quarter turn of its file
   about its origin (and no other turn) was saved turned: stood so, the costs asked only
   not to object clearly (by `costs.margin`; else flagged), or not asked at all when that
   turn is the other common convention's. Step 1 records each shape's floor turn and
   whether it rests on the floor as given for step 2.
   Both conventions in one collection (`_mixed_conventions`): when at least
   `costs.convention_files` shapes are clearly stood on the other convention's up line,
   and at least `costs.convention_share` of the shapes stood on a side are, a shape
   flagged "may be on its side" on that line is stood too, and step 2 keeps each of them
   on the end that convention puts up unless the costs clearly turn it over. Where so many
   files lie as read that the upright shapes are no majority, they still set the up when
   they and the shapes evidently lying on the other convention's up line are
   (`_upright_with_convention`).
2. Top and bottom (`tops_and_bottoms`): a shape is turned over only when the collection
   agrees on top and bottom and the shape clearly does not:
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
3. Facing (`facings`): turns about up only, by the Chamfer cost (`_CostFacing`: where the
   inputs share a facing, a turn of more than `facing.angle` that at least
   `costs.agreement` of its `costs.references` settled shapes fit `costs.margin` times
   better; half of them: a flag "may face another way") and by the facing signature
   (`_SignatureFacing`, `signature.Signatures`, exact odd moments: a shared facing
   differing by more than `facing.angle`), with `_settle`'s majority: the poses most
   shapes share are the collection's and are never changed. Inputs turned about up at
   random share no facing (at most `facing.shared_facing` of the votes agree): one
   shape's facing is then the collection's, and the others are turned to it (beyond the
   thesis, issue 13).
4. Last (`outlier_flags`), a shape fitting its nearest shapes `outlier_factor` times
   worse than the median shape does is flagged (an unusual shape, or a pose no turn
   fixes).

Each turn comes with its reason ("turned 90° about x: 9 of 10 shapes fit it 4.2× better
standing on its y axis (a file-convention turn)"); each flag with its reason and the
turn that would put it right.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..meshes.mesh import Mesh
from ..base.progress import Progress, sub_range
from .floors import FileFloors, Floor
from .hollow import Hollows
from .posesearch import NearestInPool, PoseSearch
from .rotations import TILTS, describe_rotation, up_rotation, yaw_rotation
from .signature import Signatures
from .symmetry import AxisSymmetry

__all__ = ["ConsensusSettings", "CostSettings", "EndSettings", "FacingSettings", "SignatureSettings",
           "SymmetrySettings", "HollowSettings", "FloorSettings", "PoseDecision", "ShapeEvidence",
           "StandingCosts", "ConsensusState", "consensus_rotations", "convention_up"]


@dataclass(frozen=True)
class CostSettings:
    """The Chamfer-cost votes of steps 1-3: how many surface samples, how many references
    each shape asks, and how many of them must ask for a turn, by how much."""

    #: surface samples per shape for the Chamfer costs
    points: int = 600
    #: shapes each shape is compared with for a turn of its up, its ends or its facing
    #: (all others in a smaller collection)
    references: int = 10
    #: share of the references that must ask for a turn of up, ends or facing
    agreement: float = 0.8
    #: cost ratio (its pose / the turned pose) a reference's vote for a turn needs
    margin: float = 1.5
    #: shapes clearly stood on the other common convention's up line (by these votes or
    #: their symmetry) that show a collection mixes the two file conventions
    convention_files: int = 2
    #: the share of the shapes stood on a side (by these votes or their symmetry) that must
    #: stand on the other convention's up line for that: a collection's files may also lie
    #: on their sides (PSB Cup: 5 of 20), and hand turns fall on either side line alike
    convention_share: float = 0.75


@dataclass(frozen=True)
class EndSettings:
    """Which end is up by the costs (step 2, and the end of a shape stood on another axis
    in step 1)."""

    #: median cost ratio a turn-over by the costs alone needs (and that tells the ends of
    #: a shape stood on another axis apart)
    flip_margin: float = 3.0
    #: ... or with the odd moments agreeing (as strongly, over the collection) this one
    flip_support: float = 2.0


@dataclass(frozen=True)
class FacingSettings:
    """Turns about up (step 3) and the nearest shapes of the pose check (step 4)."""

    #: nearest settled shapes a shape's facing is compared with (step 3), and its fit
    #: measured against (step 4)
    neighbours: int = 3
    #: grid step of the turn about z, degrees
    yaw_step: float = 15.0
    #: relative cost within which an exact axis rotation beats a refined turn
    snap: float = 0.03
    #: relative Chamfer cost increase a turn by the facing signature may cost at most
    tolerance: float = 0.1
    #: facing difference (degrees) above which a shape is turned about z
    angle: float = 30.0
    #: share of the facing votes at or below which the collection shares no input facing
    shared_facing: float = 0.4
    #: facing difference (degrees) above which a shape is turned when no facing is shared
    unshared_angle: float = 0.5
    #: share of the Chamfer votes at or below which the collection shares no input pose
    shared_pose: float = 0.4
    #: cost ratio above which a shape is turned about up when no input pose is shared
    unshared_margin: float = 1.1


@dataclass(frozen=True)
class SignatureSettings:
    """The exact odd-moment signatures (`signature.Signatures`) of top and bottom (step 2)
    and of facing (step 3)."""

    #: Legendre polynomials in height in the facing signature
    order: int = 5
    #: signature coherence above which facings are compared, and below whose negative a
    #: reference's top and bottom oppose a shape's (0..1)
    coherence: float = 0.5


@dataclass(frozen=True)
class SymmetrySettings:
    """Which axis is up by the symmetries the collection's up axes share
    (`symmetry.AxisSymmetry`, step 1)."""

    #: shapes needed for the symmetry test of a stand on another axis
    shapes: int = 5
    #: lowest spread (log units) of a symmetry feature in the up profile
    spread: float = 0.3
    #: score difference (its up − another axis) above which that axis has the collection's
    #: up symmetry clearly more than its up
    gap: float = 0.4
    #: ... and the factor by which the other axis must score better
    ratio: float = 1.3


@dataclass(frozen=True)
class HollowSettings:
    """Top and bottom by which way a shape's hollows open (`hollow.Hollows`, step 2)."""

    #: voxel grid cells along a shape's longest side for its hollows
    grid: int = 40
    #: up component of a hollow's opening vector above which it tells top from bottom
    opening: float = 0.1
    #: cost ratio (turned over / its pose) up to which a hollow turns a shape over
    cost: float = 1.5
    #: share of the telling hollows that must open the same way for it to be the collection's
    agreement: float = 0.6


@dataclass(frozen=True)
class FloorSettings:
    """The floor the collection's files share (`floors.FileFloors`, steps 1 and 2)."""

    #: a shape's lowest point within this many times the median size (RMS radius) of the
    #: upright shapes' shared floor rests on it
    tolerance: float = 0.15
    #: lowest points within this many times the median size of each other (at least three
    #: and a third of the upright shapes) make a floor where fewer than half rest on one
    exact: float = 0.02


@dataclass(frozen=True)
class ConsensusSettings:
    """The constants of the consensus orientation (module docstring), by subsystem. Plain
    constants of the method: not a user option, never saved in a file."""

    costs: CostSettings = field(default_factory=CostSettings)
    ends: EndSettings = field(default_factory=EndSettings)
    facing: FacingSettings = field(default_factory=FacingSettings)
    signature: SignatureSettings = field(default_factory=SignatureSettings)
    symmetry: SymmetrySettings = field(default_factory=SymmetrySettings)
    hollows: HollowSettings = field(default_factory=HollowSettings)
    floor: FloorSettings = field(default_factory=FloorSettings)
    #: a shape fitting its nearest shapes this many times worse than the median is flagged
    outlier_factor: float = 3.0


@dataclass(frozen=True)
class PoseDecision:
    """The rotation consensus applied to one shape (after its up rotation) and why, and
    why its pose may still be wrong with the rotation that would put it right."""

    rotation: np.ndarray
    reason: str = ""  # empty when the shape kept its base pose
    #: the reasons of the single turns a combined decision is made of (`_combined`)
    steps: tuple[str, ...] = ()
    #: why the pose may be wrong, empty when it looks right (the shape is left as it is)
    flag: str = ""
    #: the rotation (from the base pose) that Turn Flagged applies; None: no suggestion
    flag_rotation: np.ndarray | None = field(default=None, compare=False)
    #: a stand on another axis whose end nothing told (step 2 confirms the end or flags it)
    end_guessed: bool = False

    @property
    def changed(self) -> bool:
        return bool(self.reason)


_HALF_TURN_X = TILTS[1]
_HALF_TURN_Y = np.diag([-1.0, 1.0, -1.0])
#: the six axis directions a shape may stand on, as the index pairs of TILTS per line
_LINES = {"z": (0, 1), "x": (2, 3), "y": (4, 5)}
RESTING = "left as given: it rests on the floor the collection's files share, where its author put it"
LANDS = "it rests on the floor the collection's files share only once turned so"
_YAWS = np.stack([yaw_rotation(a) for a in np.arange(0.0, 360.0, 30.0)])


def convention_up(up_axis: str) -> np.ndarray | None:
    """The base-frame direction a file written in the other common convention has as its
    up (given z: a y-up file's +y; given y: a z-up file's +z; otherwise none)."""
    other = {"z": np.array([0.0, 1.0, 0.0]), "y": np.array([0.0, 0.0, 1.0])}.get(up_axis)
    return None if other is None else up_rotation(up_axis) @ other


@dataclass(frozen=True)
class ShapeEvidence:
    """What Prepare measures of every shape in its base pose (the given up along z) for
    the consensus: the pose search (Chamfer costs, nearest shapes), the odd-moment
    signatures, the axis symmetry, the hollows and the files' floors."""

    search: PoseSearch
    signatures: Signatures
    symmetry: AxisSymmetry | None = None
    hollows: Hollows | None = None
    floors: FileFloors | None = None

    @classmethod
    def of(cls, meshes: Sequence[Mesh], up: np.ndarray, settings: ConsensusSettings, seed: int,
           report: Progress) -> "ShapeEvidence":
        """Measured on `meshes` (pose proxies) turned by `up`; `report` goes 0 to 0.2."""
        base = [up] * len(meshes)
        search = PoseSearch.of(meshes, base, settings.costs.points, seed,
                               sub_range(report, 0.0, 0.15, "pose search: "))
        signatures = Signatures(meshes, base, settings.signature.order, sub_range(report, 0.15, 0.17))
        symmetry = AxisSymmetry.of(search, meshes, base, seed, settings.symmetry.spread,
                                   sub_range(report, 0.17, 0.18))
        hollows = Hollows.of(meshes, base, settings.hollows.grid, seed, sub_range(report, 0.18, 0.2))
        return cls(search, signatures, symmetry, hollows, FileFloors.of(meshes, up))


class StandingCosts:
    """Pairwise standing costs of a collection (module docstring): for shape j in pose R_j
    against shape i in pose R_i, the cost of j standing on each of its six axis
    directions (TILTS, after R_j), each at its best turn about up on a 30° grid."""

    def __init__(self, search: PoseSearch, settings: ConsensusSettings):
        self.search = search
        self.count = min(settings.costs.references, len(search) - 1)
        self._costs: dict[tuple[int, int, bytes], np.ndarray] = {}

    def references(self, j: int, pool: Sequence[int]) -> list[int]:
        """The shapes of `pool` (j excluded) most like shape j at any axis rotation."""
        return self.search.nearest(j, pool, self.count)

    def standing_costs(self, j: int, pose: np.ndarray, i: int, reference_pose: np.ndarray) -> np.ndarray:
        """(6,): the cost of shape j standing on each axis direction of its `pose`, best
        turn about up, against shape i in `reference_pose`."""
        key = (j, i, (reference_pose.T @ pose).tobytes())
        if key not in self._costs:
            relative = reference_pose.T @ _YAWS[:, None] @ TILTS[None] @ pose  # (12, 6, 3, 3)
            costs = self.search.coarse_pair_costs(j, i, relative.reshape(-1, 3, 3)).reshape(len(_YAWS), len(TILTS))
            self._costs[key] = costs.min(axis=0)
        return self._costs[key]

    def side_ratio(self, j: int, i: int) -> tuple[float, str]:
        """Shapes j and i as given: j's cost standing on its up line (z, the better end)
        over its cost on its better side line, and that line ("x" or "y")."""
        identity = np.eye(3)
        c = self.standing_costs(j, identity, i, identity)
        lines = {line: min(c[a], c[b]) for line, (a, b) in _LINES.items()}
        side = min(("x", "y"), key=lambda line: lines[line])
        return lines["z"] / max(lines[side], 1e-300), side


@dataclass
class ConsensusState:
    """One collection's consensus orientation in progress: the evidence (`ShapeEvidence`,
    the pairwise `StandingCosts`), the shapes' names, which poses are kept, the settings,
    and the decisions each step (module docstring) has made so far, read by the steps
    after it."""

    evidence: ShapeEvidence
    costs: StandingCosts
    names: Sequence[str]
    #: per shape: its pose is kept by request (flagged, never turned)
    keep: list[bool]
    #: False: nobody is turned (align "none" or "pca"), every step only flags
    may_turn: bool
    #: per shape: never turned, only flagged (kept, or nobody may turn)
    frozen: list[bool]
    settings: ConsensusSettings
    #: the base-frame up of a file of the other common convention (`convention_up`)
    convention: np.ndarray | None
    report: Progress
    #: step 1: the floor the upright shapes' files share, if any; per shape the TILTS
    #: index of the one turn of its file after which it rests on it (`_floor_turn`) and
    #: whether it rests on it as given (`FileFloors.keeps`); x or y axis whose symmetry
    #: is the collection's up's (`_symmetric_side`); each shape's stand (`up_lines`)
    floor: Floor | None = None
    floor_turns: list[int | None] = field(default_factory=list)
    resting: list[bool] = field(default_factory=list)
    symmetric_sides: list[tuple[str, float, float] | None] = field(default_factory=list)
    stood: list[PoseDecision] = field(default_factory=list)
    #: step 1: the shapes stood on the other common convention's up in a collection that
    #: evidently mixes the two conventions (`_mixed_conventions`); step 2 keeps their end
    convention_files: list[int] = field(default_factory=list)
    #: step 2: after the turn-overs (`tops_and_bottoms`)
    ends: list[PoseDecision] = field(default_factory=list)
    #: step 3: after the turns about up (`facings`)
    faced: list[PoseDecision] = field(default_factory=list)
    #: step 4: the steps combined, outliers flagged (`outlier_flags`)
    decisions: list[PoseDecision] = field(default_factory=list)

    @classmethod
    def of(cls, evidence: ShapeEvidence, names: Sequence[str], keep: Sequence[bool], settings: ConsensusSettings,
           report: Progress, up_axis: str = "z", may_turn: bool = True) -> "ConsensusState":
        keep = [bool(k) for k in keep]
        return cls(evidence, StandingCosts(evidence.search, settings), names, keep, may_turn,
                   [k or not may_turn for k in keep], settings, convention_up(up_axis), report)

    @property
    def search(self) -> PoseSearch:
        return self.evidence.search

    @property
    def n(self) -> int:
        return len(self.evidence.search)

    @property
    def symmetry_profile(self) -> bool:
        """Whether the symmetry test of a stand on another axis applies."""
        return self.evidence.symmetry is not None and self.n >= self.settings.symmetry.shapes


def consensus_rotations(evidence: ShapeEvidence, names: Sequence[str], keep: Sequence[bool],
                        settings: ConsensusSettings, report: Progress, up_axis: str = "z",
                        may_turn: bool = True) -> list[PoseDecision]:
    """The pose decision of every shape: the steps of the module docstring, in order, over
    one `ConsensusState`. `may_turn` False: nobody is turned (align "none" or "pca"),
    every step only flags. `evidence.floors`: where the files put their lowest points (a
    shape resting on the collection's floor as given is flagged, never turned over or
    onto a side)."""
    state = ConsensusState.of(evidence, names, keep, settings, report, up_axis, may_turn)
    for step in (up_lines, tops_and_bottoms, facings, outlier_flags):
        step(state)
    return [_noted_kept(d) if k else d for d, k in zip(state.decisions, state.keep)]


def _part(report: Progress, start: float, span: float, prefix: str) -> Progress:
    """`report` for one step: the step's fraction f as start + span · f, its message after `prefix`."""
    return lambda fraction, message: report(start + span * fraction, f"{prefix}{message}")


def up_lines(state: ConsensusState) -> None:
    """Step 1: file-convention turns of the up axis (module docstring) into `state.stood`.
    Also the floor the upright shapes' files share, if any (`floors.FileFloors`), and
    each shape's floor turn and resting flag (`state.floor_turns`, `state.resting`)."""
    n, floors = state.n, state.evidence.floors
    report = _part(state.report, 0.2, 0.15, "up axes: ")
    state.symmetric_sides = _symmetric_sides(state)
    upright = _upright_majority(state, report)
    state.stood = [PoseDecision(np.eye(3))] * n
    state.floor_turns, state.resting = [None] * n, [False] * n
    if len(upright) < 2 or (2 * len(upright) <= n and not _upright_with_convention(state, upright)):
        return  # no up shared by most shapes: nothing to line up with
    state.floor = None if floors is None else floors.shared(upright, state.settings.floor.tolerance,
                                                               state.settings.floor.exact)
    state.floor_turns = [_floor_turn(floors, j, state.floor) for j in range(n)]
    state.resting = [floors is not None and floors.keeps(j, state.floor) for j in range(n)]
    sides = [_side(turn) for turn in state.floor_turns]
    upright = [j for j in upright if sides[j] is None]
    for j in range(n):
        if sides[j] is not None:
            state.stood[j] = _floor_stand(state, j, state.costs.references(j, upright), sides[j])
    for j in range(n):
        if j not in upright and sides[j] is None:
            report(0.5 + (j + 1) / (2 * n), f"standing {state.names[j]}")
            decision = _stand(state, j, upright)
            if decision is not None:
                state.stood[j] = decision
    _mixed_conventions(state)


def _convention_line(state: ConsensusState) -> str | None:
    """The base-frame axis line ("x" or "y") of the other common convention's up, if any."""
    if state.convention is None:
        return None
    return "xyz"[int(np.argmax(np.abs(state.convention)))]


def _lying_on(state: ConsensusState, j: int, line: str) -> bool:
    """Whether shape j as given evidently lies with its up along `line`: that side axis
    has the collection's up symmetry (`_symmetric_side`), or most of its references fit it
    better standing on that line by `costs.margin`."""
    if state.symmetric_sides[j] is not None:
        return state.symmetric_sides[j][0] == line
    pairs = [state.costs.side_ratio(j, i) for i in state.costs.references(j, list(range(state.n)))]
    votes = sum(ratio > state.settings.costs.margin and side == line for ratio, side in pairs)
    return 2 * votes > len(pairs)


def _upright_with_convention(state: ConsensusState, upright: Sequence[int]) -> bool:
    """A collection mixing the two common file conventions may have no upright majority
    (a third of its files lying when read with the given up): the upright shapes are then
    still the collection's up when, together with the shapes evidently lying on the other
    convention's up line (at least `costs.convention_files` of them), they are most of
    the collection. Each lying shape is then stood, or not, on the evidence of the
    upright ones alone, as in any collection (`_stand`)."""
    line = _convention_line(state)
    if line is None:
        return False
    lying = [j for j in range(state.n) if j not in upright and _lying_on(state, j, line)]
    return len(lying) >= state.settings.costs.convention_files and 2 * (len(upright) + len(lying)) > state.n


def _convention_height(rotation: np.ndarray | None, convention: np.ndarray | None) -> float:
    """How far up (z) `rotation` takes the other common convention's up (`convention_up`):
    1 when it stands a shape as a file of that convention stands; 0 without either."""
    if rotation is None or convention is None:
        return 0.0
    return float((rotation @ convention)[2])


def _on_convention_line(state: ConsensusState, rotation: np.ndarray | None) -> bool:
    """Whether `rotation` stands a shape on the line of the other common convention's up."""
    return abs(_convention_height(rotation, state.convention)) > 0.99


def _mixed_conventions(state: ConsensusState) -> None:
    """Files of both common conventions in one collection (a y-up file among z-up ones):
    when at least `costs.convention_files` shapes are clearly stood on the other
    convention's up line (where the files share a floor: landing on it so), and at least
    `costs.convention_share` of all the shapes stood on a side are, the collection
    evidently holds files saved in it. That is
    evidence no single shape carries: a shape that step 1 only flagged "may be on its
    side" on that same line (its symmetry or most references say so, another measure
    objecting) is stood there too, and every such shape stands on the end that
    convention puts up (+y of a y-up file) unless its costs clearly tell the other
    (step 2). A shape resting on the files' floor as given, or kept, is not moved."""
    if state.convention is None:
        return
    stands = [j for j, d in enumerate(state.stood) if d.changed and not d.flag]
    # where the files share a floor, a file saved in the other convention also lands on it
    # once turned back: a stand the costs alone made (a sitting dog saved upside down,
    # stood on a side) is no sign of a convention there
    clear = [j for j in stands if _on_convention_line(state, state.stood[j].rotation)
             and (state.floor is None or _side(state.floor_turns[j]) is not None)]
    if (len(clear) < state.settings.costs.convention_files
            or len(clear) < state.settings.costs.convention_share * len(stands)):
        return  # too few, or files turned onto other sides as often: turns, not one convention
    convention_end = next(tilt for tilt in TILTS if _convention_height(tilt, state.convention) > 0.99)
    files = f"{len(clear)} files of the collection are clearly saved in it"
    for j, decision in enumerate(state.stood):
        if j in clear:
            state.convention_files.append(j)
        elif (decision.flag.startswith("may be on its side") and _on_convention_line(state, decision.flag_rotation)
              and not state.frozen[j] and not state.resting[j]):
            evidence = decision.flag.removeprefix("may be on its side: ")
            state.stood[j] = PoseDecision(
                convention_end, f"{describe_rotation(convention_end)}: {evidence}; the other common file "
                                f"convention's up ({files}), a file-convention turn", end_guessed=True)
            state.convention_files.append(j)


def _symmetric_sides(state: ConsensusState) -> list[tuple[str, float, float] | None]:
    """Per shape, its side axis that has the collection's up symmetry clearly more than
    its up (`_symmetric_side`; the profile fitted to every shape as given), else None."""
    if not state.symmetry_profile:
        return [None] * state.n
    state.evidence.symmetry.fit_profile([np.eye(3)] * state.n, list(range(state.n)))
    return [_symmetric_side(state.evidence.symmetry, j, state.settings) for j in range(state.n)]


def _upright_majority(state: ConsensusState, report: Progress) -> list[int]:
    """The shapes that most of their references (all shapes) fit better standing on
    their up line than on a side, and whose side axes do not have the collection's up
    symmetry."""
    n, upright = state.n, []
    for j in range(n):
        report((j + 1) / (2 * n), f"{j + 1} of {n}")
        references = state.costs.references(j, list(range(n)))
        ratios = [state.costs.side_ratio(j, i)[0] for i in references]
        lying = np.mean([r > state.settings.costs.margin for r in ratios] or [0.0]) > 0.5
        if not lying and state.symmetric_sides[j] is None:
            upright.append(j)
    return upright


def _stand(state: ConsensusState, j: int, upright: Sequence[int]) -> PoseDecision | None:
    """Shape j (outside the upright majority, no floor turn) stood on the axis line its
    `upright` references or its symmetry ask for, or flagged "may be on its side" on
    weaker evidence; None when nothing asks."""
    settings, identity, symmetric_side = state.settings, np.eye(3), state.symmetric_sides[j]
    references = state.costs.references(j, upright)
    pairs = [state.costs.side_ratio(j, i) for i in references]
    ratios, lines = np.array([ratio for ratio, _ in pairs]), [line for _, line in pairs]
    line = symmetric_side[0] if symmetric_side is not None else max(set(lines), key=lines.count)
    votes = sum(r > settings.costs.margin and ln == line for r, ln in zip(ratios, lines))
    median = float(np.median(ratios))
    d, told = _standing_end(np.array([state.costs.standing_costs(j, identity, i, identity) for i in references]),
                            line, settings, state.convention)
    stand = TILTS[d]
    by_cost = votes >= settings.costs.agreement * len(references) and median >= settings.costs.margin
    symmetric = (not state.symmetry_profile
                 or state.evidence.symmetry.score(j, stand) <= state.evidence.symmetry.score(j, identity))
    words = []
    if by_cost or median > settings.costs.margin:
        words.append(f"{votes} of {len(references)} shapes fit it better standing on its {line} axis "
                     f"({median:.1f}× at the median)")
    if symmetric_side is not None:
        words.append(f"its {line} axis has the symmetry the collection's shapes have about their up "
                     f"(score {symmetric_side[1]:.1f} against {symmetric_side[2]:.1f} for its up)")
    clear = (by_cost and symmetric) or (symmetric_side is not None and median >= 1.0)
    if not words:
        return None
    if clear and not state.frozen[j] and not state.resting[j]:
        return PoseDecision(stand, f"{describe_rotation(stand)}: {' and '.join(words)}, a file-convention turn",
                            end_guessed=not told)
    why = "" if symmetric else "; its own up has the collection's symmetry"
    if state.resting[j]:
        why += f"; {RESTING}"
    return PoseDecision(identity, flag=f"may be on its side: {' and '.join(words)}{why}", flag_rotation=stand)


def _floor_turn(floors: FileFloors | None, j: int, floor: Floor | None) -> int | None:
    """The TILTS index of the turn of shape j's file (about its origin) after which it
    rests on the collection's floor while it does not as given (`FileFloors.lands`),
    when exactly one turn does (two: a coincidence of where its origin is); else None.
    1 is the half turn (step 2's), 2-5 the quarter turns onto a side (step 1's)."""
    if floors is None or floor is None:
        return None
    turns = [d for d in range(1, len(TILTS)) if floors.lands(j, TILTS[d], floor)]
    return turns[0] if len(turns) == 1 else None


def _side(turn: int | None) -> int | None:
    """A floor turn onto a side (step 1), not over (step 2)."""
    return turn if turn is not None and turn >= 2 else None


def _floor_stand(state: ConsensusState, j: int, references: Sequence[int], side: int) -> PoseDecision:
    """Shape j stood on the side its file's floor is on (`_floor_turn`) unless its
    upright references fit it clearly better as given (by `costs.margin`; in a class that
    varies in pose they may: a rearing cat fits standing cats better lying). Evidence
    that disagrees so is flagged, the floor's stand suggested."""
    identity, margin = np.eye(3), state.settings.costs.margin
    line = next(ln for ln, ends in _LINES.items() if side in ends)
    a, b = _LINES[line]
    costs = np.array([state.costs.standing_costs(j, identity, i, identity) for i in references]).reshape(-1, 6)
    ratio = float(np.median(np.minimum(costs[:, 0], costs[:, 1])
                            / np.maximum(np.minimum(costs[:, a], costs[:, b]), 1e-300))) if len(costs) else 0.0
    stand = TILTS[side]
    words = f"{LANDS}, standing on its {line} axis"
    # the turn that lands it is the other common convention's (its file's +y up among z-up
    # files): two facts of the file agree, which a pose differing from the references'
    # (a sitting dog among standing ones fits them better lying) does not outweigh
    convention = _convention_height(stand, state.convention) > 0.99
    if (ratio * margin >= 1.0 or convention) and not state.frozen[j]:
        why = ", the other common file convention's up" if ratio * margin < 1.0 else ""
        return PoseDecision(stand, f"{describe_rotation(stand)}: {words}{why}, a file-convention turn")
    if ratio * margin < 1.0:
        words += f", but its upright references fit it {1.0 / max(ratio, 1e-300):.1f}× better as given (median)"
    return PoseDecision(identity, flag=f"may be on its side: {words}", flag_rotation=stand)


def _symmetric_side(symmetry: AxisSymmetry, j: int, settings: ConsensusSettings) -> tuple[str, float, float] | None:
    """(axis, its score, its up's score) when shape j's x or y axis has the symmetry of the
    collection's up profile clearly more than its up (`symmetry.gap`, `symmetry.ratio`;
    `AxisSymmetry.axis_scores`, 0 = the collection's typical up), else None."""
    scores = symmetry.axis_scores(j, np.eye(3))
    other = 1 + int(np.argmin(scores[1:]))
    if (scores[0] - scores[other] > settings.symmetry.gap
            and scores[0] > settings.symmetry.ratio * scores[other]):
        return "xy"[other - 1], float(scores[other]), float(scores[0])
    return None


def _standing_end(costs: np.ndarray, line: str, settings: ConsensusSettings,
                  convention: np.ndarray | None) -> tuple[int, bool]:
    """(TILTS index, told) of the end of `line` a shape stands on: the end the references'
    median costs (rows of `costs`) prefer by `ends.flip_margin` (told), else the file
    convention's end when it lies on the line, else the cheaper one (both guesses)."""
    a, b = _LINES[line]
    ca, cb = float(np.median(costs[:, a])), float(np.median(costs[:, b]))
    cheaper = a if ca <= cb else b
    if max(ca, cb) >= settings.ends.flip_margin * min(ca, cb):
        return cheaper, True
    for d in (a, b):
        if _convention_height(TILTS[d], convention) > 0.99:
            return d, False
    return cheaper, False


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
    votes = _EndVotes.of(state, poses, _part(state.report, 0.35, 0.15, "tops and bottoms: "))
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
    flipped = min((_HALF_TURN_X @ poses[j], _HALF_TURN_Y @ poses[j]),
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
    if _convention_height(pose, state.convention) > 0.99:
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
    state.faced = [_combined(a, b) for a, b in zip(first, second)]


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
                                              f"({_names(state.names, references)}) fit {ratio:.1f}× better ({why})")
        share = f"{each} of {len(references)} shapes fit it {ratio:.1f}× better turned about up"
        if ratio <= least or 2 * each <= len(references) or _angle(turn) <= settings.facing.angle:
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
                                       f"{len(references)} nearest shapes ({_names(state.names, references)})"
                                       + (f" ({why})" if why else ""))


def outlier_flags(state: ConsensusState) -> None:
    """Step 4: the steps' decisions combined (`_combined`) into `state.decisions`; a shape
    not flagged yet that fits its nearest shapes (final poses) over `outlier_factor`
    times worse than the median shape does is flagged, with no turn."""
    decisions = [_combined(*stages) for stages in zip(state.stood, state.ends, state.faced)]
    state.decisions = decisions
    n, search = state.n, state.search
    if n < 3:
        return
    report = _part(state.report, 0.86, 0.02, "checking the poses: ")
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


def _noted_kept(decision: PoseDecision) -> PoseDecision:
    """A kept shape's flag says its pose is kept by request."""
    if not decision.flag:
        return decision
    return PoseDecision(decision.rotation, decision.reason, decision.steps,
                        f"{decision.flag} (its pose is kept by request)", decision.flag_rotation)


def _angle(rotation: np.ndarray) -> float:
    """The angle of a rotation, degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def _names(names: Sequence[str], references: Sequence[tuple[int, np.ndarray]]) -> str:
    return ", ".join(names[i] for i, _ in references)


def _combined(*stages: PoseDecision) -> PoseDecision:
    """One decision for the stages: the last one's rotation (each starts from the one
    before), the reasons of those that turned the shape, the first flag (its suggested
    rotation followed by the later stages' turns)."""
    reasons = [step for d in stages if d.reason for step in (d.steps or (d.reason,))]
    flagged = next((d for d in stages if d.flag), None)
    flag, flag_rotation = "", None
    if flagged is not None:  # its suggested turn, after what the later stages turned
        flag = flagged.flag
        if flagged.flag_rotation is not None:
            flag_rotation = flagged.flag_rotation @ flagged.rotation.T @ stages[-1].rotation
    if reasons and np.trace(stages[-1].rotation) > 1.0 + 2.0 * np.cos(np.radians(1.0)):
        return PoseDecision(np.eye(3), flag=flag, flag_rotation=flag_rotation)  # turned there and back
    reason = "; then ".join(reasons)
    if len(reasons) > 1:
        reason = f"{describe_rotation(stages[-1].rotation)} in all ({reason})"
    return PoseDecision(stages[-1].rotation, reason, tuple(reasons), flag, flag_rotation)


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
    # the pool grows, not asked of every shape after every decision: issue 15)
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


