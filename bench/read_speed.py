"""What reading a mesh file costs: `reading.read_mesh` (trimesh's reader, then intake: weld,
twins, walls, slivers, winding) against trimesh's plain load of the same file
(`trimesh.load(path, process=False, force="mesh")`: one mesh, as read_mesh makes),
paired file by file in one run.

    python bench/read_speed.py [--repeats 3] [--collections psb,tosca,bottles,cad-vases]

Collections:
* `psb`, `tosca`: every file of the real PSB and TOSCA collections (tests/shared_data.py; clean OFF files);
* `bottles`: ten CAD-like bottles modelled in Blender (bench/blender_cad.py: soups with
  UV seams, double-sided, separate parts), made when bpy can be imported (the project's
  .venv), else left out with a note;
* `cad-vases`: the PSB vases made CAD-like as bench/cad.py makes them (a label, every face
  twice, a soup with one UV per corner; OBJ).

Each file is read `--repeats` times by each reader in turn, and its fastest time per reader
is kept. Prints, per collection and overall, the median and worst ratio (read_mesh over
plain load) and the worst file; writes bench_output/read_speed.json. The target is a ratio
of at most 5 on every file.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from shapegen_core.base.errors import MeshError, MeshFileError  # noqa: E402
from shapegen_core.meshes.reading import list_mesh_files, read_mesh  # noqa: E402
from shared_data import folder_or_exit  # noqa: E402

OUTPUT = ROOT / "bench_output"
TARGET = 5.0


def collection_files(name: str) -> list[Path]:
    """Every mesh file of the real collection `name` (psb or tosca), class by class."""
    return [path for folder in sorted(folder_or_exit(name).iterdir()) if folder.is_dir()
            for path in list_mesh_files(folder)]


def bottle_files(folder: Path) -> list[Path]:
    """The Blender bottles (bench/blender_cad.py), or none when bpy is not importable."""
    try:
        import bpy  # noqa: F401
    except ImportError:
        print("bottles: left out (bpy cannot be imported here; run with the project's .venv python)")
        return []
    from blender_cad import write_bottles

    return write_bottles(folder, 10)


def cad_vase_files(folder: Path) -> list[Path]:
    """The PSB vases made CAD-like by bench/cad.py's `write_cad_obj`."""
    from cad import write_cad_obj

    rng = np.random.default_rng(0)
    paths = []
    for path in list_mesh_files(folder_or_exit("psb", "Vase")):
        mesh = read_mesh(path)
        paths.append(folder / f"{path.stem}.obj")
        write_cad_obj(mesh, paths[-1], "y", rng)
    return paths


def seconds(read, path: Path) -> float:
    start = time.perf_counter()
    read(path)
    return time.perf_counter() - start


def time_files(paths: list[Path], repeats: int) -> list[dict]:
    """Per file: the mesh's faces, the fastest read_mesh and plain load, their ratio, the
    intake's message (or why the file was refused)."""
    rows = []
    for path in paths:
        try:
            mesh = read_mesh(path)
        except (MeshError, MeshFileError) as exc:  # a damaged file of the real collections (TOSCA horse7) is named
            rows.append({"file": str(path), "refused": str(exc)})
            print(f"  {path.name}: refused ({exc})")
            continue
        ours = theirs = np.inf
        for _ in range(repeats):  # paired: the two readers alternate on the same file
            ours = min(ours, seconds(read_mesh, path))
            theirs = min(theirs, seconds(lambda p: trimesh.load(p, process=False, force="mesh"), path))
        rows.append({"file": str(path), "faces": mesh.n_faces, "read_mesh_s": ours, "plain_load_s": theirs,
                     "ratio": ours / theirs, "summary": mesh.report.summary()})
    return rows


def table(results: dict[str, list[dict]]) -> list[str]:
    lines = [f"{'collection':>10} {'files':>5} {'median':>7} {'worst':>7}  worst file (faces, read_mesh s / plain s)"]

    def line(name: str, rows: list[dict]) -> str:
        timed = [r for r in rows if "ratio" in r]
        if not timed:
            return f"{name:>10} {0:5d}"
        ratios = np.array([r["ratio"] for r in timed])
        worst = timed[int(ratios.argmax())]
        return (f"{name:>10} {len(timed):5d} {np.median(ratios):7.2f} {ratios.max():7.2f}  {Path(worst['file']).name} "
                f"({worst['faces']}, {worst['read_mesh_s']:.3f} / {worst['plain_load_s']:.3f})")

    for name, rows in results.items():
        lines.append(line(name, rows))
    lines.append(line("all", [r for rows in results.values() for r in rows]))
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--collections", default="psb,tosca,bottles,cad-vases")
    args = parser.parse_args(argv)
    OUTPUT.mkdir(exist_ok=True)
    results = {}
    with tempfile.TemporaryDirectory(prefix="read-speed-") as folder:
        for name in args.collections.split(","):
            made = Path(folder) / name
            made.mkdir()
            paths = {"psb": lambda: collection_files("psb"), "tosca": lambda: collection_files("tosca"),
                     "bottles": lambda: bottle_files(made), "cad-vases": lambda: cad_vase_files(made)}[name]()
            print(f"{name}: {len(paths)} files", flush=True)
            results[name] = time_files(paths, args.repeats)
    lines = table(results)
    print("\n".join(lines))
    over = [r for rows in results.values() for r in rows if r.get("ratio", 0) > TARGET]
    print(f"files above {TARGET:g}x: {len(over)}" + "".join(f"\n  {Path(r['file']).name} {r['ratio']:.2f}" for r in over))
    (OUTPUT / "read_speed.json").write_text(json.dumps({"table": lines, "files": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
