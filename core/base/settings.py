"""Typed settings: frozen dataclasses that check themselves and travel as one JSON string.

A settings class derives from `Settings` and declares each option with `option(...)`: its
help text, its command-line flag and its allowed values live on the field, so the checks
here, the command line (`cli_common.add_settings_options`) and the saved JSON all read
the same declaration. Nested settings (e.g. `FitSettings.prepare`) are dataclass fields
and nest in the JSON. A subsystem's options inside one settings class are a `group` field
(e.g. `CorrespondenceSettings.stiffness`): nested in the JSON, offered on the command line
with their parent's options. What files written before hold, and flat option dicts such as
the add-on's, read as today's settings through the tables and code of `compat.py`.
"""

from __future__ import annotations

import json
import types
from dataclasses import MISSING, asdict, field, fields, is_dataclass
from typing import Any, Mapping, Sequence, Union, get_args, get_origin, get_type_hints

from .compat import is_key_value_layout, key_value_settings, nested_data, read_as_today
from .errors import ModelFileError, SettingsError
from .npzfile import ArraySpec, validate_arrays

__all__ = ["Settings", "SettingsError", "option", "group", "is_group", "check_fields", "settings_from_dict",
           "settings_from_json", "settings_to_json", "nested_data", "recorded_settings"]


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
    ("deform.final_alpha"). Names of before are read as today's (`compat.read_as_today`:
    flat names moved into their groups, removed fields left out or refused). `recorded`:
    the data is what a file recorded, so a field the file predates takes the value its run
    used (`FIELDS_ADDED_LATER` of the class that holds it), not today's default, and a
    removed field it records is left out silently."""
    label = path or cls.__name__
    if not isinstance(data, Mapping):
        raise SettingsError(label, f"must be a JSON object, got {data!r}")
    data = read_as_today(cls, data, path, recorded)
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


def settings_from_json(cls, text: str, recorded: bool = False):
    """`settings_from_dict` of one JSON string; a broken string raises SettingsError."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SettingsError(cls.__name__, f"is not valid JSON ({exc})") from None
    return settings_from_dict(cls, data, recorded=recorded)


def recorded_settings(cls, arrays: Mapping, label: str, key: str = "settings"):
    """The `cls` settings a loaded file records in array `key`: one JSON string ("null":
    none recorded), or in files written before that, key/value string arrays
    (`compat.key_value_settings`; none: nothing recorded). Invalid settings are a
    ModelFileError starting with `label`."""
    try:
        if not is_key_value_layout(arrays, key):
            validate_arrays(arrays, {key: ArraySpec("U", ())}, label)
            text = str(arrays[key])
            return None if text == "null" else cls.from_json(text, recorded=True)
        data = key_value_settings(arrays, label, key)
        return cls.from_dict(data, recorded=True) if data else None
    except SettingsError as exc:
        raise ModelFileError(f"{label}: recorded settings are invalid: {exc}") from None


class Settings:
    """Base of frozen settings dataclasses: checks its fields after construction and
    round-trips through plain data / JSON. Class attributes (not fields) keep files of
    before readable, each pointing to its table in `compat.py` (which says what they
    mean): `FIELDS_ADDED_LATER`, `FIELDS_REMOVED`, `FIELDS_MOVED`."""

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
