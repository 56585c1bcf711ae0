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

The steps, one module each: `up_lines` (1, up), `ends` (2, top and bottom), `facing` (3,
facing; 4, outliers); `state` holds what they share, `settings` their constants.
The policy as a user reads it: docs/user-guide.md, "What Prepare may turn, and why".

Each turn comes with its reason ("turned 90° about x: 9 of 10 shapes fit it 4.2× better
standing on its y axis (a file-convention turn)"); each flag with its reason and the
turn that would put it right.
"""

from __future__ import annotations

from typing import Sequence

from ...base.progress import Progress
from .ends import tops_and_bottoms
from .facing import facings, outlier_flags
from .settings import (ConsensusSettings, CostSettings, EndSettings, FacingSettings, FloorSettings, HollowSettings,
                       SignatureSettings, SymmetrySettings)
from .state import ConsensusState, PoseDecision, ShapeEvidence, StandingCosts, convention_up, noted_kept
from .up_lines import up_lines

__all__ = ["ConsensusSettings", "CostSettings", "EndSettings", "FacingSettings", "SignatureSettings",
           "SymmetrySettings", "HollowSettings", "FloorSettings", "PoseDecision", "ShapeEvidence",
           "StandingCosts", "ConsensusState", "consensus_rotations", "convention_up"]


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
    return [noted_kept(d) if k else d for d, k in zip(state.decisions, state.keep)]

