"""Step 1 of the consensus orientation (thesis §3.4), up (`up_lines`): the shapes whose up
line (z) fits most of their references best are the upright majority. A shape outside
it is stood on another axis of its file only when at least `costs.agreement` of its upright references fit it better standing on
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
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ...base.progress import Progress
from ..floors import FileFloors, Floor
from ..rotations import TILTS, describe_rotation
from ..symmetry import AxisSymmetry
from .settings import ConsensusSettings
from .state import ConsensusState, LANDS, LINES, PoseDecision, RESTING, convention_height, on_convention_line, step_progress


def up_lines(state: ConsensusState) -> None:
    """Step 1: file-convention turns of the up axis (module docstring) into `state.stood`.
    Also the floor the upright shapes' files share, if any (`floors.FileFloors`), and
    each shape's floor turn and resting flag (`state.floor_turns`, `state.resting`)."""
    n, floors = state.n, state.evidence.floors
    report = step_progress(state.report, 0.2, 0.15, "up axes: ")
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
    clear = [j for j in stands if on_convention_line(state, state.stood[j].rotation)
             and (state.floor is None or _side(state.floor_turns[j]) is not None)]
    if (len(clear) < state.settings.costs.convention_files
            or len(clear) < state.settings.costs.convention_share * len(stands)):
        return  # too few, or files turned onto other sides as often: turns, not one convention
    convention_end = next(tilt for tilt in TILTS if convention_height(tilt, state.convention) > 0.99)
    files = f"{len(clear)} files of the collection are clearly saved in it"
    for j, decision in enumerate(state.stood):
        if j in clear:
            state.convention_files.append(j)
        elif (decision.flag.startswith("may be on its side") and on_convention_line(state, decision.flag_rotation)
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
    line = next(ln for ln, ends in LINES.items() if side in ends)
    a, b = LINES[line]
    costs = np.array([state.costs.standing_costs(j, identity, i, identity) for i in references]).reshape(-1, 6)
    ratio = float(np.median(np.minimum(costs[:, 0], costs[:, 1])
                            / np.maximum(np.minimum(costs[:, a], costs[:, b]), 1e-300))) if len(costs) else 0.0
    stand = TILTS[side]
    words = f"{LANDS}, standing on its {line} axis"
    # the turn that lands it is the other common convention's (its file's +y up among z-up
    # files): two facts of the file agree, which a pose differing from the references'
    # (a sitting dog among standing ones fits them better lying) does not outweigh
    convention = convention_height(stand, state.convention) > 0.99
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
    a, b = LINES[line]
    ca, cb = float(np.median(costs[:, a])), float(np.median(costs[:, b]))
    cheaper = a if ca <= cb else b
    if max(ca, cb) >= settings.ends.flip_margin * min(ca, cb):
        return cheaper, True
    for d in (a, b):
        if convention_height(TILTS[d], convention) > 0.99:
            return d, False
    return cheaper, False

