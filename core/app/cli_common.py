"""What the `shapegen` commands share: options built from settings dataclasses, the one
source reader (folder, prepared .npz or correspondence .npz; which stages run on it is
core/app/stages.py's decision) and the console progress printer."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import types
from dataclasses import MISSING, Field, dataclass, fields
from pathlib import Path
from typing import Sequence, Union, get_args, get_origin, get_type_hints

from ..preprocess.collection import PREPARED_FORMAT, PreparedCollection, PrepareSettings, kept_poses, prepare_meshes
from ..correspond import CORRESPONDENCE_FORMAT, Correspondence, CorrespondenceSettings, correspond
from ..base.errors import CollectionError, ShapeGenError
from ..meshes.reading import read_folder, read_readable
from ..meshes.mesh import Mesh
from .fit_settings import FitSettings
from ..base.progress import Progress
from ..base.settings import SettingsError, is_group, nested_data, settings_from_dict
from ..meshes.spill import SpillStore
from .stages import SettingsConflict, StagePlan, file_stage, plan_stages, read_offered

__all__ = ["CommandError", "StagedOutput", "Source", "SOURCE_KINDS", "positive_int", "add_settings_options", "given_options", "flag_of",
           "settings_from_args", "requested_settings", "add_keep_pose_option", "add_skip_unreadable_option",
           "read_mesh_folder", "turned_on_console", "read_source", "prepare_source", "pose_lines",
           "correspond_on_console", "console_progress"]


class CommandError(ShapeGenError, ValueError):
    """A command-line argument that cannot be used (names the argument)."""


# ---------------------------------------------------------------------------- options
def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _flagged_options(cls, names: tuple[str, ...] | None = None, prefix: str = "") -> list[tuple[str, Field, type]]:
    """(path, field, type hint) of every option of the settings dataclass `cls` that declares
    a flag, those of its groups (`settings.group`, e.g. CorrespondenceSettings.stiffness)
    included under their dotted paths ("stiffness.gamma"); only the paths in `names`, if
    given. Nested settings that are not groups (FitSettings.prepare) have options of their
    own: a command adds them by themselves."""
    hints = get_type_hints(cls)
    found = []
    for f in fields(cls):
        path = prefix + f.name
        if is_group(f):
            found += _flagged_options(hints[f.name], names, f"{path}.")
        elif f.metadata.get("flag") and (names is None or path in names):
            found.append((path, f, hints[f.name]))
    return found


def _argument_type(hint):
    """int / float / str for a field typed X or X | None."""
    if get_origin(hint) in (Union, types.UnionType):
        hint = next(h for h in get_args(hint) if h is not type(None))
    return hint


def add_settings_options(parser: argparse.ArgumentParser, cls, names: tuple[str, ...] | None = None) -> None:
    """One option per field of the settings dataclass `cls` (and of its groups) that
    declares a flag (only `names`, if given), help text and choices from the field; the
    parsed value goes to the field's path (`_flagged_options`). Options left out are not
    set on the parsed namespace, so `settings_from_args` can tell them from given ones."""
    for path, f, hint in _flagged_options(cls, names):
        default = f.default if f.default is not MISSING else None
        text = f.metadata["help"] + ("" if default is None else f" (default {default})")
        flag, choices = f.metadata["flag"], f.metadata.get("choices")
        parser.add_argument(flag, dest=path, type=_argument_type(hint), choices=choices,
                            metavar=None if choices else flag.lstrip("-").upper().replace("-", "_"),
                            default=argparse.SUPPRESS, help=text.replace("%", "%%"))


def given_options(cls, args: argparse.Namespace) -> dict:
    """The options of `cls` given on the command line: {path: value} (a group's option by
    its dotted path)."""
    return {path: getattr(args, path) for path, _, _ in _flagged_options(cls) if hasattr(args, path)}


def flag_of(cls, name: str) -> str:
    """The command-line option of field `name` (a dotted path into a group) of `cls`."""
    return next(f.metadata["flag"] for path, f, _ in _flagged_options(cls) if path == name)


def settings_from_args(cls, args: argparse.Namespace, flags: dict[str, str] | None = None, **fixed):
    """`cls` from the options given on the command line (the rest at their defaults) and
    the `fixed` fields. A SettingsError names the command-line option: the field's flag,
    or `flags[option]` for options set through `fixed` (e.g. "deform.final_alpha")."""
    names = {path: f.metadata["flag"] for path, f, _ in _flagged_options(cls)} | dict(flags or {})
    try:
        return settings_from_dict(cls, {**nested_data(given_options(cls, args)), **fixed})
    except SettingsError as exc:
        raise SettingsError(names.get(exc.option, exc.option), exc.problem, exc.prefix) from None


def requested_settings(args: argparse.Namespace, **fixed) -> FitSettings:
    """The FitSettings a command's options ask for: its FitSettings, Prepare and
    correspondence options (the rest at their defaults), and the `fixed` fields."""
    return settings_from_args(FitSettings, args, prepare=settings_from_args(PrepareSettings, args),
                              correspondence=settings_from_args(CorrespondenceSettings, args), **fixed)


def add_keep_pose_option(parser: argparse.ArgumentParser) -> None:
    """--keep-pose NAME [NAME ...]: shapes of a folder whose pose Prepare keeps."""
    parser.add_argument("--keep-pose", nargs="+", metavar="NAME", default=None,
                        help="shapes (file names without extension) whose pose Prepare keeps: never turned beyond "
                             "the up axis, still flagged when their pose looks wrong")


def add_skip_unreadable_option(parser: argparse.ArgumentParser) -> None:
    """--skip-unreadable: a folder's files that cannot be read are left out (each named with
    its reason, and recorded in the output) instead of stopping the command."""
    parser.add_argument("--skip-unreadable", action="store_true",
                        help="leave out the mesh files that cannot be read (each named on stderr with its reason and "
                             "recorded in the output) and go on with the rest; without it one unreadable file stops "
                             "the command")


def read_mesh_folder(folder: Path, args: argparse.Namespace, spill: SpillStore | None = None,
                     jobs: int | None = 1) -> tuple[list[Mesh], dict[str, str]]:
    """The meshes of `folder` and {file name: message} of the files left out: none unless
    the command was given --skip-unreadable, which names each one left out on stderr (a
    "skipped: <the reader's message>" line); without it an unreadable file is an error."""
    if not getattr(args, "skip_unreadable", False):
        return read_folder(folder, jobs=jobs, spill=spill), {}
    meshes, unreadable = read_readable(folder, jobs=jobs, spill=spill)
    for message in unreadable.values():
        print(f"skipped: {message}", file=sys.stderr)
    return meshes, unreadable


# ---------------------------------------------------------------------------- sources
SOURCE_KINDS = ("folder", "prepared", "correspondence")
_KIND_OF_STAGE = {"prepare": "prepared", "correspond": "correspondence"}

_DESCRIPTIONS = {"folder": "a folder of meshes", "prepared": f"a prepared .npz ({PREPARED_FORMAT!r})",
                 "correspondence": f"a correspondence .npz ({CORRESPONDENCE_FORMAT!r})"}


def _either(things: list[str]) -> str:
    return things[0] if len(things) == 1 else f"{', '.join(things[:-1])} or {things[-1]}"


@dataclass
class Source:
    """A command's input and its `plan` (core/app/stages.py): the stages that run on it and the
    settings its result records (a file's own where it records them)."""

    path: Path
    kind: str  # one of SOURCE_KINDS
    plan: StagePlan
    meshes: list[Mesh] | None = None  # folder: the meshes read (dense ones spill.StoredMesh; None once prepared)
    keep_pose: list[bool] | None = None  # folder: per mesh, keep its pose (--keep-pose)
    prepared: PreparedCollection | None = None  # prepared .npz (or a folder once prepared)
    correspondence: Correspondence | None = None  # correspondence .npz
    unreadable: dict[str, str] | None = None  # folder: files left out as unreadable, {file name: why}

    @property
    def prepare(self) -> PrepareSettings:
        """How its shapes are (or are to be) prepared."""
        return self.plan.settings.prepare


def _source_kind(path: Path, accepts: tuple[str, ...]) -> str:
    """folder, prepared or correspondence (a file's format tag decides); a CommandError
    when `path` is missing or of a kind the command does not take."""
    expected = _either([_DESCRIPTIONS[k] for k in accepts])
    if not path.exists():
        raise CommandError(f"{path}: no such {_either(['folder'] + [f'{k} file' for k in accepts if k != 'folder'])}")
    kind = "folder"
    if not path.is_dir():
        file_format, stage = file_stage(path)
        kind = _KIND_OF_STAGE.get(stage)
        if kind not in accepts:
            raise CommandError(f"{path}: is a {file_format!r} file; expected {expected}")
    if kind not in accepts:
        raise CommandError(f"{path}: is a folder; expected {expected}")
    return kind


def read_source(path: Path, args: argparse.Namespace, accepts: tuple[str, ...] = SOURCE_KINDS,
                own: tuple[str, ...] = (), spill: SpillStore | None = None, requested: FitSettings | None = None,
                last: str = "fit") -> Source:
    """Read a folder of meshes, a prepared .npz or a correspondence .npz and plan the stages
    up to `last` on it (core/app/stages.py: a file is used as given; Prepare options given with
    it, but the `own` ones, which the command uses for itself — evaluate's --seed —, and
    for a fit its correspondence options, must agree with the settings it records).
    `requested`: the command's settings (default: its Prepare and correspondence options).
    `spill`: the run's store for a folder's dense meshes (core/meshes/spill.py). A folder's
    unreadable files are an error, or left out with --skip-unreadable (`read_mesh_folder`)."""
    path = Path(path)
    kind = _source_kind(path, accepts)
    if requested is None:
        requested = FitSettings(prepare=settings_from_args(PrepareSettings, args),
                                correspondence=settings_from_args(CorrespondenceSettings, args))
    keep_pose = getattr(args, "keep_pose", None)
    if kind == "folder":
        meshes, unreadable = read_mesh_folder(path, args, spill, jobs=getattr(args, "jobs", 1))
        for mesh in meshes:
            if mesh.report.summary() != "clean":
                print(f"{mesh.name}: {mesh.report.summary()}", file=sys.stderr)
        return Source(path, kind, plan_stages(requested, last=last), meshes=meshes,
                      keep_pose=kept_poses([m.name for m in meshes], keep_pose), unreadable=unreadable)
    if keep_pose:
        raise CommandError(f"--keep-pose applies to a folder of meshes; {path} is already prepared (its poses were "
                           "decided then: prepare its folder again with --keep-pose)")
    offered = read_offered(path, "prepare" if kind == "prepared" else "correspond")
    given = {"prepare": {k: v for k, v in given_options(PrepareSettings, args).items() if k not in own}}
    if last == "fit":
        given["correspondence"] = given_options(CorrespondenceSettings, args)
    try:
        plan = plan_stages(requested, [offered], given, last)
    except SettingsConflict as exc:
        cls = PrepareSettings if exc.group == "prepare" else CorrespondenceSettings
        flag = flag_of(cls, exc.option)
        made = "prepared" if exc.group == "prepare" else "corresponded"
        raise CommandError(f"{flag} {exc.value} conflicts with {path}, {made} with {flag} {exc.recorded}; "
                           f"leave {flag} out to use the file's") from None
    if kind == "correspondence":
        return Source(path, kind, plan, correspondence=offered.data)
    return Source(path, kind, plan, prepared=offered.data)


def prepare_source(source: Source) -> PreparedCollection:
    """The prepared collection of a folder (prepared now, with console progress and its
    pose report, `pose_lines`, on stderr; recording the folder's files left out as
    unreadable) or of a prepared file."""
    if source.prepared is None:
        source.prepared = prepare_meshes(source.meshes, source.prepare, progress=console_progress("prepare"),
                                         keep_pose=source.keep_pose)
        source.prepared.unreadable = dict(source.unreadable or {})
        source.meshes = None  # the input meshes are not needed again: free them (dense meshes)
        for line in pose_lines(source.prepared):
            print(line, file=sys.stderr)
    return source.prepared


def turned_on_console(prepared: PreparedCollection, names: Sequence[str]) -> PreparedCollection:
    """`PreparedCollection.turn_flagged` for --turn-flagged (no names: every flagged shape),
    one line per turned shape on stderr; a named shape without a suggested turn is an error."""
    unturnable = [name for name in names if name in prepared.names and name not in prepared.flagged()]
    if unturnable:
        raise CommandError(f"--turn-flagged: {', '.join(unturnable)} not flagged with a turn to make")
    try:
        turned = prepared.turn_flagged(names or None)
    except CollectionError as exc:
        raise CommandError(f"--turn-flagged: {exc}") from None
    for before, after in zip(prepared.shapes, turned.shapes):
        if after.pose_change != before.pose_change:
            print(f"{after.name}: {after.pose_change}", file=sys.stderr)
    return turned


def pose_lines(prepared: PreparedCollection) -> list[str]:
    """What Prepare did to the poses: a line per turned or flagged shape
    (`PreparedCollection.pose_notes`) and the summary "poses: N kept, M turned, K flagged"."""
    turned = sum(bool(s.pose_change) for s in prepared.shapes)
    flagged = sum(bool(s.pose_outlier) for s in prepared.shapes)
    return prepared.pose_notes() + [f"poses: {len(prepared) - turned} kept, {turned} turned, {flagged} flagged"]


def correspond_on_console(prepared: PreparedCollection, template: str | None = None, jobs: int | None = None,
                          settings: CorrespondenceSettings = CorrespondenceSettings(), scheduler: str | None = None):
    """`correspond.correspond` with console progress (default settings unless given; on a
    Dask cluster when `scheduler` is given)."""
    return correspond(prepared, settings, template=template, jobs=jobs, progress=console_progress("correspond"),
                      scheduler=scheduler)


# ---------------------------------------------------------------------------- progress
def console_progress(prefix: str) -> Progress:
    """A progress printing one line per 10 % step, and every new message at the end or that
    states something about one shape ("<name>: <what happened>", e.g. which start its
    registration took and why), which a step would otherwise hide."""
    state = {"last": -1, "message": None}

    def report(fraction: float, message: str) -> None:
        step = int(fraction * 10)
        if step > state["last"] or (message != state["message"] and (fraction >= 1.0 or ": " in message)):
            print(f"[{prefix}] {100 * fraction:5.1f} %  {message}", file=sys.stderr, flush=True)
            state["last"] = step
            state["message"] = message

    return report


class StagedOutput:
    """A folder written completely in a sibling temporary folder, then moved into place."""

    def __init__(self, target: Path):
        self.target = Path(target)

    def __enter__(self) -> Path:
        if self.target.exists() and any(self.target.iterdir()):
            raise CommandError(f"{self.target}: output folder exists and is not empty")
        self.target.parent.mkdir(parents=True, exist_ok=True)
        self.staging = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.", dir=self.target.parent))
        return self.staging

    def __exit__(self, kind, value, traceback):
        if kind is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            return False
        if self.target.exists():
            self.target.rmdir()
        os.replace(self.staging, self.target)
        return False
