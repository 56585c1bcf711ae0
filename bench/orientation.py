"""Orientation benchmark (issue 12): how many shapes Prepare turns, and how many it leaves
in a wrong pose, old default (consensus from each shape's PCA pose, commit 5a0b44e) vs
new default (consensus from the input pose), in one run.

Sets:
  (a) procedural classes generated upright and facing +x (vases; barrels, nearly
      symmetric top-to-bottom), random size and position, at --seeds seeds;
  (b) the same with a known subset (--perturbed shapes) turned by a random one of the 23
      non-identity axis rotations (axis permutations, half turns), or by a random turn
      about up of 45°-315° (every third perturbed shape);
  (c) the shared PSB classes (files y-up: --up y).

Counts per set: "changed" = shapes whose rotation is not the up rotation alone (for the
new default: pose_change given); "wrong" = shapes whose pose (canonical frame → prepared
frame) is more than 20° from the collection's pose, defined as the pose most shapes share
to within 20° (the procedural sets know every shape's canonical frame); "flagged" = new
pose_outlier flags; for (b) also perturbed shapes restored and unperturbed shapes
moved. PSB has no canonical frame: the counts are changed and flagged; wrong ones are
counted on the rendered pictures (render mode: both defaults drawn, turned shapes red).

    python bench/orientation.py [--seeds 20] [--shapes 12] [--no-render] [--sets a b c]

Writes bench_output/orientation_<Class>_{before,after}.png in render mode (needs bpy).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

try:
    import shapegen_core
except ImportError:  # not installed: use the source tree
    shapegen_core = importlib.import_module("core")
    sys.modules["shapegen_core"] = shapegen_core
from shapegen_core.datasets import make_barrels, make_vases  # noqa: E402
from shapegen_core.io import read_folder  # noqa: E402
from shapegen_core.preprocess import ShapeTransform, prepare_collection  # noqa: E402
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS, up_rotation, yaw_rotation  # noqa: E402

BEFORE = "5a0b44e"  # the last commit with the old default
CLASSES = ("Fish", "Vase", "Airplane", "Cup")
COLUMNS = 8
WRONG_DEGREES = 20.0


def load_before(revision: str):
    """The old core (git archive of `revision`) imported as its own package."""
    folder = Path(tempfile.mkdtemp(prefix="shapegen_before_"))
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision, "core"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    spec = importlib.util.spec_from_file_location("shapegen_before", folder / "core" / "__init__.py",
                                                  submodule_search_locations=[str(folder / "core")])
    module = importlib.util.module_from_spec(spec)
    sys.modules["shapegen_before"] = module
    spec.loader.exec_module(module)
    return importlib.import_module("shapegen_before.preprocess").prepare_collection


def angle(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def wrong_shapes(poses: list[np.ndarray]) -> list[bool]:
    """Whether each shape is more than WRONG_DEGREES from the pose most shapes share (to
    WRONG_DEGREES)."""
    close = np.array([[angle(a @ b.T) <= WRONG_DEGREES for b in poses] for a in poses])
    reference = poses[int(np.argmax(close.sum(axis=1)))]
    return [angle(p @ reference.T) > WRONG_DEGREES for p in poses]


def upright(kind: str, n: int, seed: int):
    """Consistent input: canonical (upright, facing +x) shapes, random size and position."""
    rng = np.random.default_rng(1000 + seed)
    meshes = make_barrels(n, seed=seed, pose=False) if kind == "barrels" else \
        [v.mesh for v in make_vases(n, seed=seed, resolution=(12, 18), pose=False)]
    return [m.with_vertices(ShapeTransform(np.eye(3), rng.uniform(0.5, 2), rng.uniform(-1, 1, 3))
                            .to_normalised(m.vertices)) for m in meshes]


def perturbations(n: int, count: int, seed: int) -> dict[int, np.ndarray]:
    """A known subset of `count` shapes and the turn applied to each."""
    rng = np.random.default_rng(2000 + seed)
    chosen = rng.choice(n, count, replace=False)
    return {int(i): (yaw_rotation(float(rng.uniform(45, 315))) if k % 3 == 2 else AXIS_ROTATIONS[rng.integers(1, 24)])
            for k, i in enumerate(chosen)}


def procedural(kind: str, seeds: int, n: int, count: int, methods: dict) -> None:
    for perturbed in (False, True):
        label = f"({'b' if perturbed else 'a'}) {kind}{' perturbed' if perturbed else ''}"
        for name, prepare in methods.items():
            changed = wrong = flagged = restored = moved = total = 0
            seconds = 0.0
            for seed in range(seeds):
                meshes = upright(kind, n, seed)
                turns = perturbations(n, count, seed) if perturbed else {}
                meshes = [m.with_vertices(m.vertices @ turns[i].T) if i in turns else m for i, m in enumerate(meshes)]
                start = time.perf_counter()
                prepared = prepare(meshes, up_axis="z")
                seconds += time.perf_counter() - start
                poses = [s.transform.rotation @ turns.get(i, np.eye(3)) for i, s in enumerate(prepared)]
                turned = [not np.array_equal(s.transform.rotation, np.eye(3)) for s in prepared]
                changed += sum(turned)
                off = wrong_shapes(poses)
                wrong += sum(off)
                flagged += sum(bool(getattr(s, "pose_outlier", "")) for s in prepared)
                restored += sum(not off[i] for i in turns)
                moved += sum(t for i, t in enumerate(turned) if i not in turns)
                total += len(prepared)
            extra = f", restored {restored}/{seeds * count}, unperturbed moved {moved}" if perturbed else ""
            print(f"{label:22s} {name:6s}: {total} shapes, changed {changed}, wrong {wrong}, flagged {flagged}"
                  f"{extra}; {seconds / seeds:.1f} s per collection", flush=True)


def psb(data: Path, classes, up: str, methods: dict, out: Path, can_render: bool) -> None:
    for cls in classes:
        folder = data / cls
        if not folder.is_dir():
            print(f"(c) {cls}: {folder} missing, skipped")
            continue
        meshes = read_folder(folder)
        for name, prepare in methods.items():
            start = time.perf_counter()
            prepared = prepare(meshes, up_axis=up)
            seconds = time.perf_counter() - start
            base = up_rotation(up)
            turned = [not np.allclose(s.transform.rotation, base, atol=1e-12) for s in prepared]
            flags = [s.name for s in prepared if getattr(s, "pose_outlier", "")]
            print(f"(c) {cls:16s} {name:6s}: {len(prepared)} shapes, changed {sum(turned)}, flagged {len(flags)}"
                  f" ({' '.join(flags) or '-'}); {seconds:.1f} s", flush=True)
            if name == "after":
                for s in prepared:
                    if s.pose_change or s.pose_outlier:
                        print(f"      {s.name}: {s.pose_change or '-'} | {s.pose_outlier or '-'}")
            if can_render:
                render(prepared, turned, flags, out / f"orientation_{cls}_{name}.png", f"{cls}: {name} (red = turned)")


def render(prepared, turned, flagged, path: Path, title: str) -> None:
    """Grid picture of prepared shapes (normalised frame), front view, Workbench."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    extents = np.array([np.ptp(s.mesh.vertices[np.unique(s.mesh.faces)], axis=0) for s in prepared])
    step = 1.25 * float(extents[:, [0, 2]].max())
    rows = (len(prepared) + COLUMNS - 1) // COLUMNS

    def text(body, size, location, colour):
        curve = bpy.data.curves.new(f"text_{body}", type="FONT")
        curve.body, curve.size = body, size
        obj = bpy.data.objects.new(f"text_{body}", curve)
        obj.location, obj.rotation_euler, obj.color = location, (np.pi / 2, 0.0, 0.0), colour
        scene.collection.objects.link(obj)

    for i, (shape, red) in enumerate(zip(prepared, turned)):
        mesh = bpy.data.meshes.new(shape.name)
        mesh.from_pydata(shape.mesh.vertices.tolist(), [], shape.mesh.faces.tolist())
        mesh.update()
        obj = bpy.data.objects.new(shape.name, mesh)
        x, z = (i % COLUMNS) * step, -(i // COLUMNS) * step
        obj.location = (x, 0.0, z)
        obj.color = (0.85, 0.25, 0.2, 1.0) if red else (0.75, 0.75, 0.78, 1.0)
        scene.collection.objects.link(obj)
        text(shape.name + (" !" if shape.name in flagged else ""), 0.1 * step,
             (x - 0.4 * step, -0.5 * step, z - 0.15 * step), (0.1, 0.1, 0.1, 1.0))
    text(title, 0.15 * step, (-0.45 * step, -0.5 * step, step), (0.0, 0.0, 0.0, 1.0))

    camera_data = bpy.data.cameras.new("camera")
    camera_data.type = "ORTHO"
    camera_data.ortho_scale = 1.05 * max(COLUMNS * step, (rows * step + 0.4 * step) * 16 / 9)
    camera_data.clip_end = 100.0 * step
    camera = bpy.data.objects.new("camera", camera_data)
    camera.location = ((COLUMNS - 1) * step / 2, -10.0 * step, -(rows - 1) * step / 2 + 0.35 * step)
    camera.rotation_euler = (np.pi / 2, 0.0, 0.0)  # looks along +y, z up
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "OBJECT"
    scene.render.resolution_x, scene.render.resolution_y = 1600, 900
    world = bpy.data.worlds.new("world")
    world.color = (1.0, 1.0, 1.0)
    scene.world = world
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("/work/shared/data/psb"))
    parser.add_argument("--out", type=Path, default=ROOT / "bench_output")
    parser.add_argument("--classes", nargs="+", default=list(CLASSES))
    parser.add_argument("--up", default="y")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--shapes", type=int, default=12)
    parser.add_argument("--perturbed", type=int, default=3)
    parser.add_argument("--sets", nargs="+", default=["a", "c"], help="a (with b), c")
    parser.add_argument("--before", default=BEFORE, help="git revision of the old default")
    parser.add_argument("--methods", nargs="+", default=["before", "after"])
    parser.add_argument("--no-render", action="store_true")
    args = parser.parse_args(argv)
    methods = {"before": lambda: load_before(args.before), "after": lambda: prepare_collection}
    methods = {name: methods[name]() for name in args.methods}
    can_render = False
    if not args.no_render:
        try:
            import bpy  # noqa: F401

            can_render = True
            args.out.mkdir(parents=True, exist_ok=True)
        except ImportError:
            print("bpy not importable: counts only, no pictures", file=sys.stderr)
    if "a" in args.sets:
        for kind in ("vases", "barrels"):
            procedural(kind, args.seeds, args.shapes, args.perturbed, methods)
    if "c" in args.sets:
        psb(args.data, args.classes, args.up, methods, args.out, can_render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
