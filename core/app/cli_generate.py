"""`shapegen fit | info | sample | complete | morph`: fitting and generation commands.

Registered into the main parser by `cli.build_parser` (`add_generate_commands`); `sample`
runs in cli_sample.py. Every command reads or writes the one fitted-model file
(`shape_model.GenerativeShapeModel`). Outputs are written to a temporary folder first and
moved into place only when every file succeeded, so an error never leaves a half-written
result.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..base.npzfile import ArraySpec, load_npz, save_npz
from ..correspond import CorrespondenceSettings
from ..generate.deform import DeformSettings
from ..generate.quality import QualitySettings
from ..meshes.labels import PartLabels, labels_beside
from ..meshes.reading import list_mesh_files
from ..meshes.spill import SpillStore, loaded
from ..meshes.writing import MeshWriters
from ..preprocess import ShapeTransform
from ..preprocess.collection import PrepareSettings
from .cli_common import (CommandError, StagedOutput, add_keep_pose_option, add_settings_options,
                         add_skip_unreadable_option, console_progress, positive_int, prepare_source, read_mesh_folder,
                         read_source, requested_settings, settings_from_args)
from .cli_sample import cmd_sample
from .fit_settings import FitSettings, RunOptions
from .pipeline import fit_meshes, fit_shape_model
from .shape_model import PATH_SHAPES, GenerativeShapeModel

__all__ = ["add_generate_commands"]

MESH_FORMATS = ("obj", "ply", "glb", "stl", "off")


# ---------------------------------------------------------------------------- fit
def _meshes_for_correspondence(corr, meshes_dir: Path, args: argparse.Namespace, spill: SpillStore | None = None):
    """Training meshes in the model frame for a correspondence file: re-read the inputs from
    `meshes_dir` and apply each shape's transform to the model frame (Prepare's, then the
    pose the correspondence gave it, `Correspondence.model_transforms`; dense ones kept in `spill`),
    and the correspondence recording, besides its own, the files of `meshes_dir` left out
    as unreadable (--skip-unreadable; a shape of the correspondence must still be read)."""
    read, unreadable = read_mesh_folder(meshes_dir, args, spill)
    by_name = {m.name: m for m in read}
    missing = [n for n in corr.names if n not in by_name]
    lost = [message for file, message in unreadable.items() if Path(file).stem in missing]
    if lost:
        raise CommandError(f"{meshes_dir}: the file of shape(s) of the correspondence could not be read: "
                           + "; ".join(lost))
    if missing:
        raise CommandError(f"{meshes_dir}: no mesh file for shape(s) {missing[:5]} of the correspondence")
    meshes = []
    for name, matrix in zip(corr.names, corr.model_transforms()):
        mesh = by_name[name]
        with loaded(mesh) as full:
            vertices = ShapeTransform.from_matrix(matrix).to_normalised(full.vertices)
        meshes.append(mesh.with_vertices(vertices))
    return meshes, replace(corr, unreadable={**corr.unreadable, **unreadable})


def cmd_fit(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    # every setting is checked before the source is read
    settings = requested_settings(args, deform=settings_from_args(DeformSettings, args))
    with SpillStore() as spill:  # dense meshes on disk until the model file is written (core/meshes/spill.py)
        source = read_source(args.source, args, spill=spill, requested=settings)
        if source.correspondence is None and args.meshes is not None:
            raise CommandError(f"--meshes applies to a correspondence .npz source only; {source.path} is a "
                               f"{source.kind}")
        if source.correspondence is not None and args.meshes is None:
            raise CommandError(f"{source.path}: a correspondence file holds landmarks only; pass --meshes DIR (the "
                               "folder it was computed from) so the training meshes can be meshed")
        print(f"[fit] {source.plan.reason}", file=sys.stderr)
        report = console_progress("fit")
        if source.correspondence is None:
            run = settings_from_args(RunOptions, args)
            model = fit_meshes(prepare_source(source), source.plan.settings, progress=report, jobs=run.jobs,
                               scheduler=run.scheduler)
        else:
            meshes, corr = _meshes_for_correspondence(source.correspondence, args.meshes, args, spill)
            model = fit_shape_model(meshes, corr, source.plan.settings, progress=report)
        folder = args.meshes if source.correspondence is not None else Path(args.source)
        if folder.is_dir():
            model.part_labels = _part_labels(model, folder)
        model.save(args.output)
    fitted_on = model.correspondence
    outliers = [n for n, o in zip(model.names, fitted_on.outliers) if o]
    for name, reason in zip(model.names, fitted_on.outlier_reasons):
        if reason:
            print(f"outlier: {name}: {reason}", file=sys.stderr)
    posed, chosen = (f"; {said}" if said else "" for said in (fitted_on.pose_summary(), fitted_on.start_summary()))
    labelled = "" if model.part_labels is None else \
        f"; part labels of {sum(bool((p >= 0).any()) for p in model.part_labels.parts)} shape(s)"
    print(f"fitted {model.model_type} (latent dimension {model.latent_dim}) on {len(model.names)} shapes x "
          f"{model.n_landmarks} landmarks -> {args.output}; {len(outliers)} outlier(s){labelled}{chosen}{posed}; "
          f"{time.perf_counter() - start:.1f} s")
    return 0


def _part_labels(model, folder: Path) -> PartLabels | None:
    """The part labels beside the training meshes' files in `folder` (`<name>_labels.txt`,
    core/meshes/labels.py), mapped onto the meshes as read; None when no file has them."""
    files = {path.stem: path for path in list_mesh_files(folder)}
    found, counts = [], []
    for name, mesh in zip(model.names, model.meshes):
        with loaded(mesh) as full:
            found.append(labels_beside(files[name], full) if name in files else None)
            counts.append(len(full.faces))
    return PartLabels.merge(found, counts)


# ---------------------------------------------------------------------------- info
def cmd_info(args: argparse.Namespace) -> int:
    model = GenerativeShapeModel.load(args.model)
    corr = model.correspondence
    info = {
        "file": str(args.model),
        "model": model.model_type,
        "latent_dim": model.latent_dim,
        "shapes": len(model.names),
        "landmarks": model.n_landmarks,
        "graph_edges": int(len(corr.edges)),
        "template": corr.template_name,
        "outliers": [n for n, o in zip(model.names, corr.outliers) if o],
        "unreadable_files": corr.unreadable,
        "median_residual_percent_of_diagonal": round(100 * float(np.median(corr.residuals)), 4),
        "training_mesh_vertices": [m.n_vertices for m in model.meshes],
        "settings": model.settings.as_dict(),
        "metadata": model.metadata,
        "names": model.names,
    }
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    for key, value in info.items():
        if key == "names":
            value = ", ".join(value[:20]) + (" ..." if len(value) > 20 else "")
        elif key == "unreadable_files":  # left out of the training folder (--skip-unreadable): file and reason
            value = "; ".join(value.values()) or "none"
        print(f"{key:>38}: {value}")
    return 0


# ---------------------------------------------------------------------------- sample
def _write_meshes(model, landmarks, template: str | None, smooth: int, folder: Path, names, file_format: str) -> None:
    """Mesh landmark sets on their templates and write them (complete, morph)."""
    writers = MeshWriters(model.meshes, model.file_axes)
    for name, lm in zip(names, landmarks):
        index = model.choose_template(lm, template)
        mesh = model.mesh_from_landmarks(lm, template=model.names[index], smooth=smooth, name=name)
        writers.write(mesh, index, folder / f"{name}.{file_format}")


# ---------------------------------------------------------------------------- complete
def read_pins(path: Path, model) -> dict[int, np.ndarray]:
    """A pins file: a JSON list of {"landmark": i, "position": [x, y, z]}, positions in the
    axes of the model's files (as written samples are); returned in the model frame
    (`GenerativeShapeModel.file_axes`), by landmark index. Anything else is a CommandError
    naming the file and the entry."""
    try:
        entries = json.loads(Path(path).read_text())
    except OSError as exc:
        raise CommandError(f"{path}: cannot read the pins file ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CommandError(f"{path}: not a JSON pins file ({exc})") from None
    if not isinstance(entries, list) or not entries:
        raise CommandError(f'{path}: pins must be a non-empty JSON list of {{"landmark": i, "position": [x, y, z]}}')
    pins: dict[int, np.ndarray] = {}
    for number, entry in enumerate(entries):
        where = f"{path}: pin {number}"
        if not isinstance(entry, dict) or set(entry) != {"landmark", "position"}:
            raise CommandError(f'{where}: must be {{"landmark": i, "position": [x, y, z]}}, got {json.dumps(entry)}')
        index, position = entry["landmark"], entry["position"]
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < model.n_landmarks:
            raise CommandError(f"{where}: landmark must be an integer from 0 to {model.n_landmarks - 1}, "
                               f"got {json.dumps(index)}")
        if (not isinstance(position, list) or len(position) != 3
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in position)
                or not np.isfinite(np.asarray(position, dtype=np.float64)).all()):
            raise CommandError(f"{where}: position must be 3 finite numbers, got {json.dumps(position)}")
        if index in pins:
            raise CommandError(f"{where}: landmark {index} is pinned twice")
        pins[index] = np.asarray(position, dtype=np.float64) @ model.file_axes.T
    return pins


def _file_vertex_std(model, index: int, std: np.ndarray) -> np.ndarray:
    """Per-vertex std in the order of the written file's vertices (the template's file
    layout's vertex map, when it has one)."""
    layout = model.meshes[index].report.layout
    return std if layout is None else std[layout.vertex_map]


