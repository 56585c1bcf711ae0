"""Regression table of Prepare's orientation decisions and part-label transfer on the
PSB classes, paired against other git revisions.

For every class of the real PSB collection (tests/shared_data.py; all 20 shapes each, files read with up y, as
`shapegen correspond --up y` reads them): Prepare at its defaults (`PrepareSettings(up_axis="y")`),
its decision for each shape (kept, turned how, flagged why), and the correspondence at
its defaults (`CorrespondenceSettings()`) scored by part-label transfer: the share of
landmarks whose face carries the part label of the template's landmark (as
bench/correspondence.py part 3 scores it), averaged over the shapes other than the
template.

Each version runs in its own process with `shapegen_core` taken from that version's
`core/` (`git archive` of a revision; the working tree as "now"), so a revision is
measured with its own reading, Prepare and correspondence. A revision's results are kept
in bench_output/label_transfer/<commit>.json and reused; the working tree always runs.

    python bench/label_transfer_regression.py [--revisions a833ff8 main] [--classes Airplane Cup]
        [--decisions-only] [--without-now] [--jobs 1]

Prints the paired label-transfer table (one column per version) and each shape whose
decision differs between versions. Run it before resolving any change to Prepare.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from psb_labels import face_labels  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections
from shared_data import folder_or_exit  # noqa: E402

CACHE = ROOT / "bench_output" / "label_transfer"
CLASSES = ("Airplane", "Cup", "Fish", "Vase")


# ---------------------------------------------------------------------------- one version (child process)
def decision(shape) -> dict:
    """What Prepare did to one shape's pose: kept, turned (how), flagged (why)."""
    import numpy as np

    from shapegen_core.preprocess.rotations import describe_rotation

    rotation = np.asarray(getattr(shape, "pose_rotation", np.eye(3)), dtype=float)
    turned = bool(getattr(shape, "pose_change", ""))
    return {"turn": describe_rotation(rotation) if turned else "kept",
            "flag": getattr(shape, "pose_outlier", "") or "",
            "change": getattr(shape, "pose_change", "") or "",
            "rotation": rotation.tolist()}


def measure_class(name: str, jobs: int, decisions_only: bool) -> dict:
    """Prepare and (unless `decisions_only`) correspond one PSB class at the defaults."""
    import numpy as np

    try:
        from shapegen_core.meshes.reading import read_folder
        from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
    except ModuleNotFoundError:  # a revision from before core/ was in layers
        from shapegen_core.collection import PrepareSettings, prepare_meshes
        from shapegen_core.io import read_folder

    folder = folder_or_exit("psb", name)
    meshes = read_folder(folder)
    start = time.perf_counter()
    prepared = prepare_meshes(meshes, PrepareSettings(up_axis="y"))
    out = {"shapes": len(meshes), "prepare_seconds": time.perf_counter() - start,
           "decisions": {s.name: decision(s) for s in prepared.shapes}}
    if decisions_only:
        return out
    from shapegen_core.correspond import CorrespondenceSettings, correspond

    labels = {m.name: face_labels(folder / f"{m.name}.off", m) for m in meshes}
    start = time.perf_counter()
    result = correspond(prepared, CorrespondenceSettings(), jobs=jobs)
    ref = result.names.index(result.template_name)
    ref_labels = labels[result.template_name][result.face_index[ref]]
    per_shape = {shape: float(np.mean(labels[shape][result.face_index[m]] == ref_labels))
                 for m, shape in enumerate(result.names) if m != ref}
    out.update({"accuracy": float(np.mean(list(per_shape.values()))), "accuracy_per_shape": per_shape,
                "template": result.template_name, "outliers": int(np.sum(result.outliers)),
                "correspond_seconds": time.perf_counter() - start})
    return out


def child(args) -> int:
    results = {}
    for name in args.classes:
        results[name] = measure_class(name, args.jobs, args.decisions_only)
        row = results[name]
        print(f"  {args.child}: {name} " + (f"{100 * row['accuracy']:.1f} % " if "accuracy" in row else "")
              + f"turned {sum(d['turn'] != 'kept' for d in row['decisions'].values())}, "
              f"flagged {sum(bool(d['flag']) for d in row['decisions'].values())}", flush=True)
    Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


