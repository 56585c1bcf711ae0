"""What the consensus steps share: each shape's decision (`PoseDecision`), what Prepare
measured of every shape (`ShapeEvidence`), the pairwise standing costs and the state the
steps fill in order (`ConsensusState`).

Evidence over the collection (`StandingCosts`): every shape is compared with its
`costs.references` most similar shapes (all the others in a collection of up to
`costs.references` + 1), not with its three nearest: for each pair, the Chamfer cost of the
shape standing on each of its six axis directions (its best turn about up on a 30° grid,
coarse samples) against the other in its pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ...base.progress import Progress, sub_range
from ...meshes.mesh import Mesh
from ..floors import FileFloors, Floor
from ..hollow import Hollows
from ..posesearch import PoseSearch
from ..rotations import TILTS, describe_rotation, up_rotation, yaw_rotation
from ..signature import Signatures
from ..symmetry import AxisSymmetry
from .settings import ConsensusSettings


@dataclass(frozen=True)
class PoseDecision:
    """The rotation consensus applied to one shape (after its up rotation) and why, and
    why its pose may still be wrong with the rotation that would put it right."""

    rotation: np.ndarray
    reason: str = ""  # empty when the shape kept its base pose
    #: the reasons of the single turns a combined decision is made of (`combined`)
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


HALF_TURN_X = TILTS[1]


HALF_TURN_Y = np.diag([-1.0, 1.0, -1.0])


#: the six axis directions a shape may stand on, as the index pairs of TILTS per line
LINES = {"z": (0, 1), "x": (2, 3), "y": (4, 5)}


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
        lines = {line: min(c[a], c[b]) for line, (a, b) in LINES.items()}
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


def step_progress(report: Progress, start: float, span: float, prefix: str) -> Progress:
    """`report` for one step: the step's fraction f as start + span · f, its message after `prefix`."""
    return lambda fraction, message: report(start + span * fraction, f"{prefix}{message}")


def convention_height(rotation: np.ndarray | None, convention: np.ndarray | None) -> float:
    """How far up (z) `rotation` takes the other common convention's up (`convention_up`):
    1 when it stands a shape as a file of that convention stands; 0 without either."""
    if rotation is None or convention is None:
        return 0.0
    return float((rotation @ convention)[2])


def on_convention_line(state: ConsensusState, rotation: np.ndarray | None) -> bool:
    """Whether `rotation` stands a shape on the line of the other common convention's up."""
    return abs(convention_height(rotation, state.convention)) > 0.99


def noted_kept(decision: PoseDecision) -> PoseDecision:
    """A kept shape's flag says its pose is kept by request."""
    if not decision.flag:
        return decision
    return PoseDecision(decision.rotation, decision.reason, decision.steps,
                        f"{decision.flag} (its pose is kept by request)", decision.flag_rotation)


def reference_names(names: Sequence[str], references: Sequence[tuple[int, np.ndarray]]) -> str:
    return ", ".join(names[i] for i, _ in references)


def combined(*stages: PoseDecision) -> PoseDecision:
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

