"""Prepare by consensus on a large collection: the pose decisions of the
candidate path (above `neighbours.EXACT_SHAPES` shapes the pose search computes the exact
cost only for the pairs a descriptor proposes) against every pair computed, for the
working tree and git revisions, and where Prepare's time goes (cProfile).

    python bench/prepare_scale.py [--shapes 100] [--seed 0] [--resolution 40 90]
        [--revisions main=main] [--no-all-pairs] [--profile 20]

The collection: `make_vases(shapes, seed, resolution)`, each vase in a random yaw, scale
and position (their input poses; up is z). For each version ("after" = the working tree,
and every NAME=REV of --revisions, imported as its own package as bench/orientation.py
does) Prepare runs on the candidate path and, unless --no-all-pairs, with every pair
exact; the script prints the seconds, the exact pair costs computed (calls of
`PoseSearch.axis_distance`) and, how many shapes' rotations (to 1e-9), pose reasons and
flags differ from the working tree's all-pairs run and from its candidate run.
--profile N: the cumulative cProfile of the working tree's candidate run, top N lines.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from orientation import load_revision  # noqa: E402  (also makes shapegen_core importable)

from shapegen_core.demo_data import make_vases  # noqa: E402
from shapegen_core.preprocess import prepare_collection  # noqa: E402


def run(prepare, meshes, all_pairs: bool, profile: cProfile.Profile | None = None) -> dict:
    """Prepare the meshes with `prepare` (the candidate path, or every pair exact): its
    decisions, seconds and exact pair costs computed."""
    package = prepare.__module__.split(".")[0]
    search_class = sys.modules[f"{package}.preprocess.posesearch"].PoseSearch
    init_defaults, axis_distance = search_class.__init__.__defaults__, search_class.axis_distance
    calls = [0]

    def counted(self, j, i):
        calls[0] += 1
        return axis_distance(self, j, i)

    search_class.axis_distance = counted
    if all_pairs:
        search_class.__init__.__defaults__ = (len(meshes) + 1,) + init_defaults[1:]
    try:
        start = time.perf_counter()
        if profile is not None:
            profile.enable()
        prepared = prepare(meshes, up_axis="z", align="consensus")
        if profile is not None:
            profile.disable()
        seconds = time.perf_counter() - start
    finally:
        search_class.axis_distance = axis_distance
        search_class.__init__.__defaults__ = init_defaults
    return {"seconds": seconds, "pairs": calls[0], "rotations": [s.transform.rotation for s in prepared],
            "reasons": [s.pose_change for s in prepared], "flags": [s.pose_outlier for s in prepared],
            "names": [s.name for s in prepared]}


def differences(result: dict, reference: dict) -> str:
    """How many shapes' rotations, reasons and flags differ from the reference run's."""
    rotations = sum(not np.allclose(a, b, atol=1e-9) for a, b in zip(result["rotations"], reference["rotations"]))
    reasons = sum(a != b for a, b in zip(result["reasons"], reference["reasons"]))
    flags = sum(a != b for a, b in zip(result["flags"], reference["flags"]))
    return f"rotations {rotations}, reasons {reasons}, flags {flags} differ"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", type=int, nargs=2, default=(40, 90), help="vertex rings along the profile")
    parser.add_argument("--revisions", nargs="*", default=["main=main"], help="NAME=REV versions beside the tree")
    parser.add_argument("--no-all-pairs", dest="all_pairs", action="store_false")
    parser.add_argument("--profile", type=int, default=0, help="print the top N cProfile lines of 'after'")
    args = parser.parse_args()

    meshes = [v.mesh for v in make_vases(args.shapes, seed=args.seed, resolution=tuple(args.resolution))]
    versions = {"after": prepare_collection}
    for item in args.revisions:
        name, revision = item.split("=", 1)
        versions[name] = load_revision(name, revision)
    print(f"{args.shapes} vases (seed {args.seed}, rings {args.resolution[0]}-{args.resolution[1]}, "
          f"{int(np.mean([m.n_vertices for m in meshes]))} vertices on average), random yaw", flush=True)
    profile = cProfile.Profile() if args.profile else None
    results = {}
    for name, prepare in versions.items():
        for all_pairs in ((False, True) if args.all_pairs else (False,)):
            path = "all pairs" if all_pairs else "candidates"
            result = results[name, path] = run(prepare, meshes, all_pairs,
                                               profile if name == "after" and not all_pairs else None)
            print(f"{name:8s} {path:10s}: {result['seconds']:7.1f} s, {result['pairs']} exact pair costs, "
                  f"{sum(bool(r) for r in result['reasons'])} turned, {sum(bool(f) for f in result['flags'])} "
                  "flagged", flush=True)
    first = next(iter(versions))
    references = [key for key in ((first, "all pairs"), (first, "candidates")) if key in results]
    for reference in references:
        for key, result in results.items():
            if key != reference:
                print(f"{' '.join(key):22s} against {' '.join(reference)}: {differences(result, results[reference])}")
    if profile is not None:
        out = io.StringIO()
        pstats.Stats(profile, stream=out).sort_stats("cumulative").print_stats(args.profile)
        print(out.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