# ---------------------------------------------------------------------------- the paired table (parent)
def commit_of(revision: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", f"{revision}^{{commit}}"], check=True,
                          capture_output=True, text=True).stdout.strip()


def package_of(revision: str | None) -> Path:
    """A folder whose `shapegen_core` is the core of `revision` (None: the working tree)."""
    folder = Path(tempfile.mkdtemp(prefix="shapegen_labels_"))
    if revision is None:
        (folder / "shapegen_core").symlink_to(ROOT / "core")
        return folder
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision, "core"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    (folder / "core").rename(folder / "shapegen_core")
    return folder


def run_version(label: str, revision: str | None, args) -> dict:
    """One version's results: from the cache (a revision, every class measured the same
    way) or measured now in a child process."""
    cache = None
    if revision is not None:
        cache = CACHE / f"{commit_of(revision)}{'-decisions' if args.decisions_only else ''}.json"
        if cache.is_file():
            cached = json.loads(cache.read_text())
            if all(name in cached for name in args.classes):
                return cached
    package = package_of(revision)
    out = Path(tempfile.mkdtemp(prefix="shapegen_labels_out_")) / "results.json"
    env = {**os.environ, "PYTHONPATH": str(package)}
    command = [sys.executable, str(Path(__file__).resolve()), "--child", label, "--json", str(out),
               "--jobs", str(args.jobs), "--classes", *args.classes] + (["--decisions-only"] if args.decisions_only
                                                                         else [])
    subprocess.run(command, check=True, env=env, cwd=str(package))
    results = json.loads(out.read_text())
    if cache is not None:
        CACHE.mkdir(parents=True, exist_ok=True)
        previous = json.loads(cache.read_text()) if cache.is_file() else {}
        cache.write_text(json.dumps({**previous, **results}, indent=1))
    return results


def summary(d: dict) -> str:
    words = d["turn"]
    if d["flag"]:
        words += f", flagged ({d['flag'].split(':')[0]})"
    return words


def table(versions: dict[str, dict], classes) -> list[str]:
    lines = ["| class | " + " | ".join(versions) + " |", "|---|" + "---|" * len(versions)]
    for name in classes:
        cells = []
        for results in versions.values():
            row = results[name]
            turned = sum(d["turn"] != "kept" for d in row["decisions"].values())
            flagged = sum(bool(d["flag"]) for d in row["decisions"].values())
            accuracy = f"{100 * row['accuracy']:.1f} % · " if "accuracy" in row else ""
            cells.append(f"{accuracy}{turned} turned, {flagged} flagged")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "Shapes whose decision differs between versions:", "",
              "| class | shape | " + " | ".join(versions) + " |", "|---|---|" + "---|" * len(versions)]
    for name in classes:
        shapes = list(next(iter(versions.values()))[name]["decisions"])
        for shape in shapes:
            words = [summary(results[name]["decisions"][shape]) for results in versions.values()]
            if len(set(words)) > 1:
                accuracy = [results[name].get("accuracy_per_shape", {}).get(shape) for results in versions.values()]
                lines.append(f"| {name} | {shape} | " + " | ".join(
                    w + (f" · {100 * a:.1f} %" if a is not None else "") for w, a in zip(words, accuracy)) + " |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--revisions", nargs="*", default=["a833ff8", "main"],
                        help="git revisions measured beside the working tree (cached by commit)")
    parser.add_argument("--classes", nargs="+", default=list(CLASSES))
    parser.add_argument("--decisions-only", action="store_true", help="Prepare's decisions only, no correspondence")
    parser.add_argument("--without-now", action="store_true", help="only the revisions, not the working tree")
    parser.add_argument("--jobs", type=int, default=1, help="correspondence processes")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--json", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        return child(args)
    for name in args.classes:  # every class there before any version runs
        folder_or_exit("psb", name)
    versions = {}
    for revision in args.revisions:
        versions[revision] = run_version(revision, revision, args)
    if not args.without_now:
        versions["now"] = run_version("now", None, args)
    print()
    print("\n".join(table(versions, args.classes)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
