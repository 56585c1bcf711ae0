"""Where the groupwise rounds start every shape's registration: one plug, chosen once from
the settings (`start_for(settings)`, `data_term.initialisation`), so the rounds
(groupwise.py) hold no branch of their own for it. The decisions and messages are start.py's;
this module only wraps them.

* `ClosestStart` (the thesis): every shape's registration starts from the template as it is.
* `SpectralStart` (**beyond** the thesis): from the template's landmarks carried to the
  shape by an intrinsic map (start.py `spectral_starts`), checked in the first round against
  the closest-point start (`checked_spectral_fits`); later rounds start every shape from its
  previous landmarks (a mean template of shapes in different poses is no start).
* `AutoStart`: one of the two for the whole collection, from how its shapes differ
  (`pose_evidence`, `chosen_start`).

A start is used in three steps: `chosen` once per collection (auto reads its evidence here;
the others are already chosen), `begin` once per template (the intrinsic maps from it, or
the closest-point lines), and the `Starter` it returns once per round (`registrations`)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Protocol, Sequence

import numpy as np

from ..base.progress import Progress, sub_range
from .pool import RegistrationRunner, RegistrationTask
from .registration import Registration
from .start import checked_spectral_fits, chosen_start, pose_evidence, signature_error, spectral_starts

__all__ = ["Start", "Starter", "RoundsSetup", "ClosestStart", "SpectralStart", "AutoStart", "start_for",
           "SPECTRAL_SHARE", "EVIDENCE_SHARE"]

#: with the spectral start, the intrinsic maps fill this share of the rounds' progress
SPECTRAL_SHARE = 0.2
#: with the automatic start, the evidence (the shapes' spectra) fills this share of it
EVIDENCE_SHARE = 0.05

#: `run(tasks, report, label)`: the round's registrations as the data term runs them (matching.py)
RunRound = Callable[[list, Progress, str], list]


@dataclass(frozen=True)
class RoundsSetup:
    """What a start needs of the rounds from one template: the shapes' names, the surfaces
    registered against (a dense shape's proxy), the shape the template came from, its
    landmarks (normalised frame), whether each shape lies in the frame as the collection
    does (Prepare did not flag its pose), the registration frame (`to_frame`) and the runner."""

    names: list[str]
    surfaces: Sequence
    template: int
    template_points: np.ndarray
    in_frame: list[bool]
    to_frame: Callable[[np.ndarray], np.ndarray]
    runner: RegistrationRunner


class Starter(Protocol):
    """The start of every round from one template."""

    def registrations(self, round_index: int, tasks: list[RegistrationTask], previous, run: RunRound,
                      report: Progress, label: str) -> tuple[list[Registration], list[str] | None]:
        """The round's registrations of `tasks` (from the template of the round; `previous`:
        the last round's outcome, None in the first) and, when this round decided it, the
        start each shape took ("spectral", "closest", "template" for the template's own
        shape; None: as before)."""


class Start(Protocol):
    """Where the shapes' registrations start (module docstring)."""

    kind: str  # "closest" or "spectral" ("auto" until `chosen`)
    reason: str  # why: "asked for", or the evidence auto read

    def chosen(self, meshes: Sequence, landmark_sets: Sequence[np.ndarray], template: int, runner: RegistrationRunner,
               report: Progress) -> tuple["Start", Progress]:
        """The start for this collection and the progress left for the rounds."""

    def begin(self, setup: RoundsSetup, report: Progress) -> tuple[Starter, Progress]:
        """The start of the rounds from `setup`'s template and the progress left for them."""


def start_for(settings) -> Start:
    """The start the settings ask for (`data_term.initialisation`)."""
    initialisation = settings.data_term.initialisation
    if initialisation == "auto":
        return AutoStart()
    return SpectralStart() if initialisation == "spectral" else ClosestStart()


@dataclass(frozen=True)
class ClosestStart:
    """Every shape's registration starts from the template as it is (the thesis)."""

    reason: str = "asked for"
    kind: str = "closest"

    def chosen(self, meshes, landmark_sets, template, runner, report) -> tuple[Start, Progress]:
        return self, report

    def begin(self, setup: RoundsSetup, report: Progress) -> tuple[Starter, Progress]:
        for index, name in enumerate(setup.names):
            if index != setup.template:
                report(0.0, f"{name}: closest-point start ({self.reason})")
        return _FromTemplate(), report


class _FromTemplate:
    """Every round registers the round's template as the data term runs it."""

    def registrations(self, round_index, tasks, previous, run: RunRound, report, label):
        return run(tasks, report, label), None


@dataclass(frozen=True)
class SpectralStart:
    """Every shape's registration starts from the template's landmarks carried by an
    intrinsic map (start.py), the closest-point start where that is not trusted."""

    reason: str = "asked for"
    kind: str = "spectral"

    def chosen(self, meshes, landmark_sets, template, runner, report) -> tuple[Start, Progress]:
        return self, report

    def begin(self, setup: RoundsSetup, report: Progress) -> tuple[Starter, Progress]:
        # a shape Prepare flagged (on its side, upside down, unusual) may not face as the others do
        starts, signatures = spectral_starts(setup.names, setup.surfaces, setup.template, setup.template_points,
                                             setup.runner, sub_range(report, 0.0, SPECTRAL_SHARE), setup.in_frame)
        chosen = "" if self.reason == "asked for" else f"; chosen for the collection: {self.reason}"
        for name, spectral in zip(setup.names, starts):
            if spectral is not None:
                report(SPECTRAL_SHARE, f"{name}: {spectral.message}{chosen}")
        return _FromSpectral(starts, signatures, setup), sub_range(report, SPECTRAL_SHARE, 1.0)


class _FromSpectral:
    """The rounds from spectral starts (`SpectralStart.begin`)."""

    def __init__(self, starts: list, signatures: np.ndarray | None, setup: RoundsSetup):
        self.starts, self.signatures, self.setup = starts, signatures, setup

    def registrations(self, round_index, tasks: list[RegistrationTask], previous, run: RunRound, report: Progress,
                      label: str) -> tuple[list[Registration], list[str] | None]:
        """The first round registers every shape from its spectral start (`starts[i]`, None
        for the template's own shape) beside the closest-point start, which replaces it
        where the spectrum was not trusted, the spectral fit is clearly worse or its
        landmarks do not match the template's signatures clearly better (start.py; said per
        shape). Later rounds start every shape from its previous round's landmarks, and the
        affines then act on those landmarks."""
        runner, starts = self.setup.runner, self.starts
        if previous is not None:
            return runner.run([replace(task, template=r.placed.points, template_normals=r.normals)
                               for task, r in zip(tasks, previous.registrations)], report, label), None
        to_frame = self.setup.to_frame
        spectral = [task if s is None or s.points is None else
                    replace(task, template=to_frame(s.points), template_normals=s.normals)
                    for task, s in zip(tasks, starts)]

        def signature_errors(index: int, registration: Registration) -> float:
            return signature_error(self.signatures, starts[index], registration.placed.points, to_frame)

        registrations, reasons = checked_spectral_fits(spectral, tasks, runner, report, label,
                                                       None if self.signatures is None else signature_errors)
        for task, reason in zip(tasks, reasons):
            if reason:
                report(1.0, f"{task.name}: {reason}")
        taken = ["template" if s is None else "spectral" if s.points is not None and not reason else "closest"
                 for s, reason in zip(starts, reasons)]
        return registrations, taken


@dataclass(frozen=True)
class AutoStart:
    """Closest points or the intrinsic start for the whole collection, from how its shapes
    differ (start.py `chosen_start`)."""

    reason: str = ""
    kind: str = "auto"

    def chosen(self, meshes, landmark_sets, template, runner, report) -> tuple[Start, Progress]:
        evidence = pose_evidence(meshes, landmark_sets, template, runner, sub_range(report, 0.0, EVIDENCE_SHARE))
        kind, reason = chosen_start(evidence)
        report(EVIDENCE_SHARE, f"{'intrinsic (spectral)' if kind == 'spectral' else 'closest-point'}"
                               f" start chosen for the collection: {reason}")
        return (SpectralStart(reason) if kind == "spectral" else ClosestStart(reason)), \
            sub_range(report, EVIDENCE_SHARE, 1.0)

    def begin(self, setup: RoundsSetup, report: Progress) -> tuple[Starter, Progress]:
        raise RuntimeError("the automatic start begins as the start it chose (`chosen`)")
