"""Typed settings: frozen dataclasses that check themselves and travel as one JSON string.

A settings class derives from `Settings` and declares each option with `option(...)`: its
help text, its command-line flag and its allowed values live on the field, so the checks
here, the command line (`cli_common.add_settings_options`) and the saved JSON all read
the same declaration. Nested settings (e.g. `FitSettings.prepare`) are dataclass fields
and nest in the JSON. A subsystem's options inside one settings class are a `group` field
(e.g. `CorrespondenceSettings.stiffness`): nested in the JSON, offered on the command line
with their parent's options; `Settings.FIELDS_MOVED` reads data that still names them flat
(files written before they were grouped, the add-on's option dicts).
"""

from __future__ import annotations

import ast
import json
import types
from dataclasses import MISSING, asdict, field, fields, is_dataclass
from typing import Any, Mapping, Sequence, Union, get_args, get_origin, get_type_hints

from .errors import ModelFileError, ShapeGenError
from .npzfile import ArraySpec, validate_arrays

__all__ = ["Settings", "SettingsError", "option", "group", "is_group", "check_fields", "settings_from_dict",
           "settings_from_json", "settings_to_json", "nested_data", "legacy_settings", "recorded_settings"]


class SettingsError(ShapeGenError, ValueError):
    """A setting outside its allowed values. `option` names it (a field name, or a dotted
    path into nested settings); the message is "<prefix><option> <problem>"."""

    def __init__(self, option: str, problem: str, prefix: str = ""):
        super().__init__(f"{prefix}{option} {problem}")
        self.option = option
        self.problem = problem
        self.prefix = prefix


def option(default: Any = MISSING, help: str = "", *, flag: str | None = None, choices: Sequence | None = None,
           minimum: float | None = None, above: float | None = None, default_factory: Any = MISSING):
    """A settings field: `help` (one line), `flag` (the command-line option, if any),
    `choices` (allowed values), `minimum` (value >= minimum) or `above` (value > above)."""
    metadata = {"help": help, "flag": flag, "choices": tuple(choices) if choices is not None else None,
                "minimum": minimum, "above": above}
    return field(default=default, default_factory=default_factory, metadata=metadata)


def group(cls, help: str = ""):
    """A settings field holding one subsystem's options (settings class `cls`, at its
    defaults unless given): nested in the JSON like any nested settings, and part of its
    parent's command-line options (`cli_common.add_settings_options` offers the group's
    flags with the parent's), unlike nested settings of their own such as
    `FitSettings.prepare`, which a command adds by themselves."""
    metadata = {"help": help, "flag": None, "choices": None, "minimum": None, "above": None, "group": True}
    return field(default_factory=cls, metadata=metadata)


def is_group(f) -> bool:
    """Whether dataclass field `f` was declared with `group`."""
    return bool(f.metadata.get("group"))


def _type_text(hint) -> str:
    if get_origin(hint) in (Union, types.UnionType):
        return " or ".join(_type_text(h) for h in get_args(hint))
    return {int: "an integer", float: "a number", str: "text", bool: "true or false",
            type(None): "none"}.get(hint, getattr(hint, "__name__", str(hint)))


def _has_type(value, hint) -> bool:
    if get_origin(hint) in (Union, types.UnionType):
        return any(_has_type(value, h) for h in get_args(hint))
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def check_fields(settings) -> None:
    """Check every field of a settings dataclass against its type and `option` limits;
    raise SettingsError naming the first one that is off."""
    hints = get_type_hints(type(settings))
    for f in fields(settings):
        value, meta = getattr(settings, f.name), f.metadata
        if not _has_type(value, hints[f.name]):
            raise SettingsError(f.name, f"must be {_type_text(hints[f.name])}, got {value!r}")
        if value is None or is_dataclass(value):
            continue
        choices = meta.get("choices")
        if choices is not None and value not in choices:
            raise SettingsError(f.name, f"{value!r}; choose from {', '.join(map(str, choices))}", prefix="unknown ")
        if meta.get("minimum") is not None and not value >= meta["minimum"]:
            raise SettingsError(f.name, f"must be at least {meta['minimum']}, got {value!r}")
        if meta.get("above") is not None and not value > meta["above"]:
            raise SettingsError(f.name, f"must be greater than {meta['above']}, got {value!r}")


def settings_to_json(settings) -> str:
    """One JSON object of a settings dataclass (nested settings as nested objects)."""
    return json.dumps(asdict(settings))


