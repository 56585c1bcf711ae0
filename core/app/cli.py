"""`shapegen` command line: the headless face of the core.

Subcommands (one function each, `cmd_<name>`): prepare, correspond, ... Errors the user can fix
exit with status 2 and one line naming the file and the problem; no traceback.
"""

from __future__ import annotations

import argparse
import importlib.util
import signal
import sys
import threading
import time
from pathlib import Path

from .cli_common import (CommandError, add_keep_pose_option, add_settings_options, add_skip_unreadable_option,
                         console_progress,
                         correspond_on_console, flag_of, given_options, positive_int, prepare_source, read_source,
                         requested_settings, settings_from_args, turned_on_console)
from .. import __version__
from .cli_generate import add_generate_commands
from ..preprocess.collection import PrepareSettings
from ..correspond import CorrespondenceSettings
from ..base.errors import ShapeGenError
from .fit_settings import FitSettings, RunOptions
from ..meshes.spill import SpillStore

__all__ = ["main", "build_parser"]


# ---------------------------------------------------------------------------- prepare
def cmd_prepare(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    with SpillStore() as spill:  # dense meshes on disk until the file is written (core/meshes/spill.py)
        source = read_source(args.directory, args, accepts=("folder",), spill=spill, last="prepare")
        prepared = prepare_source(source)
        if args.turn_flagged is not None:
            prepared = turned_on_console(prepared, args.turn_flagged)
        prepared.save(args.output)
    counts = [len(l) for l in prepared.landmarks]
    print(
        f"prepared {len(prepared)} shapes -> {args.output}: landmarks {min(counts)}-{max(counts)} "
        f"(requested {source.prepare.n_landmarks}); {time.perf_counter() - start:.1f} s"
    )
    return 0


# ---------------------------------------------------------------------------- correspond
def cmd_correspond(args: argparse.Namespace) -> int:
    import numpy as np

    start = time.perf_counter()
    requested = requested_settings(args)
    with SpillStore() as spill:
        source = read_source(args.source, args, accepts=("folder", "prepared"), spill=spill, requested=requested,
                             last="correspond")
        print(f"[correspond] {source.plan.reason}", file=sys.stderr)
        settings = source.plan.settings
        run = settings_from_args(RunOptions, args)
        result = correspond_on_console(prepare_source(source), template=settings.template, jobs=run.jobs,
                                       settings=settings.correspondence, scheduler=run.scheduler)
    result.save(args.output)
    for name, reason in zip(result.names, result.outlier_reasons):
        if reason:
            print(f"outlier: {name}: {reason}", file=sys.stderr)
    chosen, posed = (f"{said}; " if said else "" for said in (result.start_summary(), result.pose_summary()))
    print(
        f"corresponded {len(result)} shapes x {result.n_landmarks} landmarks -> {args.output}; "
        f"template {result.template_name}; median residual {100 * float(np.median(result.residuals)):.2f} % "
        f"of the diagonal; {int(result.outliers.sum())} outlier(s); {result.matching_summary()}; {chosen}{posed}"
        f"{time.perf_counter() - start:.1f} s"
    )
    return 0


# ---------------------------------------------------------------------------- evaluate
def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate shape models on a folder of meshes or a correspondence .npz."""
    from ..evaluation import EvaluationSettings, parse_model_names, run_evaluation
    from ..evaluation.report import write_report

    start = time.perf_counter()
    # check the cheap settings before any expensive correspondence work
    models = parse_model_names(args.models)
    if not args.no_figures and importlib.util.find_spec("matplotlib") is None:
        raise CommandError("evaluate: the figures need matplotlib (pip install \"shapegen[figures]\"), "
                           "or pass --no-figures")
    regions = [r.strip() for r in args.regions.split(",") if r.strip()]
    with SpillStore() as spill:
        source = read_source(args.source, args, accepts=("folder", "correspondence"), own=("seed",), spill=spill,
                             last="correspond")
        corr = _evaluated_correspondence(source, args)
    prepared_seconds = time.perf_counter() - start
    outliers = [n for n, flag in zip(corr.names, corr.outliers) if flag]
    seed = settings_from_args(PrepareSettings, args).seed  # --seed seeds the evaluation (and a folder's Prepare)
    settings = EvaluationSettings(models=models, folds=args.folds, seed=seed, n_samples=args.samples,
                                  latent_dim=args.latent_dim, regions=regions)
    result = run_evaluation(corr.landmark_matrix(), corr.names, settings, progress=console_progress("evaluate"),
                            extra={"source": source.path.name, "correspondence_outliers": outliers,
                                   "unreadable_files": corr.unreadable})
    paths = write_report(result, args.output, figures=not args.no_figures)
    total_seconds = time.perf_counter() - start
    per_part: dict[str, float] = {}
    for key, seconds in result.timings.items():
        part = key.split(":")[-1]
        per_part[part] = per_part.get(part, 0.0) + seconds
    print("timing (s): " + ", ".join(f"{part} {seconds:.1f}" for part, seconds in per_part.items()), file=sys.stderr)
    print(f"evaluated {', '.join(models)} on {len(corr)} shapes x {corr.n_landmarks} landmarks -> {args.output} "
          f"({len(paths)} files); correspondence {prepared_seconds:.1f} s, total {total_seconds:.1f} s")
    return 0


def _evaluated_correspondence(source, args: argparse.Namespace):
    """The correspondence `evaluate` works on: the file's, or a folder's corresponded now."""
    from ..evaluation import EvaluationError

    if source.correspondence is not None:
        unused = [flag_of(PrepareSettings, name) for name in given_options(PrepareSettings, args) if name != "seed"]
        if unused:
            print(f"note: {', '.join(unused)} not used: {source.path} is already corresponded", file=sys.stderr)
        return source.correspondence
    if args.folds > len(source.meshes):
        raise EvaluationError(f"--folds {args.folds} is more than the {len(source.meshes)} shapes in {source.path}")
    corr = correspond_on_console(prepare_source(source), jobs=settings_from_args(RunOptions, args).jobs,
                                 settings=settings_from_args(CorrespondenceSettings, args))
    if args.save_correspondence is not None:
        corr.save(args.save_correspondence)
    return corr


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="shapegen",
        description="Learn a generative model of 3D shape from a collection of meshes.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("prepare", help="align, scale and landmark a folder of meshes")
    p.add_argument("directory", type=Path, help="folder of .obj/.ply/.stl/.off/.glb files")
    p.add_argument("-o", "--output", type=Path, required=True, help="output .npz")
    add_settings_options(p, PrepareSettings)
    add_keep_pose_option(p)
    add_skip_unreadable_option(p)
    p.add_argument("--turn-flagged", nargs="*", metavar="NAME", default=None,
                   help="turn the shapes Prepare flagged (all of them, or those named) as their flags suggest; "
                        "Prepare itself never turns a shape over on doubtful evidence")
    p.set_defaults(func=cmd_prepare)

    p = sub.add_parser("correspond", help="dense corresponding landmarks by non-rigid ICP (folder or prepared .npz)")
    p.add_argument("source", type=Path, help="folder of meshes, or a prepared collection .npz")
    p.add_argument("-o", "--output", type=Path, required=True, help="output .npz")
    add_settings_options(p, PrepareSettings)
    add_keep_pose_option(p)
    add_skip_unreadable_option(p)
    add_settings_options(p, FitSettings, ("template",))
    add_settings_options(p, RunOptions)
    add_settings_options(p, CorrespondenceSettings)
    p.set_defaults(func=cmd_correspond)

    p = sub.add_parser("evaluate", help="evaluate shape models: completion, novelty, MMD/coverage/1-NNA, NLL curve, latent map")
    p.add_argument("source", type=Path, help="folder of meshes, or a correspondence .npz")
    p.add_argument("-o", "--output", type=Path, required=True, help="report folder (report.json, summary.md, PNGs)")
    p.add_argument("--models", default="ppca,gplvm,bgplvm", help="comma-separated models (default %(default)s)")
    p.add_argument("--folds", type=int, default=5, help="k of the k-fold protocol (default %(default)s)")
    add_settings_options(p, PrepareSettings)  # --seed also seeds the evaluation
    add_keep_pose_option(p)
    add_skip_unreadable_option(p)
    p.add_argument("--samples", type=positive_int, default=100,
                   help="samples per model for novelty / specificity (default %(default)s)")
    p.add_argument("--latent-dim", type=positive_int, default=None,
                   help="latent dimension of every model (default: each model's 80 %% variance rule)")
    p.add_argument("--regions", default="top,middle,rear",
                   help="completion regions: top, middle (thirds along up), rear (lowest third along x) (default %(default)s)")
    add_settings_options(p, RunOptions, ("jobs",))
    add_settings_options(p, CorrespondenceSettings)
    p.add_argument("--no-figures", action="store_true", help="write report.json and summary.md only")
    p.add_argument("--save-correspondence", type=Path, default=None, metavar="NPZ",
                   help="when given a folder, also save its correspondence here (to re-evaluate without redoing it)")
    p.set_defaults(func=cmd_evaluate)

    add_generate_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    previous = _terminate_as_interrupt()
    try:
        return int(args.func(args) or 0)
    except ShapeGenError as exc:
        # one line (the first of a multi-line message), the rest below for folders with many failures
        print(f"shapegen {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"shapegen {args.command}: cancelled", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _terminate_as_interrupt():
    """SIGTERM (a `kill`, a scheduler's timeout) ends a command as Ctrl-C does, so its
    temporary folders and pools are closed on the way out. Returns the handler
    it replaced (None when not in the main thread, where handlers cannot be set)."""
    def interrupt(signum, frame):
        raise KeyboardInterrupt

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, interrupt)


if __name__ == "__main__":
    sys.exit(main())
