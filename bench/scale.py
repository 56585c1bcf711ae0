"""Scale benchmark: time and peak memory per stage on dense meshes and large
collections, beside the figures measured before the dense-mesh and large-collection changes.

    python bench/scale.py [--quick] [--rows dense-100k,dense-1M,vases-200,...] [--jobs 2]

Rows (each runs in its own child process; peak memory is the largest summed resident
memory of that process and every process it started, sampled every 20 ms):

* dense-100k / dense-300k / dense-1M: the first `--dense-shapes` meshes (default 20) of a
  PSB class (`--psb-class`, default Fish: 4k–10k vertices) subdivided in memory
  (trimesh's midpoint subdivision, 4x the faces per step, as many steps as bring each
  mesh nearest to the target) and written as binary PLY to a cache folder outside the
  repository (`--cache`, default /tmp/shapegen-scale; never committed); then the stages of
  `shapegen fit --model ppca` on that folder: read, prepare, correspond, fit ppca, save
  (as `shapegen fit` runs them: meshes above 100k faces kept in a spill store on disk, the
  main process holding handles, core/meshes/spill.py).
* vases-20 / vases-200 / vases-1000: procedural vases (core/demo_data/vases.py make_vases,
  ~20k vertices each) through prepare, correspond and every model (ppca, gplvm, bgplvm;
  gplvm, O(N³), only up to 200 shapes unless --all-models). Prepare aligns by consensus
  at every size (above 64 shapes its pose search computes the exact cost only for the
  pairs a descriptor proposes: core/preprocess/neighbours.py); vases-20 also corresponds
  on a Dask LocalCluster (local:2) and reports the largest difference from the process
  pool.

The table prints seconds and peak GB per stage, the figures of the same row before the
issue's changes (`BEFORE`, measured with this script on the commit named there) and the
issue's targets with the measured value. `--quick`: dense-100k and vases-20 only.
Timings depend on the load: the script prints `uptime` before and after. Writes
bench_output/scale.{json,txt}.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUTPUT = ROOT / "bench_output"
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections
from shared_data import folder_or_exit  # noqa: E402

DENSE_TARGETS = {"dense-100k": 100_000, "dense-300k": 300_000, "dense-1M": 1_000_000}
VASE_ROWS = {"vases-20": 20, "vases-200": 200, "vases-1000": 1000}
ALL_ROWS = tuple(DENSE_TARGETS) + tuple(VASE_ROWS)
QUICK_ROWS = ("dense-100k", "vases-20")
#: ~20k vertices per vase: rings along the profile (about 1.3x as many around)
VASE_RESOLUTION = (115, 135)

#: Figures of each row before those changes: {row: {"shapes": N, stage: (seconds, bytes)}},
#: measured with this script on main 5dbb1d5 (dense rows; vase rows: see there) (2 jobs)
#: while other jobs kept the load of the 2-core machine at 4-10 (git log -p docs/results.md, Scale).
#: The 300k and 1M rows ran on fewer shapes to stay within the machine's memory (the 1M row's
#: Prepare of 2 shapes peaked at 15.4 GB); its ppca fit cannot run on 2 shapes.
BEFORE: dict[str, dict] = {
    "dense-100k": {"shapes": 20, "read": (12.7, 0.50e9), "prepare": (453.9, 3.66e9), "correspond": (144.8, 2.78e9),
                   "fit ppca": (0.0, 1.25e9), "save": (10.9, 1.25e9)},
    "dense-300k": {"shapes": 6, "read": (11.6, 1.10e9), "prepare": (452.1, 5.89e9), "correspond": (463.0, 7.82e9),
                   "fit ppca": (0.0, 0.99e9), "save": (7.4, 0.99e9)},
    "dense-1M": {"shapes": 2, "read": (72.7, 2.78e9), "prepare": (376.9, 15.38e9), "correspond": (1111.0, 6.89e9)},
    # the vase rows before the large-collection changes (main 9c9d469, load 3-9;
    # vases-200 prepared with align pca, vases-1000 stopped in Prepare; a peak not recorded: 0)
    "vases-20": {"shapes": 20, "make": (0.3, 0.12e9), "prepare": (131.0, 0.77e9), "correspond": (85.9, 0.82e9),
                 "correspond (dask local:2)": (66.3, 0.97e9), "fit ppca": (0.0, 0.64e9),
                 "fit gplvm": (0.2, 0.64e9), "fit bgplvm": (0.4, 0.64e9)},
    "vases-200": {"shapes": 200, "prepare": (957.7, 5.54e9), "correspond": (173.7, 10.8e9), "fit ppca": (0.0, 0.0),
                  "fit gplvm": (4.2, 0.0), "fit bgplvm": (1.4, 0.0)},
    "vases-1000": {"shapes": 1000, "make": (42.0, 2.0e9), "prepare": "stopped after 1920 s"},
}


# ---------------------------------------------------------------------------- memory
def _tree_rss(root: int) -> int:
    """Summed resident memory (bytes) of process `root` and all its descendants."""
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        try:
            with open(f"/proc/{pid}/statm") as handle:
                total += int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
            for task in os.listdir(f"/proc/{pid}/task"):
                with open(f"/proc/{pid}/task/{task}/children") as handle:
                    todo.extend(int(child) for child in handle.read().split())
        except (FileNotFoundError, ProcessLookupError, ValueError):
            continue
    return total


class TreeMemory:
    """Samples the summed RSS of this process tree every `interval` s; `peak()` since the
    last `reset()`."""

    def __init__(self, interval: float = 0.02):
        self.interval, self._peak, self._stop = interval, 0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        pid = os.getpid()
        while not self._stop.is_set():
            self._peak = max(self._peak, _tree_rss(pid))
            time.sleep(self.interval)

    def reset(self) -> None:
        self._peak = _tree_rss(os.getpid())

    def peak(self) -> int:
        self._peak = max(self._peak, _tree_rss(os.getpid()))
        return self._peak

    def stop(self) -> None:
        self._stop.set()


def _read(read_folder, folder, jobs, spill=None):
    """The folder read as `shapegen fit` reads it: in `jobs` processes, the dense meshes
    kept in the run's spill store (core/meshes/spill.py). The core before the dense-mesh
    changes reads in this process only; before the spill store, every mesh stays in memory."""
    try:
        return read_folder(folder, jobs=jobs, **({} if spill is None else {"spill": spill}))
    except TypeError:
        return read_folder(folder)


def _spill_store(stack, read_folder):
    """The row's spill store (`shapegen fit` keeps one per run), entered on `stack`; None
    for a core whose `read_folder` takes none (asked of the function itself: with the
    editable install, `shapegen_core.meshes.spill` imports even beside an older core on
    PYTHONPATH)."""
    import inspect

    if "spill" not in inspect.signature(read_folder).parameters:
        return None
    from shapegen_core.meshes.spill import SpillStore

    return stack.enter_context(SpillStore())


def _cpu_seconds() -> float:
    """User + system CPU time of this process and of its finished child processes (a
    worker pool's, once it is closed): the work, whatever the load (wall time on an idle
    machine with 2 cores is about half of it for the parallel stages)."""
    import resource

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


# ---------------------------------------------------------------------------- inputs
def dense_folder(cache: Path, psb_class: str, target: int, shapes: int) -> Path:
    """A folder of `shapes` PLY meshes of `psb_class` subdivided to about `target` vertices
    each (cached; written once)."""
    import trimesh

    from shapegen_core.meshes.reading import read_mesh

    folder = cache / f"{psb_class}-{target}"
    folder.mkdir(parents=True, exist_ok=True)
    source = folder_or_exit("psb", psb_class)
    sources = sorted(source.glob("*.off"), key=lambda p: int(p.stem))
    if len(sources) < shapes:
        raise SystemExit(f"{source}: {len(sources)} meshes, fewer than --dense-shapes {shapes}")
    for path in sources[:shapes]:
        out = folder / f"{psb_class.lower()}_{path.stem}.ply"
        if out.exists():
            continue
        mesh = read_mesh(path)
        steps = max(0, int(round(np.log(target / mesh.n_vertices) / np.log(4.0))))
        vertices, faces = mesh.vertices, mesh.faces
        for _ in range(steps):
            vertices, faces = trimesh.remesh.subdivide(vertices, faces)
        dense = trimesh.Trimesh(vertices, faces, process=False)
        tmp = out.with_name(f".{out.name}.tmp.ply")
        dense.export(tmp, encoding="binary")
        tmp.rename(out)
    return folder


# ---------------------------------------------------------------------------- child
def run_row(row: str, args) -> dict:
    """The stages of one row in this process: {"stages": {stage: [seconds, peak bytes]}, ...}."""
    from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
    from shapegen_core.correspond import CorrespondenceSettings, correspond
    from shapegen_core.meshes.reading import read_folder
    try:
        from shapegen_core.models.scaling import CUBIC_NOTE_SHAPES
    except ImportError:  # the core before the dense-mesh changes (the "before" figures)
        CUBIC_NOTE_SHAPES = 200
    from shapegen_core.app.fit_settings import FitSettings
    from shapegen_core.app.pipeline import fit_shape_model

    memory = TreeMemory()
    stages: dict[str, list] = {}
    info: dict = {"row": row}

    def stage(name, work):
        memory.reset()
        start, cpu = time.perf_counter(), _cpu_seconds()
        value = work()
        stages[name] = [time.perf_counter() - start, memory.peak(), _cpu_seconds() - cpu]
        print(f"  {row}: {name} {stages[name][0]:.1f} s, {stages[name][1] / 1e9:.2f} GB, cpu {stages[name][2]:.1f} s",
              file=sys.stderr, flush=True)
        return value

    align = args.align or "consensus"
    prepare_settings = PrepareSettings(up_axis="y" if row in DENSE_TARGETS else "z", align=align)
    info["align"] = align
    stack = ExitStack()  # the dense rows' spill store, removed at the end of the row
    if row in DENSE_TARGETS:
        folder = dense_folder(Path(args.cache), args.psb_class, DENSE_TARGETS[row], args.dense_shapes)
        spill = _spill_store(stack, read_folder)
        meshes = stage("read", lambda: _read(read_folder, folder, args.jobs, spill))
        models = ("ppca",)
    else:
        from shapegen_core.demo_data import make_vases

        meshes = stage("make", lambda: [s.mesh for s in make_vases(VASE_ROWS[row], seed=0, resolution=VASE_RESOLUTION,
                                                                     pose=not args.landmarks_only)])
        models = tuple(args.models.split(","))
        if VASE_ROWS[row] > CUBIC_NOTE_SHAPES and not args.all_models and "gplvm" in models:
            models = tuple(m for m in models if m != "gplvm")  # hours: measured on fewer, see docs
            try:
                from shapegen_core.models.scaling import size_note
                info["gplvm note"] = size_note("gplvm", VASE_ROWS[row])  # what a gplvm fit says
            except ImportError:
                pass
    info["shapes"] = len(meshes)
    info["vertices"] = int(np.mean([m.n_vertices for m in meshes]))
    if args.landmarks_only and row in VASE_ROWS:
        info["align"] = "landmarks only"
        prepared = stage("landmarks", lambda: landmarks_only(meshes, prepare_settings))
    else:
        prepared = stage("prepare", lambda: prepare_meshes(meshes, prepare_settings))
    del meshes
    corr = stage("correspond", lambda: correspond(prepared, CorrespondenceSettings(), jobs=args.jobs))
    info["median_residual"] = float(np.median(corr.residuals))
    if args.dask and row in VASE_ROWS and VASE_ROWS[row] <= 20:
        on_dask = stage("correspond (dask local:2)", lambda: correspond(prepared, CorrespondenceSettings(),
                                                                         scheduler="local:2"))
        info["dask_max_difference"] = float(np.abs(on_dask.points - corr.points).max())
    for model in models:
        settings = FitSettings(prepare=prepare_settings, model=model)
        fitted = stage(f"fit {model}", lambda: fit_shape_model([s.mesh for s in prepared.shapes], corr, settings))
        if model == models[0]:
            out = Path(args.cache) / f"{row}-model.npz"
            stage("save", lambda: fitted.save(out))
            out.unlink()
        del fitted
    stack.close()
    memory.stop()
    info["stages"] = stages
    return info


def landmarks_only(meshes, settings):
    """A prepared collection of meshes made upright and facing alike (make_vases with
    pose=False), left in their frame: Prepare's landmarks without its alignment, to time
    the correspondence of a large collection on its own (--landmarks-only)."""
    from shapegen_core.preprocess.collection import PreparedCollection
    from shapegen_core.preprocess.landmarks import select_landmarks
    from shapegen_core.preprocess.transform import PreparedShape, ShapeTransform

    shapes = [PreparedShape(mesh, ShapeTransform.identity()) for mesh in meshes]
    landmarks = [select_landmarks(mesh, settings.n_landmarks, seed=settings.seed + i) for i, mesh in enumerate(meshes)]
    return PreparedCollection(shapes, landmarks, settings)


# ---------------------------------------------------------------------------- table
def _cell(value) -> str:
    if value is None or isinstance(value, str):
        return value or "—"
    return f"{value[0]:7.1f} s " + (f"{value[1] / 1e9:5.2f} GB" if value[1] else "    — GB")


def table(results: list[dict]) -> str:
    lines = ["| row | shapes | vertices | stage | now | cpu | before |", "|---|---|---|---|---|---|---|"]
    for result in results:
        row = result["row"]
        before = BEFORE.get(row, {})
        for name, value in result["stages"].items():
            old = before.get(name)
            note = "" if old is None or before.get("shapes") == result["shapes"] else f" ({before['shapes']} shapes)"
            cpu = f"{value[2]:.1f} s" if len(value) > 2 else "—"
            lines.append(f"| {row} | {result['shapes']} | {result['vertices']} | {name} | {_cell(value)} | {cpu} | "
                         f"{_cell(old)}{note} |")
        total = [sum(v[0] for k, v in result["stages"].items() if k not in ("make",)),
                 max(v[1] for v in result["stages"].values())]
        lines.append(f"| {row} | {result['shapes']} | {result['vertices']} | **total** | {_cell(total)} | | |")
        if result.get("gplvm note"):
            lines.append(f"| {row} | {result['shapes']} | {result['vertices']} | fit gplvm | not run: "
                         f"{result['gplvm note']} | | |")
    return "\n".join(lines)


def _per_shape(result: dict, stage: str) -> float:
    return result["stages"][stage][0] / result["shapes"]


def targets(results: list[dict]) -> str:
    """The issue's targets beside what this run measured (rows it did not run: —)."""
    by_row = {r["row"]: r for r in results}
    lines = ["| target | measured |", "|---|---|"]
    dense = by_row.get("dense-1M")
    if dense:
        seconds = sum(v[0] for k, v in dense["stages"].items() if k in ("read", "prepare", "correspond", "fit ppca",
                                                                          "save"))
        peak = max(v[1] for v in dense["stages"].values())
        lines.append(f"| {dense['shapes']} x ~1M vertices, fit ppca (read..save) <= 180 s, <= 2 GB | "
                     f"{seconds:.0f} s, {peak / 1e9:.2f} GB |")
    small = by_row.get("vases-20")
    if dense and small:
        ratio = _per_shape(dense, "correspond") / _per_shape(small, "correspond")
        lines.append(f"| correspond time per shape, ~{dense['vertices'] // 1000}k / ~{small['vertices'] // 1000}k "
                     f"vertices <= 2x | {ratio:.2f}x |")
    large = by_row.get("vases-1000")
    if large:
        seconds, peak = large["stages"]["correspond"][:2]
        lines.append(f"| 1000 x 20k correspond <= 900 s, <= 4 GB | {seconds:.0f} s, {peak / 1e9:.2f} GB |")
    if small and "dask_max_difference" in small:
        lines.append(f"| Dask LocalCluster == pool to 1e-12 | max |difference| {small['dask_max_difference']:.1e} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"rows {', '.join(QUICK_ROWS)} only")
    parser.add_argument("--rows", default=",".join(ALL_ROWS), help="comma-separated rows (default all)")
    parser.add_argument("--dense-shapes", type=int, default=20, help="meshes per dense row (default 20)")
    parser.add_argument("--psb-class", default="Fish", help="PSB class of the dense rows (default Fish)")
    parser.add_argument("--models", default="ppca,gplvm,bgplvm", help="models of the vase rows")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes for reading and correspondence (default 2)")
    parser.add_argument("--cache", default="/tmp/shapegen-scale", help="folder of the dense PLY files")
    parser.add_argument("--align", default=None, choices=("consensus", "pca", "none"),
                        help="Prepare's align (default consensus)")
    parser.add_argument("--all-models", action="store_true", help="also gplvm above 200 shapes (N³: hours)")
    parser.add_argument("--landmarks-only", action="store_true",
                        help="vase rows: vases made upright, only Prepare's landmarks (times correspondence alone)")
    parser.add_argument("--no-dask", dest="dask", action="store_false",
                        help="skip the Dask LocalCluster comparison of the vases-20 row")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--label", default="now", help="name of this run in the json output")
    parser.add_argument("--output", default=str(OUTPUT), help="folder of scale.txt / scale.json (default bench_output)")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(run_row(args.child, args)))
        return 0
    rows = QUICK_ROWS if args.quick else tuple(r.strip() for r in args.rows.split(",") if r.strip())
    unknown = [r for r in rows if r not in ALL_ROWS]
    if unknown:
        parser.error(f"unknown rows {unknown}; choose from {', '.join(ALL_ROWS)}")
    if any(row in DENSE_TARGETS for row in rows):
        folder_or_exit("psb", args.psb_class)  # before any row runs
    load = [subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()]
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    results = []
    for row in rows:
        command = [sys.executable, __file__, "--child", row, "--dense-shapes", str(args.dense_shapes),
                   "--psb-class", args.psb_class, "--models", args.models, "--jobs", str(args.jobs),
                   "--cache", args.cache] + (["--all-models"] if args.all_models else []) + \
            (["--align", args.align] if args.align else []) + \
            (["--landmarks-only"] if args.landmarks_only else []) + \
            ([] if args.dask else ["--no-dask"])
        done = subprocess.run(command, stdout=subprocess.PIPE, text=True)
        if done.returncode != 0:
            print(f"{row}: failed (exit {done.returncode})", file=sys.stderr)
            continue
        results.append(json.loads(done.stdout.strip().splitlines()[-1]))
        now = load + [subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()]
        text = table(results) + "\n\n" + targets(results) + "\nload: " + " / ".join(now) + "\n"
        (output / "scale.txt").write_text(text)  # after every row: a long run keeps what it measured
        (output / "scale.json").write_text(json.dumps({"label": args.label, "load": now, "rows": results}, indent=1))
    print((output / "scale.txt").read_text() if results else "no row finished")
    return 0


if __name__ == "__main__":
    sys.exit(main())
