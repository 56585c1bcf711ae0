"""Reading older files: every table of what changed since files were written, and the code
that reads their older layouts as today's settings, in one place. A file written today
reads without any of it; dropping support for a kind of old file is an edit here.

Settings classes point to their tables here through class attributes, which
`settings.settings_from_dict` applies (`read_as_today`):

- `FIELDS_MOVED`: a flat name of before → the dotted place the option moved to when
  options were grouped by subsystem (`settings.group`), e.g. "gamma" →
  "stiffness.gamma". Files written before the grouping
  record them flat, and option dicts may still name them flat (the add-on's panel
  options do, so that Extra Settings naming an option nested override the panel's).
- `FIELDS_REMOVED`: a field taken out → why. A file that records one reads as if it had
  not, silently: the removal kept the behaviour the file's run had, or the field never
  said what the file holds. Settings given now that name one are refused, saying why.
- `FIELDS_ADDED_LATER`: a field added after files were written → the value the runs of
  those files used, where it differs from today's default.

Older layouts of the files themselves:

- settings as key/value string arrays (`<key>_keys`, `<key>_values`: str() or repr() of
  each value), before settings were one JSON string (`key_value_settings`);
- model files of that time (`old_model_settings`): Prepare's options flat beside the
  fit's, the meshing settings as numbers by key in `deform_keys` / `deform_values`.
"""

from __future__ import annotations

import ast
from typing import Mapping, Sequence

from .errors import SettingsError
from .npzfile import ArraySpec, validate_arrays

__all__ = ["read_as_today", "is_key_value_layout", "key_value_settings", "key_value_data", "nested_data",
           "old_model_settings", "CORRESPONDENCE_MOVED", "CORRESPONDENCE_REMOVED", "DATA_TERM_ADDED_LATER",
           "RUN_OPTIONS_REMOVED", "OLD_MODEL_PREPARE_NAMES", "OLD_MODEL_DEFORM_INTEGERS"]


# ---------------------------------------------------------------------------- tables
def _moved(group_name: str, names: tuple[str, ...], prefix: str = "") -> dict[str, str]:
    """{flat name of before: its dotted place} of the options now in one group: `prefix` +
    name before, group.name now."""
    return {f"{prefix}{name}": f"{group_name}.{name}" for name in names}


#: CorrespondenceSettings.FIELDS_MOVED: its options were flat until they were grouped by
#: subsystem; the outlier options lost their prefixes then
CORRESPONDENCE_MOVED = {
    **_moved("stiffness", ("gamma", "k_neighbours", "alpha_start", "alpha_end", "alpha_steps")),
    **_moved("data_term", ("bidirectional_weight", "normal_max_angle", "matching", "feature_between",
                           "initialisation", "distance_weights", "snap_to_vertices")),
    **_moved("iterations", ("update_template", "tolerance", "max_iterations_per_alpha", "max_iterations", "ridge")),
    "outlier_mad_factor": "outliers.residual_mad_factor", "outlier_min_ratio": "outliers.residual_min_ratio",
    **_moved("outliers", ("max_residual", "max_scale_ratio", "loo_mad_factor", "loo_min_ratio", "loo_variance")),
}

#: CorrespondenceSettings.FIELDS_REMOVED, by their flat names of before: the research knobs
#: of feature matches, fixed at the values every file that records them ran with
#: and the group of groupwise refinement after NICP with its flat names of before (files
#: that ran it load as today's settings; its record stays in the diagnostics)
CORRESPONDENCE_REMOVED = {
    **dict.fromkeys(
        ("feature_normals", "feature_tilt", "feature_up", "feature_up_width", "feature_stiffness", "feature_trim",
         "feature_merged_regions", "feature_samples", "feature_fit_check", "feature_fallback_share"),
        "a research knob of feature matches, now a constant of core/correspond/features.py"),
    **dict.fromkeys(
        ("refinement", "refine", *(f"refine_{name}" for name in (
            "iterations", "compactness", "spread", "regulariser", "normals", "smooth_fields", "sigma", "step",
            "max_move", "alignment", "tolerance"))),
        "groupwise refinement after NICP (refine population) was removed: it won no class beyond run-to-run "
        "noise (docs/results.md, Correspondence across classes); files that ran it still load"),
}

#: DataTermSettings.FIELDS_ADDED_LATER: files written before these fields existed ran with
#: the turning-line feature off and every registration started from the template as it is
DATA_TERM_ADDED_LATER = {"feature_between": 0.0, "initialisation": "closest"}

#: FitSettings.FIELDS_REMOVED: how a run was scheduled, which model files recorded among
#: the model's settings; the same settings make the same model whatever ran them
RUN_OPTIONS_REMOVED = dict.fromkeys(
    ("jobs", "scheduler"),
    "it says how a run is scheduled, not what it makes: an option of the run (--jobs, --scheduler; "
    "core.app.fit_settings.RunOptions), never recorded in a file")

#: the Prepare options model files of the key/value layout record flat beside the fit's
#: own (nested under "prepare" since)
OLD_MODEL_PREPARE_NAMES = ("n_landmarks", "up_axis", "align", "scale", "centre", "seed")

#: the meshing settings those files record as float64 numbers by key: these are integers
OLD_MODEL_DEFORM_INTEGERS = ("n_stages", "k_blend")


