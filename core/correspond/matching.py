"""The data term's part in the groupwise rounds: one plug, chosen once from the settings
(`data_term_for(settings)`, `data_term.matching`), so the rounds (groupwise.py) hold no
branch of their own for it. Within one registration the data term is data_terms.py's.

* `ClosestPoints` (the thesis): every round registers the shapes as they are given.
* `FeatureMatching` (**beyond** the thesis; features.py): the first round checks feature
  matches against closest points and matches the collection by closest points when they
  fit too many shapes worse (`worse_fits`, `keeps_features`); from the groupwise round on,
  the template keeps the positions between turning lines of the shape it was made from and
  each shape compares them with its share of `feature_between` (`agreement_weights`), and
  template regions that merge on a shape are compared plainly there (`merged_regions`).

A data term is used in two steps: `begin` once per template, and the `RoundMatches` it
returns in every round (`tasks`: what the round's registrations are given beyond the
template; `run`: how they run) and at the end (`record`: what it decided, for the
correspondence's diagnostics)."""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np

from ..base.progress import Progress
from .features import (agreement_weights, checks_fit, checks_regions, keeps_features, merged_regions, uses_between,
                       uses_features, worse_fits)
from .pool import RegistrationRunner, RegistrationTask
from .registration import Registration
from .settings import CorrespondenceSettings

__all__ = ["DataTerm", "RoundMatches", "ClosestPoints", "FeatureMatching", "data_term_for"]


class RoundMatches(Protocol):
    """The data term of the rounds from one template."""

    def tasks(self, tasks: list[RegistrationTask], previous) -> tuple[list[RegistrationTask], str]:
        """The round's tasks as this data term registers them (`previous`: the last round's
        outcome, None in the first), and what it adds to the round's message ("" nothing)."""

    def run(self, round_index: int, tasks: list[RegistrationTask], runner: RegistrationRunner, report: Progress,
            label: str) -> list[Registration]:
        """The round's registrations of `tasks` from the round's template."""

    def record(self) -> dict:
        """What it decided, as fields of `CorrespondenceDiagnostics` (none: {})."""


class DataTerm(Protocol):
    """The data term of the groupwise rounds (module docstring)."""

    def begin(self, template: int, template_normals: np.ndarray) -> RoundMatches:
        """The data term of the rounds from the landmarks of shape `template` (their normals
        `template_normals`)."""


def data_term_for(settings: CorrespondenceSettings) -> DataTerm:
    """The data term the settings ask for (`data_term.matching`)."""
    return FeatureMatching(settings) if uses_features(settings) else ClosestPoints()


class ClosestPoints:
    """Closest (normal-compatible) points, the thesis's: nothing beyond the template."""

    def begin(self, template: int, template_normals: np.ndarray) -> RoundMatches:
        return _AsGiven()


class _AsGiven:
    def tasks(self, tasks, previous):
        return tasks, ""

    def run(self, round_index, tasks, runner, report, label):
        return runner.run(tasks, report, label)

    def record(self) -> dict:
        return {}


class FeatureMatching:
    """Feature-space matches (features.py), checked against closest points."""

    def __init__(self, settings: CorrespondenceSettings):
        self.settings = settings

    def begin(self, template: int, template_normals: np.ndarray) -> RoundMatches:
        return _FeatureRounds(self.settings, template, template_normals)


class _FeatureRounds:
    """Feature matches over the rounds from one template: the settings the rounds run with
    (closest points after a failed fit check), and what the rounds found."""

    def __init__(self, settings: CorrespondenceSettings, template: int, template_normals: np.ndarray):
        self.settings, self.template, self.template_normals = settings, template, template_normals
        self.between = None  # the template's positions between turning lines, from the groupwise round on
        self.shares = None  # (M,) each shape's share of feature_between (None: not compared)
        self.plain = None  # per shape, the template points matched plainly (merged_regions), from round 2 on
        self.worse = None  # (M,) bool: the shapes feature matches fitted worse in the first round (None: not run)

    def tasks(self, tasks: list[RegistrationTask], previous) -> tuple[list[RegistrationTask], str]:
        message = ""
        if previous is not None:
            names = len(previous.results)
            if self.between is None and uses_between(self.settings):
                # the template shape's own positions (its registration onto itself in the first
                # round): the population's mean at the first round's matches carries that
                # round's bias (it compares sides only), and measured worse (docs/results.md)
                self.between = previous.results[self.template].between
                self.shares = agreement_weights(self.between, [r.between for r in previous.results])
                message += f"; turning lines compared on {int(np.count_nonzero(self.shares))} of {names} shapes"
            if self.plain is None and checks_regions(self.settings):
                template_regions = previous.results[self.template].regions
                self.plain = [merged_regions(template_regions, self.template_normals, r.regions)
                              for r in previous.results]
                message += f"; regions merged on {sum(int(p.any()) for p in self.plain)} of {names} shapes"
        shaped = []
        for index, task in enumerate(tasks):
            settings = self.settings if self.shares is None else _with_between_share(self.settings, self.shares[index])
            shaped.append(replace(task, settings=settings, template_between=self.between,
                                  plain_points=None if self.plain is None else self.plain[index]))
        return shaped, message

    def run(self, round_index: int, tasks: list[RegistrationTask], runner: RegistrationRunner, report: Progress,
            label: str) -> list[Registration]:
        """From the second round on, the tasks as they are. The first round registers by
        feature matches and by closest points side by side, from the same template; when
        feature matches fit more than features.FALLBACK_SHARE of the shapes worse
        (features.worse_fits: the template collapsed onto part of them), the collection is
        matched by closest points from then on, and the result is the closest-point
        correspondence exactly. The template's own shape decides nothing (it fits itself
        either way)."""
        if round_index or not checks_fit(self.settings):
            return runner.run(tasks, report, label)
        closest = replace(self.settings, data_term=replace(self.settings.data_term, matching="closest"))
        closest_tasks = [replace(task, index=len(tasks) + task.index, name=f"{task.name} (closest points)",
                                 settings=closest, template_between=None) for task in tasks]
        both = runner.run(tasks + closest_tasks, report, f"{label}, feature matches checked against closest points")
        by_features, by_closest = both[:len(tasks)], both[len(tasks):]
        self.worse = worse_fits([r.residual for r in by_features], [r.residual for r in by_closest])
        self.worse[self.template] = False
        if keeps_features(self.worse):
            return by_features
        report(1.0, f"feature matches fit {int(self.worse.sum())} of {len(tasks)} shapes worse than closest points "
                    f"({', '.join(t.name for t, w in zip(tasks, self.worse) if w)}): closest points for the collection")
        self.settings = closest
        return by_closest

    def record(self) -> dict:
        found = {}
        if self.shares is not None:
            found["between_shares"] = self.shares
        if self.worse is not None:
            found["feature_fit_worse"] = self.worse
        if self.plain is not None:
            found["plain_shares"] = np.array([p.mean() for p in self.plain])
        return found


def _with_between_share(settings: CorrespondenceSettings, share: float) -> CorrespondenceSettings:
    """`settings` comparing positions between turning lines with `share` of `feature_between`
    (features.agreement_weights)."""
    data_term = settings.data_term
    return replace(settings, data_term=replace(data_term, feature_between=data_term.feature_between * share))