def _complete_from_pins(args: argparse.Namespace, model) -> int:
    pins = read_pins(args.pins, model)
    done = model.complete_from_pins(pins)
    index = model.choose_template(done.landmarks, args.template)
    distances = done.distances(pins)
    with StagedOutput(args.output) as staging:
        save_npz(staging / "completed.npz", "shapegen.samples", 1,
                 {"landmarks": done.landmarks[None], "latents": done.latent[None],
                  "landmark_std": done.std[None], "templates": np.asarray([model.names[index]]),
                  "pin_landmarks": np.asarray(list(pins), dtype=np.int64),
                  "pin_distances": np.asarray(list(distances.values()), dtype=np.float64)})
        _write_meshes(model, done.landmarks[None], model.names[index], args.smooth, staging, ["completed_0000"],
                      args.format)
        if args.std:
            save_npz(staging / "completed_0000_std.npz", "shapegen.vertex_std", 1,
                     {"vertex_std": _file_vertex_std(model, index, model.vertex_std(done.std, index)),
                      "landmark_std": done.std})
    print(f"completed 1 shape from {len(pins)} pin(s) (farthest pin {max(distances.values()):.4g} from the shape"
          f"{', per-vertex std in completed_0000_std.npz' if args.std else ''}) -> {args.output}")
    return 0


