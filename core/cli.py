"""`shapegen` command line: the headless face of the core.

Subcommands (one function each, `cmd_<name>`): prepare, correspond, ... Errors the user can fix
exit with status 2 and one line naming the file and the problem; no traceback.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .errors import ShapeGenError

__all__ = ["main", "build_parser"]


def _console_progress(prefix: str):
    """A progress callback printing one line per 10 % step (or per new message)."""
    state = {"last": -1.0, "message": None}

    def report(fraction: float, message: str) -> None:
        step = int(fraction * 10)
        if step > state["last"] or (message != state["message"] and fraction >= 1.0):
            print(f"[{prefix}] {100 * fraction:5.1f} %  {message}", file=sys.stderr, flush=True)
            state["last"] = step
            state["message"] = message

    return report


# ---------------------------------------------------------------------------- prepare
def cmd_prepare(args: argparse.Namespace) -> int:
    from .collection import PrepareSettings, prepare_meshes
    from .io import read_folder

    start = time.perf_counter()
    meshes = read_folder(args.directory)
    for mesh in meshes:
        if mesh.report.summary() != "clean":
            print(f"{mesh.name}: {mesh.report.summary()}", file=sys.stderr)
    prepared = prepare_meshes(
        meshes, PrepareSettings(n_landmarks=args.landmarks, up_axis=args.up, align=args.align,
                                scale=args.scale, centre=args.centre, seed=args.seed),
        progress=_console_progress("prepare"),
    )
    prepared.save(args.output)
    turned = [s.name for s in prepared.shapes if s.orientation_changed]
    counts = [len(l) for l in prepared.landmarks]
    print(
        f"prepared {len(prepared)} shapes -> {args.output}: landmarks {min(counts)}-{max(counts)} "
        f"(requested {args.landmarks}); consensus re-oriented {len(turned)}"
        + (f" ({', '.join(turned)})" if turned else "")
        + f"; {time.perf_counter() - start:.1f} s"
    )
    return 0


# ---------------------------------------------------------------------------- correspond
def cmd_correspond(args: argparse.Namespace) -> int:
    from .collection import PrepareSettings, PreparedCollection, prepare_meshes
    import numpy as np

    from .correspond import CorrespondenceSettings, correspond
    from .io import read_folder

    start = time.perf_counter()
    source = Path(args.source)
    if source.is_dir():
        meshes = read_folder(source)
        prepared = prepare_meshes(
            meshes, PrepareSettings(n_landmarks=args.landmarks, up_axis=args.up, align=args.align,
                                    scale=args.scale, centre=args.centre, seed=args.seed),
            progress=_console_progress("prepare"),
        )
    else:
        prepared = PreparedCollection.load(source)
    settings = CorrespondenceSettings()
    total = len(prepared) * (settings.groupwise_rounds + 1)
    done = {"count": 0}
    report = _console_progress("correspond")

    def progress(shape: str, stage: str, iteration: int) -> None:
        if stage == "registered":
            done["count"] += 1
            report(done["count"] / total, f"{shape} registered ({iteration} iterations)")
        elif stage in ("template", "mean template"):
            report(done["count"] / total, f"{stage}: {shape}" if stage == "template" else "mean template")

    result = correspond(prepared, settings, template=args.template, jobs=args.jobs, progress=progress)
    result.save(args.output)
    for name, reason in zip(result.names, result.outlier_reasons):
        if reason:
            print(f"outlier: {name}: {reason}", file=sys.stderr)
    print(
        f"corresponded {len(result)} shapes x {result.n_landmarks} landmarks -> {args.output}; "
        f"template {result.template_name}; median residual {100 * float(np.median(result.residuals)):.2f} % "
        f"of the diagonal; {int(result.outliers.sum())} outlier(s); {time.perf_counter() - start:.1f} s"
    )
    return 0


# ---------------------------------------------------------------------------- evaluate
def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate shape models on a folder of meshes or a correspondence .npz (issue 7)."""
    from .evaluation import EvaluationError, EvaluationSettings, parse_model_names, run_evaluation
    from .report import write_report

    start = time.perf_counter()
    # check the cheap settings before any expensive correspondence work
    models = parse_model_names(args.models)
    regions = [r.strip() for r in args.regions.split(",") if r.strip()]
    source = Path(args.source)
    if source.is_dir():
        from .collection import PrepareSettings, prepare_meshes
        from .correspond import CorrespondenceSettings, correspond
        from .io import read_folder

        meshes = read_folder(source)
        if args.folds > len(meshes):
            raise EvaluationError(f"--folds {args.folds} is more than the {len(meshes)} shapes in {source}")
        prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=args.landmarks, up_axis=args.up, seed=args.seed),
                                  progress=_console_progress("prepare"))
        report = _console_progress("correspond")
        total = len(prepared) * (CorrespondenceSettings().groupwise_rounds + 1)
        done = {"count": 0}

        def progress(shape: str, stage: str, iteration: int) -> None:
            if stage == "registered":
                done["count"] += 1
                report(done["count"] / total, f"{shape} registered")

        corr = correspond(prepared, CorrespondenceSettings(), jobs=args.jobs, progress=progress)
        if args.save_correspondence is not None:
            corr.save(args.save_correspondence)
    elif source.is_file():
        from .correspond import Correspondence

        corr = Correspondence.load(source)
    else:
        raise EvaluationError(f"{source}: no such folder or correspondence file")
    prepared_seconds = time.perf_counter() - start
    outliers = [n for n, flag in zip(corr.names, corr.outliers) if flag]
    settings = EvaluationSettings(models=models, folds=args.folds, seed=args.seed, n_samples=args.samples,
                                  latent_dim=args.latent_dim, regions=regions)
    result = run_evaluation(corr.landmark_matrix(), corr.names, settings, progress=_console_progress("evaluate"),
                            extra={"source": source.name, "correspondence_outliers": outliers})
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


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    from .landmarks import DEFAULT_LANDMARKS
    from .preprocess import CENTRE_MODES, SCALE_MODES, UP_AXES

    parser = argparse.ArgumentParser(
        prog="shapegen",
        description="Learn a generative model of 3D shape from a collection of meshes.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("prepare", help="align, scale and landmark a folder of meshes")
    p.add_argument("directory", type=Path, help="folder of .obj/.ply/.stl/.off/.glb files")
    p.add_argument("-o", "--output", type=Path, required=True, help="output .npz")
    p.add_argument("--landmarks", type=int, default=DEFAULT_LANDMARKS, help="landmarks per shape (default %(default)s)")
    p.add_argument("--align", choices=("consensus", "pca", "none"), default="consensus",
                   help="orientation: per-shape PCA, PCA then agreement with the collection (default), or none")
    p.add_argument("--up", choices=UP_AXES, default="z", help="input axis that points up (default %(default)s)")
    p.add_argument("--scale", choices=SCALE_MODES, default="variance", help="scaling rule (default %(default)s)")
    p.add_argument("--centre", choices=CENTRE_MODES, default="centroid", help="horizontal centring (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    p.set_defaults(func=cmd_prepare)

    p = sub.add_parser("correspond", help="dense corresponding landmarks by non-rigid ICP (folder or prepared .npz)")
    p.add_argument("source", type=Path, help="folder of meshes, or a prepared collection .npz")
    p.add_argument("-o", "--output", type=Path, required=True, help="output .npz")
    p.add_argument("--landmarks", type=int, default=DEFAULT_LANDMARKS,
                   help="landmarks per shape when given a folder (default %(default)s)")
    p.add_argument("--template", default=None, help="template shape name (default: the medoid by Chamfer distance)")
    p.add_argument("--jobs", type=_positive_int, default=None, help="worker processes (default: all cores)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    p.add_argument("--align", choices=("consensus", "pca", "none"), default="consensus",
                   help="orientation when given a folder (default %(default)s)")
    p.add_argument("--up", choices=UP_AXES, default="z", help="input axis that points up (default %(default)s)")
    p.add_argument("--scale", choices=SCALE_MODES, default="variance", help="scaling rule (default %(default)s)")
    p.add_argument("--centre", choices=CENTRE_MODES, default="centroid", help="horizontal centring (default %(default)s)")
    p.set_defaults(func=cmd_correspond)
    p = sub.add_parser("evaluate", help="evaluate shape models: completion, novelty, MMD/coverage/1-NNA, NLL curve, latent map")
    p.add_argument("source", type=Path, help="folder of meshes, or a correspondence .npz")
    p.add_argument("-o", "--output", type=Path, required=True, help="report folder (report.json, summary.md, PNGs)")
    p.add_argument("--models", default="ppca,gplvm,bgplvm", help="comma-separated models (default %(default)s)")
    p.add_argument("--folds", type=int, default=5, help="k of the k-fold protocol (default %(default)s)")
    p.add_argument("--landmarks", type=int, default=DEFAULT_LANDMARKS,
                   help="landmarks per shape when given a folder (default %(default)s)")
    p.add_argument("--up", choices=UP_AXES, default="z", help="input axis that points up (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="random seed of everything (default %(default)s)")
    p.add_argument("--samples", type=_positive_int, default=100,
                   help="samples per model for novelty / specificity (default %(default)s)")
    p.add_argument("--latent-dim", type=_positive_int, default=None,
                   help="latent dimension of every model (default: each model's 80 %% variance rule)")
    p.add_argument("--regions", default="top,middle,rear",
                   help="completion regions: top, middle (thirds along up), rear (lowest third along x) (default %(default)s)")
    p.add_argument("--jobs", type=_positive_int, default=None, help="correspondence worker processes (default: all cores)")
    p.add_argument("--no-figures", action="store_true", help="write report.json and summary.md only")
    p.add_argument("--save-correspondence", type=Path, default=None, metavar="NPZ",
                   help="when given a folder, also save its correspondence here (to re-evaluate without redoing it)")
    p.set_defaults(func=cmd_evaluate)

    from .cli_generate import add_generate_commands

    add_generate_commands(sub, _positive_int)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ShapeGenError as exc:
        # one line (the first of a multi-line message), the rest below for folders with many failures
        print(f"shapegen {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"shapegen {args.command}: cancelled", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
