"""Render samples of articulated classes: TOSCA people (man + woman), cat, dog and horse and
the procedural quadrupeds, one row per class and start, a training shape first.

    .venv/bin/python scripts/render_samples.py [--tosca DIR] [--work bench_output/samples_articulated]
        [--starts default,closest] [--samples 8] [--seed 0] [--output docs/samples_articulated.png]

From scratch, step by step (each step skipped when its output is already in --work):
1. the collections: links to the TOSCA files (people: the man and woman files, not the
   gorilla) and the procedural quadrupeds (core/demo_data/ `make_quadrupeds`) as OBJ files;
2. `shapegen fit FOLDER --up z --skip-unreadable` with the defaults ("default": the start
   the collection chooses, auto) and with `--initialisation closest` ("closest": the
   template as it is, the thesis' start): WORK/<start>/<class>.npz;
3. `shapegen sample MODEL -n 8 --seed 0 --keep-failed`: WORK/<start>/<class>_samples/
   (a run that falls short of 8 passing samples writes only its failing ones, to failed/:
   the row then shows those, in red);
4. Blender as a module, headless: one row per class and start, the model's correspondence
   template (a training shape, grey) first, then the samples (blue), each row turned so its
   template's long horizontal axis runs across the picture, then --azimuth (30°) towards the
   camera, seen a little from above. Camera and light are the demo's (scripts/demo.py); the
   PNG is cut to 128 colours (~600 KB).
The fits run one after the other, each with --jobs (default 1: the machine is shared).
"""

from __future__ import annotations

import argparse
import atexit
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections
from shared_data import shared_path  # noqa: E402

CLASSES = ("people", "cat", "dog", "horse", "quadrupeds")
STARTS = {"default": [], "closest": ["--initialisation", "closest"]}
COLOURS = {"training": (0.8, 0.82, 0.86, 1.0), "sample": (0.45, 0.65, 0.95, 1.0), "failed": (0.95, 0.35, 0.3, 1.0)}


def shapegen(*arguments: str, log: Path) -> int:
    """Run the project's CLI (the interpreter's own install) with its output in `log`."""
    command = [sys.executable, "-m", "shapegen_core.app.cli", *arguments]
    print("$ shapegen " + " ".join(arguments), flush=True)
    with open(log, "w") as out:
        return subprocess.run(command, stdout=out, stderr=subprocess.STDOUT).returncode


def collections(tosca: Path, work: Path, quadrupeds: int) -> dict[str, Path]:
    """The class folders under WORK/data (links to the TOSCA files, quadrupeds written)."""
    folders = {}
    for name in CLASSES:
        folder = work / "data" / name
        folders[name] = folder
        if folder.is_dir() and any(folder.iterdir()):
            continue
        folder.mkdir(parents=True, exist_ok=True)
        if name == "quadrupeds":
            from shapegen_core.demo_data import make_quadrupeds, write_collection

            write_collection(make_quadrupeds(quadrupeds, seed=0), folder)
            continue
        source = tosca / name
        files = sorted(source.glob("*.off"))
        if name == "people":  # man and woman: different people in different poses; the gorilla is another body
            files = [f for f in files if "_man_" in f.name or "_woman_" in f.name]
        if not files:
            sys.exit(f"render_samples: no .off files in {source}")
        for file in files:
            (folder / file.name).symlink_to(file.resolve())
    return folders


def fit_and_sample(folders: dict[str, Path], work: Path, args) -> None:
    for start in args.starts:
        out = work / start
        out.mkdir(parents=True, exist_ok=True)
        for name, folder in folders.items():
            model, samples = out / f"{name}.npz", out / f"{name}_samples"
            if not model.exists():
                begin = time.perf_counter()
                # --skip-unreadable: TOSCA's horse7.off holds fewer lines than its header declares
                code = shapegen("fit", str(folder), "--up", "z", "--skip-unreadable", "--jobs", str(args.jobs),
                                *STARTS[start],
                                "-o", str(model), log=out / f"{name}_fit.log")
                if code:
                    sys.exit(f"render_samples: fit failed ({code}), see {out / f'{name}_fit.log'}")
                print(f"  fitted in {time.perf_counter() - begin:.0f} s", flush=True)
            if not samples.exists():
                code = shapegen("sample", str(model), "-n", str(args.samples), "--seed", str(args.seed),
                                "--keep-failed", "--jobs", "1", "-o", str(samples), log=out / f"{name}_sample.log")
                if code not in (0, 2):
                    sys.exit(f"render_samples: sample failed ({code}), see {out / f'{name}_sample.log'}")


def row_meshes(model_path: Path, samples: Path):
    """(label of the start taken, training mesh, [(sample mesh, kind)]) of one row, all in
    the axes the CLI writes samples in."""
    from shapegen_core.meshes.reading import read_mesh
    from shapegen_core.meshes.mesh import Mesh
    from shapegen_core.app.shape_model import GenerativeShapeModel

    model = GenerativeShapeModel.load(model_path)
    corr = model.correspondence
    template = model.meshes[model.shape_index(corr.template_name)]
    reference = Mesh(template.vertices @ model.file_axes, template.faces, name=template.name)
    found = [(read_mesh(p), "sample") for p in sorted(samples.glob("sample_*.obj"))]
    found += [(read_mesh(p), "failed") for p in sorted((samples / "failed").glob("sample_*.obj"))]
    return corr.start_used, reference, found


