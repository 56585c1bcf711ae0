"""The fit's stages, prepare → correspond → fit, and the one decision of which of them run.

A fit (or a correspondence, `last="correspond"`) may start from an earlier stage's output
(`Offered`): a prepared collection (a prepared .npz, Blender's "<name> Prepared"
collection) or a correspondence (a correspondence .npz, the one inside the scene's
model). `plan_stages` decides, for the settings asked for, which offered output is reused
and which stages run, and says why in one line (`StagePlan.reason`) that the CLI prints
and Blender shows. The CLI and Blender only describe what they were offered; the rules
live here:

| offered | its recorded settings | its shapes | stages that run |
|---|---|---|---|
| nothing | | | prepare, correspond, fit |
| prepared collection, found | the Prepare settings asked for | the inputs as they are now | correspond, fit (it is reused) |
| prepared collection, found | other Prepare settings, or none recorded | | prepare, correspond, fit |
| prepared collection, found | the settings asked for | changed since | prepare, correspond, fit |
| correspondence, found, on a reused prepared collection | the Prepare, correspondence and template settings asked for | the prepared shapes | fit (both reused) |
| correspondence, found, on a reused prepared collection | other correspondence settings or template, or none recorded | | correspond, fit (the prepared collection is kept) |
| prepared collection, given (the CLI's SOURCE) | any, or none | | correspond, fit (its settings win) |
| correspondence, given | any, or none | | fit (its settings win) |

"Found" outputs (Blender's) are a cache: reused only when they are exactly what the
settings would make now. "Given" ones (a file the user named) are used as they are: the
settings they record win over the defaults, an option the user gave that contradicts them
is a `SettingsConflict` (the stage cannot run again without its inputs), and an old file
that records none is taken as made with the settings asked for. Whether an output's shapes
are the inputs as they are now is the caller's check (`Offered.current`: Blender compares
the objects, which is scene reading); `same_shapes` compares a model's training shapes with
a prepared collection's.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, is_dataclass, replace
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..preprocess.collection import PREPARED_FORMAT, PreparedCollection, PrepareSettings
from ..correspond import CORRESPONDENCE_FORMAT, Correspondence, CorrespondenceSettings
from ..correspond.posing import apply_pose
from ..base.errors import ShapeGenError
from ..base.npzfile import read_format
from .fit_settings import FitSettings

__all__ = ["STAGES", "FILE_STAGES", "Offered", "StagePlan", "SettingsConflict", "plan_stages", "file_stage",
           "read_offered", "same_shapes"]

STAGES = ("prepare", "correspond", "fit")
#: the stage whose output a file of each format holds
FILE_STAGES = {PREPARED_FORMAT: "prepare", CORRESPONDENCE_FORMAT: "correspond"}
_DOING = {"prepare": "preparing", "correspond": "corresponding", "fit": "fitting"}
_MADE = {"prepare": "prepared", "correspondence": "corresponded"}


class SettingsConflict(ShapeGenError, ValueError):
    """An option given explicitly that contradicts the settings a given file records.
    `group` ("prepare" or "correspondence") and `option` name it; the CLI names its flag."""

    def __init__(self, group: str, option: str, value, recorded, label: str):
        self.group, self.option, self.value, self.recorded, self.label = group, option, value, recorded, label
        super().__init__(f"{option} {value} conflicts with {label}, {_MADE[group]} with {option} {recorded}; "
                         "leave it out to use the file's")


@dataclass(frozen=True)
class Offered:
    """An earlier stage's output a run may start from, as the caller found or was given it.

    `stage`: "prepare" (a prepared collection) or "correspond" (a correspondence).
    `label` names it in the plan's reason ("prepared.npz", "'vases Prepared'").
    `prepare`, `correspondence`, `template`: the settings it records (None: not recorded;
    `template` is the correspondence template that was asked for, None: the medoid).
    `given`: the user named it as the source (used as it is, see the module docstring).
    `current(prepared)`: whether its shapes are the inputs as they are now (None: they are);
    a correspondence's gets the prepared collection reused under it (an `Offered`).
    `data`: the caller's own handle on it (a loaded file, Blender's collection), untouched."""

    stage: str
    label: str
    prepare: PrepareSettings | None = None
    correspondence: CorrespondenceSettings | None = None
    template: str | None = None
    given: bool = False
    current: Callable[["Offered | None"], bool] | None = None
    data: Any = None


@dataclass(frozen=True)
class StagePlan:
    """What runs: `run`, the stages in order; `reused`, the offered outputs it starts from
    (earliest first); `settings`, the settings the result records (a given file's own
    where it records them); `reason`, one line saying why."""

    run: tuple[str, ...]
    reused: tuple[Offered, ...]
    settings: FitSettings
    reason: str

    def reused_stage(self, stage: str) -> Offered | None:
        """The reused output of `stage`, if any."""
        return next((o for o in self.reused if o.stage == stage), None)

    @property
    def reused_labels(self) -> str:
        """"'vases Prepared' and the correspondence of model 'vases'" ("" when nothing is reused)."""
        return " and ".join(o.label for o in self.reused)


def plan_stages(requested: FitSettings, offered: Sequence[Offered] = (), given: Mapping[str, Mapping] | None = None,
                last: str = "fit") -> StagePlan:
    """The stages up to `last` that run for `requested` settings and the `offered` outputs
    (rules: the module docstring). `given`: the options set explicitly
    ({"prepare": {name: value}, "correspondence": {...}}, e.g. on the command line), checked
    against a given file's recorded settings. Found outputs are tried in the order offered
    (newest first); a correspondence only on top of a reused prepared collection."""
    wanted = STAGES[:STAGES.index(last) + 1]
    named = next((o for o in offered if o.given), None)
    if named is not None:
        return _plan_given(requested, named, given or {}, wanted)
    prepared, why_not = _first_reusable(requested, [o for o in offered if o.stage == "prepare"], None)
    if prepared is None:
        return StagePlan(wanted, (), requested, f"{_doing(wanted)}: {why_not or 'no earlier result to reuse'}")
    if last == "prepare":
        return StagePlan((), (prepared,), requested, f"reusing {prepared.label}: same shapes and Prepare settings")
    corresponded, why_not = _first_reusable(requested, [o for o in offered if o.stage == "correspond"], prepared)
    if corresponded is None:
        then = f"; {_doing(wanted[1:])}" + (f": {why_not}" if why_not else "")
        return StagePlan(wanted[1:], (prepared,), requested,
                         f"reusing {prepared.label}: same shapes and Prepare settings{then}")
    then = f"; {_doing(wanted[2:])} only" if wanted[2:] else ""
    return StagePlan(wanted[2:], (prepared, corresponded), requested,
                     f"reusing {prepared.label} and {corresponded.label}: same shapes, Prepare and correspondence "
                     f"settings{then}")


def _first_reusable(requested: FitSettings, candidates: Sequence[Offered], prepared: Offered | None):
    """(the first found candidate that can be reused, None) or (None, why the first one
    cannot: None when there is none). Settings are compared before `current` is asked (the
    caller's check may read every mesh)."""
    first_reason = None
    for candidate in candidates:
        reason = _settings_differ(requested, candidate)
        if reason is None and not (candidate.current is None or candidate.current(prepared)):
            reason = (f"{candidate.label} is out of date: its shapes changed since" if candidate.stage == "prepare"
                      else f"{candidate.label} was made from other shapes")
        if reason is None:
            return candidate, None
        first_reason = first_reason or reason
    return None, first_reason


def _settings_differ(requested: FitSettings, candidate: Offered) -> str | None:
    """Why `candidate`'s recorded settings are not those asked for (None: they are):
    its Prepare settings, and for a correspondence its own settings and template."""
    checks = [("Prepare", candidate.prepare, requested.prepare)]
    if candidate.stage == "correspond":
        checks.append(("correspondence", candidate.correspondence, requested.correspondence))
    for name, recorded, wanted in checks:
        if recorded is None:
            return f"{candidate.label} records no {name} settings"
        if recorded != wanted:
            return f"{candidate.label} was made with other {name} settings ({_differences(recorded, wanted)})"
    if candidate.stage == "correspond" and candidate.template != requested.template:
        return (f"{candidate.label} was made on template {candidate.template or 'the medoid'}, "
                f"now {requested.template or 'the medoid'}")
    return None


def _plan_given(requested: FitSettings, named: Offered, given: Mapping[str, Mapping], wanted: tuple) -> StagePlan:
    """The plan for a file the user named: used as it is, its recorded settings winning."""
    settings = replace(requested, prepare=_recorded_or_asked("prepare", named.prepare, requested.prepare,
                                                             given.get("prepare", {}), named.label))
    groups = ["Prepare"]
    if named.stage == "correspond":
        settings = replace(settings, correspondence=_recorded_or_asked(
            "correspondence", named.correspondence, requested.correspondence, given.get("correspondence", {}),
            named.label))
        groups.append("correspondence")
    unrecorded = [g for g, s in zip(groups, (named.prepare, named.correspondence)) if s is None]
    how = (f"it records no {' or '.join(unrecorded)} settings: taken as asked" if unrecorded
           else "with the settings it records")
    run = wanted[STAGES.index(named.stage) + 1:]
    return StagePlan(run, (named,), settings, f"using {named.label} as given ({how})"
                     + (f"; {_doing(run)}" if run else ""))


def _recorded_or_asked(group: str, recorded, asked, given: Mapping, label: str):
    """A given file's recorded settings of `group` (`asked` when it records none); an
    option in `given` that contradicts them is a SettingsConflict."""
    if recorded is None:
        return asked
    leaves = _leaves(recorded)
    for name, value in given.items():
        if name in leaves and value != leaves[name]:
            raise SettingsConflict(group, name, value, leaves[name], label)
    return recorded


def _leaves(settings, prefix: str = "") -> dict:
    """Every field of (possibly nested) settings by its dotted path ("seed",
    "iterations.max_iterations")."""
    found = {}
    for f in fields(settings):
        value = getattr(settings, f.name)
        if is_dataclass(value):
            found.update(_leaves(value, f"{prefix}{f.name}."))
        else:
            found[f"{prefix}{f.name}"] = value
    return found


def _differences(recorded, wanted, shown: int = 3) -> str:
    """"seed 0, now 1; iterations.max_iterations 5, now 30": the fields that differ (the
    first `shown`), by their dotted paths."""
    had, now = _leaves(recorded), _leaves(wanted)
    names = [n for n in now if had.get(n) != now[n]]
    text = "; ".join(f"{n} {had.get(n)}, now {now[n]}" for n in names[:shown])
    return text + (f"; and {len(names) - shown} more" if len(names) > shown else "")


def _doing(stages: Sequence[str]) -> str:
    """"preparing, corresponding and fitting"."""
    words = [_DOING[s] for s in stages]
    if not words:
        return "nothing to run"
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} and {words[-1]}"