def cmd_complete(args: argparse.Namespace) -> int:
    if args.pins is not None and args.partial is not None:
        raise CommandError("give PARTIAL or --pins, not both")
    if args.pins is None and args.partial is None:
        raise CommandError("give PARTIAL (a .npz of partial landmark sets) or --pins PINS.json")
    if args.std and args.pins is None:
        raise CommandError("--std needs --pins (the standard deviation of the completion from pins)")
    model = GenerativeShapeModel.load(args.model)
    if args.pins is not None:
        return _complete_from_pins(args, model)
    arrays = load_npz(args.partial, "shapegen.partial", 1,
                      {"landmarks": ArraySpec("f", (None, None, 3), finite=False)})
    partial = arrays["landmarks"]
    if partial.ndim == 2:
        partial = partial[None]
    if partial.shape[1] != model.n_landmarks:
        raise CommandError(f"{args.partial}: has {partial.shape[1]} landmarks per shape, the model "
                           f"{model.n_landmarks}")
    completed = model.complete(partial)
    with StagedOutput(args.output) as staging:
        save_npz(staging / "completed.npz", "shapegen.samples", 1,
                 {"landmarks": completed, "observed": np.isfinite(partial).all(axis=2)})
        _write_meshes(model, completed, args.template, args.smooth, staging,
                      [f"completed_{i:04d}" for i in range(len(completed))], args.format)
    missing = int((~np.isfinite(partial).all(axis=2)).sum())
    print(f"completed {len(completed)} shape(s) ({missing} missing landmarks filled) -> {args.output}")
    return 0