# ---------------------------------------------------------------------------- names of before
def read_as_today(cls, data: Mapping, path: str, recorded: bool) -> dict:
    """`data` for the settings class `cls` under today's names: a file's (`recorded`) fields
    added later at the values its run used (`FIELDS_ADDED_LATER`), removed fields left out
    (`FIELDS_REMOVED`; refused when given now) and flat names of before in their nested
    places (`FIELDS_MOVED`). `path`: where `cls` sits in the settings read, for messages."""
    if recorded:
        data = {**getattr(cls, "FIELDS_ADDED_LATER", {}), **data}
    return _moved_into_place(cls, _without_removed(cls, data, path, recorded), path)


def _moved_into_place(cls, data: Mapping, path: str) -> dict:
    """`data` with every option named by a flat name of before (`cls.FIELDS_MOVED`: flat
    name → dotted place) moved to its nested place. An option named both ways takes its
    nested value: the add-on's panel options are flat, and Extra Settings that name an
    option nested override them as they would flat."""
    moved = getattr(cls, "FIELDS_MOVED", {})
    flat = {name: value for name, value in data.items() if name in moved}
    if not flat:
        return dict(data)
    result = {name: value for name, value in data.items() if name not in moved}
    for name, value in flat.items():
        *parents, leaf = moved[name].split(".")
        target = result
        for parent in parents:
            inner = target.get(parent, {})
            if not isinstance(inner, Mapping):
                raise SettingsError(f"{path}.{name}" if path else name,
                                    f"cannot be given flat beside {parent!r} given as settings")
            target[parent] = dict(inner)  # a copy: the caller's data stays as it was
            target = target[parent]
        target.setdefault(leaf, value)  # named both ways: today's nested name wins
    return result


def _without_removed(cls, data: Mapping, path: str, recorded: bool) -> Mapping:
    """`data` without the fields `cls.FIELDS_REMOVED` names (name → why it went). A file
    (`recorded`) that records one is read as if it had not; settings given now that name
    one are refused, naming the option and why it went."""
    removed = getattr(cls, "FIELDS_REMOVED", {})
    named = [name for name in data if name in removed]
    if named and not recorded:
        raise SettingsError(f"{path}.{named[0]}" if path else named[0], f"was removed: {removed[named[0]]}")
    return {name: value for name, value in data.items() if name not in removed}


# ---------------------------------------------------------------------------- layouts of before
def nested_data(dotted: Mapping) -> dict:
    """Plain data with dotted names ("deform.gamma": 2.0) as nested objects
    ({"deform": {"gamma": 2.0}})."""
    data: dict = {}
    for key, value in dotted.items():
        *parents, name = key.split(".")
        target = data
        for parent in parents:
            target = target.setdefault(parent, {})
        target[name] = value
    return data


def key_value_data(keys: Sequence[str], values: Sequence[str]) -> dict:
    """Plain data from the key/value strings of a file written before settings were one
    JSON string: values were str() or repr() of scalars ("800", "'z'", "consensus",
    "None"); dotted keys ("deform.gamma") name nested settings."""
    data = {}
    for key, text in zip(keys, values):
        try:
            data[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            data[key] = text  # str() of a word, e.g. consensus
    return nested_data(data)


def is_key_value_layout(arrays: Mapping, key: str = "settings") -> bool:
    """Whether a loaded file records its settings `key` as key/value strings (the layout of
    before) rather than one JSON string."""
    return key not in arrays and f"{key}_keys" in arrays


def key_value_settings(arrays: Mapping, label: str, key: str = "settings") -> dict:
    """The plain data of the settings a file records as `<key>_keys` / `<key>_values`
    string arrays (empty: none recorded). A malformed record is a ModelFileError starting
    with `label`."""
    keys, values = f"{key}_keys", f"{key}_values"
    validate_arrays(arrays, {keys: ArraySpec("U", ("S",)), values: ArraySpec("U", ("S",))}, label)
    return key_value_data(arrays[keys].tolist(), arrays[values].tolist())


#: a model file of the key/value layout: its meshing settings, numbers by key
_OLD_MODEL_DEFORM_SPEC = {"deform_keys": ArraySpec("U", ("K",)), "deform_values": ArraySpec("f", ("K",))}


def old_model_settings(arrays: Mapping, label: str) -> dict:
    """The FitSettings, as plain data, of a model file of the key/value layout: its
    Prepare options (flat then) nested under "prepare", the meshing settings read from
    their numbers (`OLD_MODEL_DEFORM_INTEGERS` as integers). A malformed record is a
    ModelFileError starting with `label`."""
    data = key_value_settings(arrays, label)
    validate_arrays(arrays, _OLD_MODEL_DEFORM_SPEC, label)
    nested = {key: value for key, value in data.items() if key not in OLD_MODEL_PREPARE_NAMES}
    nested["prepare"] = {key: value for key, value in data.items() if key in OLD_MODEL_PREPARE_NAMES}
    nested["deform"] = {key: int(value) if key in OLD_MODEL_DEFORM_INTEGERS else float(value)
                        for key, value in zip(arrays["deform_keys"].tolist(), arrays["deform_values"].tolist())}
    return nested
