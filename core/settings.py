"""Typed settings: frozen dataclasses that check themselves and travel as one JSON string.

A settings class derives from `Settings` and declares each option with `option(...)`: its
help text, its command-line flag and its allowed values live on the field, so the checks
here, the command line (`cli_common.add_settings_options`) and the saved JSON all read
the same declaration. Nested settings (e.g. `FitSettings.prepare`) are dataclass fields
and nest in the JSON.
"""

from __future__ import annotations

import ast
import json
import types
from dataclasses import MISSING, asdict, field, fields, is_dataclass
from typing import Any, Mapping, Sequence, Union, get_args, get_origin, get_type_hints

from .errors import ModelFileError, ShapeGenError
from .npzfile import ArraySpec, validate_arrays

__all__ = ["Settings", "SettingsError", "option", "check_fields", "settings_from_dict", "settings_from_json",
           "settings_to_json", "legacy_settings", "recorded_settings"]


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
    ("deform.final_alpha"). `recorded`: the data is what a file recorded, so a field the
    file predates takes the value its run used (`cls.FIELDS_ADDED_LATER`), not today's
    default."""
    label = path or cls.__name__
    if not isinstance(data, Mapping):
        raise SettingsError(label, f"must be a JSON object, got {data!r}")
    if recorded:
        data = {**getattr(cls, "FIELDS_ADDED_LATER", {}), **data}
    data = _without_removed(cls, data, path, recorded)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise SettingsError(label, f"has no option {unknown[0]!r} (options: {', '.join(sorted(known))})")
    hints = get_type_hints(cls)
    values = {}
    for name, value in data.items():
        if is_dataclass(hints[name]) and isinstance(value, Mapping):
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


def legacy_settings(keys: Sequence[str], values: Sequence[str]) -> dict:
    """Plain data from the key/value string arrays of files written before settings were
    one JSON string: values were str() or repr() of scalars ("800", "'z'", "consensus",
    "None"); dotted keys ("deform.gamma") name nested settings."""
    data: dict = {}
    for key, text in zip(keys, values):
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text  # str() of a word, e.g. consensus
        *parents, name = key.split(".")
        target = data
        for parent in parents:
            target = target.setdefault(parent, {})
        target[name] = value
    return data


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
    round-trips through plain data / JSON. A subclass's `FIELDS_ADDED_LATER` (a class
    attribute) maps a field added after files were written to the value runs recorded
    in those files used (when it differs from the field's default); its `FIELDS_REMOVED`
    maps a field taken out to why (files that record it still load, `_without_removed`)."""

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