def settings_from_dict(cls, data: Mapping, path: str = "", recorded: bool = False):
    """A settings dataclass `cls` from plain data (parsed JSON): nested settings from
    nested objects, missing fields at their defaults. Unknown names and invalid values
    raise SettingsError; an error of nested settings names the option by its dotted path
    ("deform.final_alpha"). Options named by their flat names of before (`cls.FIELDS_MOVED`)
    are read into their nested places. `recorded`: the data is what a file recorded, so a
    field the file predates takes the value its run used (`FIELDS_ADDED_LATER` of the class
    that holds it), not today's default."""
    label = path or cls.__name__
    if not isinstance(data, Mapping):
        raise SettingsError(label, f"must be a JSON object, got {data!r}")
    if recorded:
        data = {**getattr(cls, "FIELDS_ADDED_LATER", {}), **data}
    data = _moved_into_place(cls, _without_removed(cls, data, path, recorded), path)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise SettingsError(label, f"has no option {unknown[0]!r} (options: {', '.join(sorted(known))})")
    hints = get_type_hints(cls)
    if recorded:  # settings a file leaves out entirely: read as recorded too (their FIELDS_ADDED_LATER)
        data = {**{name: {} for name in known if _is_settings(hints[name])}, **data}
    values = {}
    for name, value in data.items():
        if _is_settings(hints[name]) and isinstance(value, Mapping):
            value = settings_from_dict(hints[name], value, f"{path}.{name}" if path else name, recorded)
        values[name] = value
    try:
        return cls(**values)
    except SettingsError as exc:
        if not path:
            raise
        raise SettingsError(f"{path}.{exc.option}", exc.problem, exc.prefix) from None
    except (TypeError, ValueError) as exc:
        raise SettingsError(label, f"is invalid: {exc}") from None


def _is_settings(hint) -> bool:
    """Whether a field's type hint is a settings dataclass (not X | None, not a scalar)."""
    return isinstance(hint, type) and is_dataclass(hint)


def _moved_into_place(cls, data: Mapping, path: str) -> dict:
    """`data` with every option named by a flat name of before (`cls.FIELDS_MOVED`: flat
    name → dotted place, e.g. "gamma" → "stiffness.gamma") moved to its nested place, so
    files written before options were grouped, and option dicts that still name them flat
    (the add-on's, a worker's), read as the nested settings. An option named both ways
    takes its nested value: the add-on's panel options are flat, and Extra Settings that
    name an option nested override them as they would flat."""
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
    (`recorded`) that records one is read as if it had not: the field's removal kept the
    behaviour of its default, which the class documents. Settings given now (JSON, command
    line, the add-on) that name one are refused, naming the option and why it went."""
    removed = getattr(cls, "FIELDS_REMOVED", {})
    named = [name for name in data if name in removed]
    if named and not recorded:
        raise SettingsError(f"{path}.{named[0]}" if path else named[0], f"was removed: {removed[named[0]]}")
    return {name: value for name, value in data.items() if name not in removed}


def settings_from_json(cls, text: str, recorded: bool = False):
    """`settings_from_dict` of one JSON string; a broken string raises SettingsError."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SettingsError(cls.__name__, f"is not valid JSON ({exc})") from None
    return settings_from_dict(cls, data, recorded=recorded)


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


def legacy_settings(keys: Sequence[str], values: Sequence[str]) -> dict:
    """Plain data from the key/value string arrays of files written before settings were
    one JSON string: values were str() or repr() of scalars ("800", "'z'", "consensus",
    "None"); dotted keys ("deform.gamma") name nested settings."""
    data = {}
    for key, text in zip(keys, values):
        try:
            data[key] = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            data[key] = text  # str() of a word, e.g. consensus
    return nested_data(data)


def recorded_settings(cls, arrays: Mapping, label: str, key: str = "settings"):
    """The `cls` settings a loaded file records in array `key`: one JSON string ("null":
    none recorded), or in files written before that, the key/value string arrays
    `<key>_keys` / `<key>_values` (`legacy_settings`; none: nothing recorded). Invalid
    settings are a ModelFileError starting with `label`."""
    keys, values = f"{key}_keys", f"{key}_values"
    try:
        if key in arrays or keys not in arrays:
            validate_arrays(arrays, {key: ArraySpec("U", ())}, label)
            text = str(arrays[key])
            return None if text == "null" else cls.from_json(text, recorded=True)
        validate_arrays(arrays, {keys: ArraySpec("U", ("S",)), values: ArraySpec("U", ("S",))}, label)
        legacy = legacy_settings(arrays[keys].tolist(), arrays[values].tolist())
        return cls.from_dict(legacy, recorded=True) if legacy else None
    except SettingsError as exc:
        raise ModelFileError(f"{label}: recorded settings are invalid: {exc}") from None


class Settings:
    """Base of frozen settings dataclasses: checks its fields after construction and
    round-trips through plain data / JSON. Class attributes (not fields) keep files of
    before readable (`settings_from_dict`):

    - `FIELDS_ADDED_LATER`: a field added after files were written → the value runs
      recorded in those files used (when it differs from the field's default);
    - `FIELDS_REMOVED`: a field taken out → why (files that record it still load,
      `_without_removed`);
    - `FIELDS_MOVED`: a flat name of before → the dotted place the option moved to when
      options were grouped (`group`), e.g. {"gamma": "stiffness.gamma",
      "outlier_mad_factor": "outliers.residual_mad_factor"}: data naming it flat is read into that place
      (`_moved_into_place`), so flat JSON and key/value files of before load as the
      nested settings, and option dicts may keep naming it flat."""

    def __post_init__(self):
        check_fields(self)

    def as_dict(self) -> dict:
        return asdict(self)

    def to_json(self) -> str:
        return settings_to_json(self)

    @classmethod
    def from_dict(cls, data: Mapping, recorded: bool = False):
        return settings_from_dict(cls, data, recorded=recorded)

    @classmethod
    def from_json(cls, text: str, recorded: bool = False):
        return settings_from_json(cls, text, recorded)
