"""Orientation benchmark on real data: per-shape PCA vs collection consensus.

For each PSB class (Fish, Vase, Airplane, Cup; files mostly y-up) run
`prepare_collection(up_axis="y")` with align="pca" and align="consensus", count the shapes
whose orientation consensus changed, and render both results with Blender (bpy as a
module, Workbench): one mesh per prepared shape on a 5-column grid, seen from the front
(camera on -y looking towards +y, z up). Shapes consensus re-oriented are drawn red.

    python bench/orientation.py [--data DIR] [--out bench_output] [--classes Fish Vase ...]

Writes bench_output/orientation_<Class>.png (consensus) and
bench_output/orientation_<Class>_pca.png (per-shape PCA), and prints one line per class.
Needs the PSB folder (../shared/data/psb); rendering needs `bpy` (skipped without it).
Not a test: look at the pictures.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

try:
    from shapegen_core.io import read_folder
    from shapegen_core.preprocess import prepare_collection
except ImportError:  # not installed: use the source tree
    import importlib

    sys.modules["shapegen_core"] = importlib.import_module("core")
    from shapegen_core.io import read_folder  # noqa: F811
    from shapegen_core.preprocess import prepare_collection  # noqa: F811

CLASSES = ("Fish", "Vase", "Airplane", "Cup")
COLUMNS = 5


def render(prepared, changed, path: Path, title: str) -> None:
    """Grid picture of prepared shapes (normalised frame), front view, Workbench."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    extents = np.array([np.ptp(s.mesh.vertices[np.unique(s.mesh.faces)], axis=0) for s in prepared])
    step = 1.25 * float(extents[:, [0, 2]].max())
    rows = (len(prepared) + COLUMNS - 1) // COLUMNS
    for i, (shape, turned) in enumerate(zip(prepared, changed)):
        mesh = bpy.data.meshes.new(shape.name)
        mesh.from_pydata(shape.mesh.vertices.tolist(), [], shape.mesh.faces.tolist())
        mesh.update()
        obj = bpy.data.objects.new(shape.name, mesh)
        obj.location = ((i % COLUMNS) * step, 0.0, -(i // COLUMNS) * step)
        obj.color = (0.85, 0.25, 0.2, 1.0) if turned else (0.75, 0.75, 0.78, 1.0)
        scene.collection.objects.link(obj)
        label = bpy.data.curves.new(f"label_{shape.name}", type="FONT")
        label.body = shape.name + (" *" if turned else "")
        label.size = 0.08 * step
        text = bpy.data.objects.new(f"label_{shape.name}", label)
        text.location = ((i % COLUMNS) * step - 0.4 * step, -0.5 * step, -(i // COLUMNS) * step - 0.12 * step)
        text.rotation_euler = (np.pi / 2, 0.0, 0.0)
        text.color = (0.1, 0.1, 0.1, 1.0)
        scene.collection.objects.link(text)
    title_curve = bpy.data.curves.new("title", type="FONT")
    title_curve.body = title
    title_curve.size = 0.12 * step
    title_obj = bpy.data.objects.new("title", title_curve)
    title_obj.location = (-0.45 * step, -0.5 * step, 0.85 * step + 0.15 * step)
    title_obj.rotation_euler = (np.pi / 2, 0.0, 0.0)
    title_obj.color = (0.0, 0.0, 0.0, 1.0)
    scene.collection.objects.link(title_obj)

    camera_data = bpy.data.cameras.new("camera")
    camera_data.type = "ORTHO"
    width = COLUMNS * step
    height = rows * step + 0.4 * step
    camera_data.ortho_scale = 1.05 * max(width, height * 16 / 9)
    camera = bpy.data.objects.new("camera", camera_data)
    centre_x = (COLUMNS - 1) * step / 2
    centre_z = -(rows - 1) * step / 2 + 0.35 * step
    camera.location = (centre_x, -10.0 * step, centre_z)
    camera.rotation_euler = (np.pi / 2, 0.0, 0.0)  # looks along +y, z up
    camera_data.clip_end = 100.0 * step
    scene.collection.objects.link(camera)
    scene.camera = camera

    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "OBJECT"
    scene.display.shading.show_cavity = True
    scene.render.resolution_x, scene.render.resolution_y = 1280, 720
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    world = bpy.data.worlds.new("world")
    world.color = (1.0, 1.0, 1.0)
    scene.world = world
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data" / "psb")
    parser.add_argument("--out", type=Path, default=ROOT / "bench_output")
    parser.add_argument("--classes", nargs="+", default=list(CLASSES))
    parser.add_argument("--up", default="y")
    parser.add_argument("--no-render", action="store_true")
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        args.data = Path("/work/shared/data/psb")
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        import bpy  # noqa: F401

        can_render = not args.no_render
    except ImportError:
        can_render = False
        print("bpy not importable: counts only, no pictures", file=sys.stderr)

    for name in args.classes:
        folder = args.data / name
        if not folder.is_dir():
            print(f"{name}: {folder} missing, skipped")
            continue
        meshes = read_folder(folder)
        start = time.perf_counter()
        pca = prepare_collection(meshes, up_axis=args.up, align="pca")
        t_pca = time.perf_counter() - start
        start = time.perf_counter()
        consensus = prepare_collection(meshes, up_axis=args.up, align="consensus")
        t_con = time.perf_counter() - start
        changed = [s.orientation_changed for s in consensus]
        # how each changed shape was turned relative to its PCA pose
        kinds = []
        for a, b in zip(pca, consensus):
            if not b.orientation_changed:
                continue
            turn = b.transform.rotation @ a.transform.rotation.T
            up = turn[2, 2]
            kinds.append(f"{a.name}:" + ("flip" if up < -0.5 else "tilt" if up < 0.5 else
                                          f"yaw{int(round(np.degrees(np.arctan2(turn[1, 0], turn[0, 0]))))}"))
        print(f"{name}: {len(meshes)} shapes, consensus changed {sum(changed)} "
              f"({', '.join(kinds) or 'none'}); pca {t_pca:.1f} s, consensus {t_con:.1f} s", flush=True)
        if can_render:
            render(pca, [False] * len(pca), args.out / f"orientation_{name}_pca.png",
                   f"{name}: align=pca (up {args.up})")
            render(consensus, changed, args.out / f"orientation_{name}.png",
                   f"{name}: align=consensus (red = re-oriented)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
