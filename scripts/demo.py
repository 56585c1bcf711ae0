"""ShapeGen demo, headless (`make demo`): the main job on the built-in procedural class.

1. Generate a class of procedural vases (core/datasets.py: varied triangulations, random
   input poses) and write them as OBJ files.
2. Install the built extension (dist/) into a throwaway Blender user folder, as a user
   would, and drive its operators: Import Training Collection → Prepare.
3. Render the prepared (aligned, scaled, landmarked) shapes with Blender's Workbench
   engine into OUTPUT/intake.png.
"""

from __future__ import annotations

import argparse
import glob
import importlib
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _extension_zip() -> Path:
    machine = {"x86_64": "x64", "amd64": "x64", "arm64": "arm64", "aarch64": "arm64"}[platform.machine().lower()]
    system = {"linux": "linux", "darwin": "macos", "windows": "windows"}[platform.system().lower()]
    found = sorted(glob.glob(str(ROOT / "dist" / f"shapegen-*-{system}_{machine}.zip")))
    if not found:
        sys.exit(f"demo: no extension zip for {system}_{machine} in dist/ (run `make build`)")
    return Path(found[-1])


def install_extension(bpy) -> str:
    module = "bl_ext.user_default.shapegen"
    result = bpy.ops.extensions.package_install_files(
        filepath=str(_extension_zip()), repo="user_default", enable_on_install=True)
    if result != {"FINISHED"} or module not in bpy.context.preferences.addons:
        sys.exit("demo: the extension did not install")
    return module


def frame_camera(bpy, objects, resolution=(1600, 1000)):
    """An orthographic camera looking at the objects from the front, slightly above."""
    import numpy as np
    from mathutils import Euler, Vector

    corners = []
    for obj in objects:
        corners.extend(obj.matrix_world @ Vector(c) for c in obj.bound_box)
    corners = np.array([tuple(c) for c in corners])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    centre = (lo + hi) / 2
    scene = bpy.context.scene
    camera_data = bpy.data.cameras.new("Demo Camera")
    camera_data.type = "ORTHO"
    tilt = np.radians(80.0)
    # projected height of the grid seen at this tilt, with a margin
    width = hi[0] - lo[0]
    height = (hi[1] - lo[1]) * np.cos(tilt) + (hi[2] - lo[2]) * np.sin(tilt)
    aspect = resolution[0] / resolution[1]
    camera_data.ortho_scale = 1.08 * max(width, height * aspect)
    camera = bpy.data.objects.new("Demo Camera", camera_data)
    scene.collection.objects.link(camera)
    distance = 4 * float(np.linalg.norm(hi - lo))
    direction = Vector((0.0, -np.sin(tilt), np.cos(tilt)))
    camera.location = Vector(tuple(centre)) + distance * direction
    camera.rotation_euler = Euler((tilt, 0.0, 0.0), "XYZ")
    camera_data.clip_end = 3 * distance
    scene.camera = camera
    scene.render.resolution_x, scene.render.resolution_y = resolution


def layout_for_front_view(objects, columns: int = 6):
    """Re-place shapes on a grid in the x–z plane (rows stacked upwards) for a front view."""
    import math

    import numpy as np

    extents = np.array([np.ptp(np.array([c[:] for c in o.bound_box]), axis=0) for o in objects])
    step_x, step_z = 1.25 * extents[:, :2].max(), 1.2 * extents[:, 2].max()
    rows = math.ceil(len(objects) / columns)
    for index, obj in enumerate(objects):
        obj.location = ((index % columns) * step_x, 0.0, (rows - 1 - index // columns) * step_z)


def render_png(bpy, path: Path):
    scene = bpy.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    shading = scene.display.shading
    shading.light = "STUDIO"
    shading.color_type = "OBJECT"
    shading.show_shadows = False
    shading.show_cavity = True
    scene.render.film_transparent = False
    scene.world = scene.world or bpy.data.worlds.new("World")
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=ROOT / "demo_output")
    parser.add_argument("--shapes", type=int, default=12, help="training shapes to generate")
    parser.add_argument("--landmarks", type=int, default=800)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    output = args.output.resolve()
    output.mkdir(parents=True, exist_ok=True)

    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="shapegen-demo-user-")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import bpy

    start = time.perf_counter()
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    module = install_extension(bpy)
    datasets = importlib.import_module(f"{module}.core.datasets")

    data_dir = output / "training_data"
    shapes = datasets.make_vases(args.shapes, seed=args.seed)
    for old in data_dir.glob("*.obj"):
        old.unlink()
    datasets.write_collection(shapes, data_dir, "obj")
    print(f"demo: wrote {len(shapes)} procedural vases to {data_dir}")

    bpy.ops.shapegen.import_collection(directory=str(data_dir))
    settings = bpy.context.scene.shapegen
    settings.n_landmarks = args.landmarks
    settings.seed = args.seed
    source = settings.source_collection
    bpy.ops.shapegen.prepare()
    prepared = bpy.data.collections[f"{source.name} Prepared"]
    print(f"demo: prepared {len(shapes)} shapes in {time.perf_counter() - start:.1f} s")

    # render only the prepared collection
    bpy.context.view_layer.layer_collection.children[source.name].exclude = True
    shape_objects = [o for o in prepared.objects if "shapegen_landmarks" in o]
    layout_for_front_view(shape_objects)
    bpy.context.view_layer.update()
    for obj in shape_objects:
        obj.color = (0.82, 0.84, 0.88, 1.0)
    frame_camera(bpy, shape_objects)
    png = output / "intake.png"
    render_png(bpy, png)
    counts = [len(o["shapegen_landmarks"]) // 3 for o in shape_objects]
    print(f"demo: landmarks per shape {min(counts)}-{max(counts)} (requested {args.landmarks})")
    print(f"demo: wrote {png} ({time.perf_counter() - start:.1f} s in all)")
    import addon_utils

    addon_utils.disable(module, default_set=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