def turn_of(vertices):
    """Rotation about z (3 × 3) that lays the long horizontal axis of `vertices` along x."""
    import numpy as np

    xy = vertices[:, :2] - vertices[:, :2].mean(axis=0)
    _, vectors = np.linalg.eigh(xy.T @ xy)
    a = np.arctan2(vectors[1, -1], vectors[0, -1])
    c, s = np.cos(-a), np.sin(-a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def render(rows, output: Path, azimuth: float, cell: int) -> None:
    import bpy
    import numpy as np

    from demo import frame_camera, render_png  # the demo's camera and light, shared

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    sheet = bpy.data.collections.new("Samples")
    bpy.context.scene.collection.children.link(sheet)
    a = np.radians(azimuth)
    view = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    placed = []  # (row, column, vertices, faces, kind)
    for r, (_, reference, found) in enumerate(rows):
        turn = view @ turn_of(reference.vertices)
        cells = [(mesh.vertices @ turn.T, mesh.faces, kind) for mesh, kind in [(reference, "training"), *found]]
        # each row at its own scale (the classes' model frames differ in size): the row's
        # typical shape fills a cell; within a row sizes compare
        scale = 1.0 / float(np.median([np.ptp(v[:, [0, 2]], axis=0).max() for v, _, _ in cells]))
        floor = float(cells[0][0][:, 2].min())
        for c, (v, faces, kind) in enumerate(cells):
            v = scale * (v - np.array([*(v[:, :2].min(axis=0) + v[:, :2].max(axis=0)) / 2, floor]))
            placed.append((r, c, v, faces, kind))
    extents = np.array([np.ptp(v, axis=0) for _, _, v, _, _ in placed])
    step_x, step_z = 1.15 * np.percentile(extents[:, 0], 90), 1.15 * np.percentile(extents[:, 2], 90)
    objects = []
    for r, c, v, faces, kind in placed:
        data = bpy.data.meshes.new(f"row {r} cell {c}")
        data.from_pydata(v.astype(np.float64).tolist(), [], faces.tolist())
        obj = bpy.data.objects.new(data.name, data)
        obj.location = (c * step_x, 0.0, (len(rows) - 1 - r) * step_z)
        obj.color = COLOURS[kind]
        sheet.objects.link(obj)
        objects.append(obj)
    for r, (label, _, _) in enumerate(rows):
        text = bpy.data.curves.new(f"label {r}", "FONT")
        text.body = label
        text.size = 0.13 * step_z
        text.align_x = "RIGHT"
        label_obj = bpy.data.objects.new(f"label {r}", text)
        label_obj.location = (-0.6 * step_x, 0.0, (len(rows) - 1 - r) * step_z + 0.35 * step_z)
        label_obj.rotation_euler = (np.pi / 2, 0.0, 0.0)
        label_obj.color = (0.95, 0.95, 0.95, 1.0)
        sheet.objects.link(label_obj)
        objects.append(label_obj)
    bpy.context.view_layer.update()
    columns = 1 + max(len(found) for _, _, found in rows)
    frame_camera(bpy, objects, resolution=(int(cell * (columns + 2.2)), int(cell * 0.95 * len(rows))))
    render_png(bpy, output)
    from PIL import Image  # 128 colours, no dithering: the picture stays under ~600 KB

    Image.open(output).convert("RGB").quantize(colors=128, dither=Image.Dither.NONE).save(output, optimize=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tosca", type=Path, default=shared_path("tosca"),
                        help="TOSCA folder: cat/, dog/, horse/, people/ (default: %(default)s)")
    parser.add_argument("--work", type=Path, default=ROOT / "bench_output" / "samples_articulated",
                        help="collections, models, samples and logs (kept: a second run only renders)")
    parser.add_argument("--starts", default="default,closest", help="comma-separated: default, closest")
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quadrupeds", type=int, default=12, help="procedural quadrupeds to fit on")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes of each fit")
    parser.add_argument("--azimuth", type=float, default=30.0, help="degrees the rows turn towards the camera")
    parser.add_argument("--cell", type=int, default=150, help="pixels per shape")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "samples_articulated.png")
    args = parser.parse_args()
    args.starts = [s.strip() for s in args.starts.split(",") if s.strip()]
    unknown = [s for s in args.starts if s not in STARTS]
    if unknown:
        parser.error(f"--starts: unknown {', '.join(unknown)} (known: {', '.join(STARTS)})")
    work = args.work.resolve()
    folders = collections(args.tosca, work, args.quadrupeds)
    fit_and_sample(folders, work, args)
    rows = []
    for name in CLASSES:
        for start in args.starts:
            used, reference, found = row_meshes(work / start / f"{name}.npz", work / start / f"{name}_samples")
            failed = sum(kind == "failed" for _, kind in found)
            label = f"{name}, {start} ({used})" + (f", {failed} failed" if failed else "")
            rows.append((label, reference, found))
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="shapegen-render-samples-")
    atexit.register(shutil.rmtree, os.environ["BLENDER_USER_RESOURCES"], True)
    render(rows, args.output.resolve(), args.azimuth, args.cell)
    print(f"wrote {args.output} ({args.output.stat().st_size // 1024} KB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
