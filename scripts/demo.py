"""ShapeGen demo, headless (`make demo`): the main job on the built-in procedural class.

1. Generate a class of procedural vases (core/demo_data/: varied triangulations, random
   input poses) and write them as OBJ files.
2. Install the built extension (dist/) into a throwaway Blender user folder, as a user
   would, and drive its operators: Import Training Collection → Prepare. Render the
   prepared (aligned, scaled, landmarked) shapes into OUTPUT/intake.png.
3. Fit: correspondence (groupwise non-rigid ICP) → Bayesian GP-LVM, with the core shipped
   inside the installed extension; save OUTPUT/model.npz.
4. Generate: 8 samples and a morph row (straight latent line between the two training
   shapes farthest apart in latent space), meshed by embedded deformation, rendered by
   Blender beside the training shapes into the contact sheet OUTPUT/shapegen_demo.png.
"""

from __future__ import annotations

import argparse
import atexit
import glob
import importlib
import os
import platform
import shutil
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


def layout_for_front_view(objects, columns: int = 8):
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
    parser.add_argument("--shapes", type=int, default=20, help="training shapes to generate")
    parser.add_argument("--landmarks", type=int, default=800)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    output = args.output.resolve()
    output.mkdir(parents=True, exist_ok=True)

    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="shapegen-demo-user-")
    # registered before bpy is imported, so it runs after bpy's own exit handlers (atexit
    # runs last-registered first): the throwaway user folder goes on every exit
    atexit.register(shutil.rmtree, os.environ["BLENDER_USER_RESOURCES"], True)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    import bpy

    start = time.perf_counter()
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    module = install_extension(bpy)
    datasets = importlib.import_module(f"{module}.core.demo_data")

    data_dir = output / "training_data"
    shapes = datasets.make_vases(args.shapes, seed=args.seed)
    for old in data_dir.glob("*.obj"):
        old.unlink()
    datasets.write_collection(shapes, data_dir, "obj")
    print(f"demo: wrote {len(shapes)} procedural vases to {data_dir}")

    bpy.ops.shapegen.import_collection(directory=str(data_dir))
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = args.landmarks
    settings.prepare.seed = args.seed
    source = settings.source_collection
    bpy.ops.shapegen.prepare(wait=True)
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
    contact_sheet(bpy, module, source, output, args)
    import addon_utils

    addon_utils.disable(module, default_set=True)
    return 0


