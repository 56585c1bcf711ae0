"""`shapegen` command line: the headless face of the core.

Subcommands (one function each, `cmd_<name>`): prepare, ... Errors the user can fix
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
    from .collection import prepare_meshes
    from .io import read_folder

    start = time.perf_counter()
    meshes = read_folder(args.directory)
    for mesh in meshes:
        if mesh.report.summary() != "clean":
            print(f"{mesh.name}: {mesh.report.summary()}", file=sys.stderr)
    prepared = prepare_meshes(
        meshes, n_landmarks=args.landmarks, up_axis=args.up, align=args.align,
        scale=args.scale, centre=args.centre, seed=args.seed,
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
