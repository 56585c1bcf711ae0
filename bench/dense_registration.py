"""Correspondence time per shape, dense against ordinary meshes (the target:
registration time per shape grows by at most 2x from 20k to 1M vertices), in CPU seconds
of this one process (jobs=1: every registration, proxy and placement runs here, so the
process's CPU time is all the work), split by part.

    python bench/dense_registration.py [--shapes 4] [--vases 20] [--dense-folder /tmp/shapegen-scale/Fish-1000000]

Two collections, each prepared (not timed) and then corresponded with the default
settings: the first `--shapes` meshes of the dense folder (bench/scale.py's dense-1M
cache: PSB fish subdivided to ~1.4M vertices; made by `bench/scale.py --rows dense-1M`
when missing) and `--vases` procedural vases of ~20k vertices (the same vases as
bench/scale.py's vases-20 row). Per shape: the whole correspondence, and the parts that run per dense shape: the
registration proxy built (a dense shape's; later code removes that rebuild by
reusing Prepare's proxy, so the script also prints the ratio without it, an estimate), the
registration rounds (`register_task`), the exact placement on the full surface, and the
rest (template, outlier flags, mean templates in the main process). CPU seconds depend on
the load less than wall seconds, but not nothing: the script prints `uptime` before and
after, and both collections run back to back in the same process.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from scale import VASE_RESOLUTION  # noqa: E402


class _Timed:
    """CPU seconds spent in module-level functions (replaced by timing wrappers)."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self._undo: list = []

    def wrap(self, module, name: str, label: str) -> None:
        original = getattr(module, name, None)
        if original is None:  # the function is gone in this version of the core
            return

        def timed(*args, **kwargs):
            start = time.process_time()
            try:
                return original(*args, **kwargs)
            finally:
                self.seconds[label] = self.seconds.get(label, 0.0) + time.process_time() - start

        setattr(module, name, timed)
        self._undo.append((module, name, original))

    def restore(self) -> None:
        for module, name, original in reversed(self._undo):
            setattr(module, name, original)
        self._undo.clear()


def _correspond(collection) -> dict[str, float]:
    from shapegen_core.correspond import CorrespondenceSettings, correspond, pool, proxy

    timed = _Timed()
    timed.wrap(proxy, "build_proxy", "proxy build")
    timed.wrap(pool, "register_task", "registration rounds")
    timed.wrap(proxy, "place_on_full_surface", "placement on the full surface")
    start, wall = time.process_time(), time.perf_counter()
    try:
        correspond(collection, CorrespondenceSettings(), jobs=1)
    finally:
        timed.restore()
    parts = dict(timed.seconds)
    parts["total"] = time.process_time() - start
    parts["wall"] = time.perf_counter() - wall
    return parts


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=4, help="dense meshes (default 4)")
    parser.add_argument("--vases", type=int, default=20, help="vases (default 20: bench/scale.py's vases-20)")
    parser.add_argument("--dense-folder", default="/tmp/shapegen-scale/Fish-1000000",
                        help="folder of dense PLY files (bench/scale.py's dense-1M cache)")
    args = parser.parse_args()
    from shapegen_core import __file__ as core_file
    from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
    from shapegen_core.demo_data import make_vases
    from shapegen_core.meshes.reading import read_mesh

    files = sorted(Path(args.dense_folder).glob("*.ply"))[: args.shapes]
    if len(files) < args.shapes:
        raise SystemExit(f"{args.dense_folder}: fewer than {args.shapes} PLY files (run bench/scale.py --rows dense-1M)")
    print(f"core: {Path(core_file).parent}")
    print(f"uptime before: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    collections = {
        "dense": [read_mesh(f) for f in files],
        "vases": [s.mesh for s in make_vases(args.vases, seed=0, resolution=VASE_RESOLUTION)],
    }
    results = {}
    for name, meshes in collections.items():
        prepared = prepare_meshes(meshes, PrepareSettings())
        vertices = int(sum(m.n_vertices for m in meshes) / len(meshes))
        parts = _correspond(prepared)
        results[name] = {key: value / len(meshes) for key, value in parts.items()}
        results[name]["vertices"] = vertices
        del prepared
    print(f"uptime after: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")
    labels = ["total", "proxy build", "registration rounds", "placement on the full surface"]
    print(f"\nCPU seconds per shape ({args.shapes} dense shapes, {args.vases} vases, jobs=1):")
    print("| collection | vertices | " + " | ".join(labels) + " | rest | wall |")
    print("|---|---|" + "---|" * (len(labels) + 2))
    for name, row in results.items():
        rest = row["total"] - sum(row.get(label, 0.0) for label in labels[1:])
        print(f"| {name} | {row['vertices']} | " + " | ".join(f"{row.get(label, 0.0):.2f}" for label in labels)
              + f" | {rest:.2f} | {row['wall']:.2f} |")
    dense, vases = results["dense"], results["vases"]
    print(f"\ndense / vases, CPU per shape: {dense['total'] / vases['total']:.2f}x")
    without = dense["total"] - dense.get("proxy build", 0.0)
    print(f"estimate without the proxy rebuild (Prepare's proxy reused): {without / vases['total']:.2f}x "
          f"({without:.2f} / {vases['total']:.2f} CPU s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