# ---------------------------------------------------------------------------- morph
def cmd_morph(args: argparse.Namespace) -> int:
    if args.n < 2:
        raise CommandError(f"-n must be at least 2 (both ends), got {args.n}")
    model = GenerativeShapeModel.load(args.model)
    index_a, index_b = model.shape_index(args.name_a), model.shape_index(args.name_b)
    latents = model.training_latents()
    weights, line = model.latent_path(latents[index_a], latents[index_b], args.n)
    landmarks = model.decode(line)
    # one template along the whole line, so every step has the same mesh (pipeline.path_template)
    template = model.names[model.path_template(latents[index_a], latents[index_b], args.template)]
    with StagedOutput(args.output) as staging:
        _write_meshes(model, landmarks, template, args.smooth, staging,
                      [f"morph_{k:03d}" for k in range(len(landmarks))], args.format)
        save_npz(staging / "landmarks.npz", "shapegen.samples", 1,
                 {"landmarks": landmarks, "latents": line, "weights": weights,
                  "ends": np.asarray([args.name_a, args.name_b])})
    print(f"wrote {args.n} meshes on the latent line {args.name_a} -> {args.name_b}, "
          f"all on template {template} -> {args.output}")
    return 0


# ---------------------------------------------------------------------------- parser
def add_generate_commands(sub) -> None:
    p = sub.add_parser("fit", help="fit a generative shape model (folder, prepared .npz or correspondence .npz)")
    p.add_argument("source", type=Path, help="folder of meshes, prepared .npz, or correspondence .npz (+ --meshes)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output model .npz")
    add_settings_options(p, FitSettings)
    add_settings_options(p, RunOptions)
    add_settings_options(p, PrepareSettings)
    add_keep_pose_option(p)
    p.add_argument("--meshes", type=Path, default=None, help="mesh folder of a correspondence .npz source")
    add_skip_unreadable_option(p)
    add_settings_options(p, CorrespondenceSettings)
    add_settings_options(p, DeformSettings)
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("info", help="describe a fitted model file")
    p.add_argument("model", type=Path)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_info)

    def mesh_options(p):
        p.add_argument("--format", choices=MESH_FORMATS, default="obj", help="mesh file format (default %(default)s)")
        p.add_argument("--template", default=None,
                       help="template mesh: a training shape NAME, nearest-data (default) or nearest-latent")
        p.add_argument("--smooth", type=int, default=0, help="curvature-flow smoothing iterations (default 0)")

    p = sub.add_parser("sample", help="sample N new meshes (+ landmarks.npz)")
    p.add_argument("model", type=Path)
    p.add_argument("-n", type=int, required=True, help="number of samples")
    p.add_argument("-o", "--output", type=Path, required=True, help="output folder (must be new or empty)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--exact", action="store_true", help="full stiffness relaxation instead of the linear fast path")
    p.add_argument("--labels", action="store_true",
                   help="also write sample_XXXX_labels.txt: the part of every face, from the template's labels")
    p.add_argument("--jobs", type=positive_int, default=None,
                   help="worker processes for 64+ samples (default: all cores)")
    p.add_argument("--keep-failed", action="store_true",
                   help="when samples still fail the quality gate once the draws are spent, write them to DIR/failed/ "
                   "with their reasons (the run still writes no samples and exits 2)")
    add_settings_options(p, QualitySettings)
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="mesh the samples on Dask: tcp://host:8786 or local:N (needs Dask: pip install dask[distributed])")
    mesh_options(p)
    p.set_defaults(func=cmd_sample)

    p = sub.add_parser("complete", help="complete partial landmark sets (NaN where missing), or one shape from "
                       "pinned landmarks, and mesh them")
    p.add_argument("model", type=Path)
    p.add_argument("partial", type=Path, nargs="?", default=None,
                   help=".npz (format shapegen.partial) with 'landmarks' (n, L, 3), NaN = missing (not with --pins)")
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--pins", type=Path, default=None, metavar="PINS.json",
                   help='the most probable shape given pins: a JSON list of {"landmark": i, "position": [x, y, z]}, '
                   "in the files' axes")
    p.add_argument("--std", action="store_true",
                   help="with --pins: also write completed_0000_std.npz, the posterior standard deviation per vertex")
    mesh_options(p)
    p.set_defaults(func=cmd_complete)

    p = sub.add_parser("morph", help="meshes on the straight latent line between two training shapes")
    p.add_argument("model", type=Path)
    p.add_argument("name_a")
    p.add_argument("name_b")
    p.add_argument("-n", type=int, default=PATH_SHAPES, help="meshes on the line, ends included (default %(default)s)")
    p.add_argument("-o", "--output", type=Path, required=True)
    mesh_options(p)
    p.set_defaults(func=cmd_morph)