def same_shapes(model, prepared) -> bool:
    """Whether a fitted model's training shapes are exactly a prepared collection's: the
    same names in order, faces, vertices (to 1e-5 of the shape's size; the model's are in
    the model frame, so each prepared mesh is first moved by the pose the correspondence
    gave its shape, core/correspond/posing.py) and transforms back to the inputs (to 1e-6;
    the correspondence's, to the prepared frame), so its correspondence is one of those shapes."""
    if model.names != prepared.names:
        return False
    corr = model.correspondence
    for mesh, shape, transform, pose in zip(model.meshes, prepared.shapes, corr.transforms, corr.model_poses):
        size = max(float(np.ptp(mesh.vertices, axis=0).max()), 1e-12)
        if (mesh.vertices.shape != shape.mesh.vertices.shape or not np.array_equal(mesh.faces, shape.mesh.faces)
                or np.abs(mesh.vertices - apply_pose(pose, shape.mesh.vertices)).max() > 1e-5 * size
                or np.abs(transform - shape.transform.matrix).max() > 1e-6 * max(1.0, np.abs(transform).max())):
            return False
    return True


def file_stage(path) -> tuple[str, str | None]:
    """(the format tag of the ShapeGen file at `path`, the stage whose output it holds or
    None), read without loading the file's other arrays."""
    file_format = read_format(path)
    return file_format, FILE_STAGES.get(file_format)


def read_offered(path, stage: str) -> Offered:
    """The prepared (`stage` "prepare") or correspondence ("correspond") file at `path`,
    named by the user: a given `Offered` with the settings it records, `data` the loaded
    PreparedCollection or Correspondence."""
    if stage == "prepare":
        prepared = PreparedCollection.load(path)
        return Offered("prepare", str(path), prepare=prepared.settings, given=True, data=prepared)
    correspondence = Correspondence.load(path)
    return Offered("correspond", str(path), prepare=correspondence.prepare, correspondence=correspondence.settings,
                   given=True, data=correspondence)