def contact_sheet(bpy, module: str, source, output: Path, args) -> None:
    """Fit BGP-LVM on the imported collection, sample, morph, render one PNG."""
    import numpy as np

    pipeline = importlib.import_module(f"{module}.core.app.pipeline")
    fit_settings = importlib.import_module(f"{module}.core.app.fit_settings")
    shape_model = importlib.import_module(f"{module}.core.app.shape_model")
    collection = importlib.import_module(f"{module}.core.preprocess.collection")
    jobs = importlib.import_module(f"{module}.core.app.jobs")
    meshset = importlib.import_module(f"{module}.core.meshes.meshset")
    convert = importlib.import_module(f"{module}.shapegen_addon.convert")
    start = time.perf_counter()
    meshes = [convert.object_to_mesh(o) for o in sorted(source.objects, key=lambda o: o.name)]
    # the fit runs in a worker process, as Blender's Fit does (a child of Blender cannot
    # import bpy, and only a plain process can start the correspondence process pool)
    meshset.save_mesh_set(output / "training_meshes.npz", [m.name for m in meshes],
                          [m.vertices for m in meshes], [m.faces for m in meshes])
    job = jobs.BackgroundJob("fit", {
        "meshes": str(output / "training_meshes.npz"), "output": str(output / "model.npz"),
        # built from the settings dataclasses, so the worker's format cannot drift from the demo's
        "settings": fit_settings.FitSettings(prepare=collection.PrepareSettings(n_landmarks=args.landmarks, seed=args.seed),
                                         model="bgplvm").as_dict(),
    }).start()
    report = _print_progress("fit")
    while not (status := job.poll()).finished:
        report(status.fraction, status.stage)
        time.sleep(0.1)
    if status.state != "done":
        sys.exit(f"demo: fit {status.state}: {status.error}")
    model = shape_model.GenerativeShapeModel.load(output / "model.npz")
    print(f"demo: fitted {model.model_type} (latent dimension {model.latent_dim}) on {len(meshes)} shapes "
          f"x {model.n_landmarks} landmarks in {time.perf_counter() - start:.1f} s -> {output / 'model.npz'}")

    rng = np.random.default_rng(args.seed)
    samples, _ = model.sample(8, rng)
    latents = model.training_latents()
    distance = ((latents[:, None] - latents[None]) ** 2).sum(axis=2)
    a, b = np.unravel_index(np.argmax(distance), distance.shape)
    line = np.linspace(0, 1, 8)[:, None] * (latents[b] - latents[a]) + latents[a]
    morph = model.decode(line)
    # one template along the whole row (as Blender's Interpolate and `shapegen morph`): no jump mid-path
    morph_template = model.names[model.path_template(latents[a], latents[b], None)]
    rows = {
        "training": [model.meshes[i] for i in range(min(8, len(model.meshes)))],
        "samples": [model.mesh_from_landmarks(lm, name=f"sample {i}") for i, lm in enumerate(samples)],
        f"morph {model.names[a]} to {model.names[b]}": [
            model.mesh_from_landmarks(lm, template=morph_template, name=f"morph {k}") for k, lm in enumerate(morph)],
    }
    colours = {"training": (0.8, 0.82, 0.86, 1.0), "samples": (0.45, 0.65, 0.95, 1.0)}
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    sheet = bpy.data.collections.new("ShapeGen Demo")
    bpy.context.scene.collection.children.link(sheet)
    step_x = 1.3 * max(np.ptp(m.vertices[:, :2], axis=0).max() for row in rows.values() for m in row)
    step_z = 1.25 * max(np.ptp(m.vertices[:, 2]) for row in rows.values() for m in row)
    objects = []
    for r, (label, row) in enumerate(rows.items()):
        z = (len(rows) - 1 - r) * step_z
        for c, mesh in enumerate(row):
            obj = bpy.data.objects.new(mesh.name or label, convert.mesh_data_from_arrays(mesh.name, mesh.vertices, mesh.faces))
            obj.location = (c * step_x, 0.0, z)
            t = c / max(1, len(row) - 1)
            obj.color = colours.get(label, (0.95, 0.55 + 0.2 * t, 0.25 + 0.5 * t, 1.0))
            sheet.objects.link(obj)
            objects.append(obj)
        text = bpy.data.curves.new(f"label {label}", "FONT")
        text.body = label
        text.size = 0.1 * step_z
        text.align_x = "RIGHT"
        label_obj = bpy.data.objects.new(f"label {label}", text)
        label_obj.location = (-0.45 * step_x, 0.0, z + 0.3 * step_z)
        label_obj.rotation_euler = (np.pi / 2, 0.0, 0.0)
        label_obj.color = (0.95, 0.95, 0.95, 1.0)
        sheet.objects.link(label_obj)
        objects.append(label_obj)
    bpy.context.view_layer.update()
    frame_camera(bpy, objects, resolution=(1800, 900))
    png = output / "shapegen_demo.png"
    render_png(bpy, png)
    print(f"demo: wrote {png} (8 training shapes, 8 samples, 8-step morph)")


def _print_progress(prefix: str):
    state = {"step": -1}

    def report(fraction: float, stage: str) -> None:
        if int(10 * fraction) > state["step"]:
            state["step"] = int(10 * fraction)
            print(f"demo: [{prefix}] {100 * fraction:5.1f} %  {stage}", flush=True)

    return report


if __name__ == "__main__":
    sys.exit(main())
