"""Render the user guide's "Sculpt with pins" picture: a live vase with three pins moved,
shaded by the Show Uncertainty colours (grey levels of the posterior standard deviation).

    .venv/bin/python scripts/render_pins.py [--output docs/pins.png]

Headless Blender as a module with the built extension (`make build`) installed into a
throwaway user folder, driven through its operators as an artist would: Explore, Add Pin
three times, move the pins, Show Uncertainty. The pins (Empties, which do not render) are
drawn as small red spheres for the picture.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="shapegen-render-pins-")

import bpy  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Euler, Vector  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

from demo import install_extension  # noqa: E402  (the demo's install: dist/ zip, enabled, checked)

MODULE = "bl_ext.user_default.shapegen"


def module(name: str):
    return importlib.import_module(f"{MODULE}.{name}")


def fitted_vases(folder: Path) -> Path:
    """A PPCA model of 12 procedural vases, fitted with the extension's core; its file. Ten
    latent dimensions: three pins (nine coordinates) leave some of the shape open."""
    datasets, pipeline, collection = module("core.demo_data"), module("core.app.pipeline"), module("core.preprocess.collection")
    shapes = datasets.make_vases(12, seed=4, resolution=(48, 64))
    settings = module("core.app.fit_settings").FitSettings(prepare=collection.PrepareSettings(n_landmarks=400), model="ppca",
                                    latent_dim=10, jobs=1)
    return pipeline.fit_meshes([s.mesh for s in shapes], settings).save(folder / "vases.npz")


def camera_on(obj, resolution=(720, 540)) -> None:
    scene = bpy.context.scene
    corners = np.array([obj.matrix_world @ Vector(c) for c in obj.bound_box])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    data = bpy.data.cameras.new("Pins Camera")
    data.type = "ORTHO"
    data.ortho_scale = 1.35 * float(max(hi[0] - lo[0], hi[2] - lo[2]) * resolution[0] / resolution[1])
    camera = bpy.data.objects.new("Pins Camera", data)
    scene.collection.objects.link(camera)
    tilt = np.radians(72.0)
    distance = 4.0 * float(np.linalg.norm(hi - lo))
    camera.location = Vector(tuple((lo + hi) / 2)) + distance * Vector((0.0, -np.sin(tilt), np.cos(tilt)))
    camera.rotation_euler = Euler((tilt, 0.0, 0.0), "XYZ")
    data.clip_end = 3 * distance
    scene.camera = camera
    scene.render.resolution_x, scene.render.resolution_y = resolution


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "pins.png")
    args = parser.parse_args()
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    install_extension(bpy)
    scene = bpy.context.scene
    assert bpy.ops.shapegen.load_model(filepath=str(fitted_vases(Path(tempfile.mkdtemp())))) == {"FINISHED"}
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    live = scene.shapegen.live_object
    model = module("shapegen_addon.store").get_model(scene)
    # three landmarks the class moves much (a vase's floor centre never moves), far apart
    spread = np.linalg.norm(np.asarray(model.model.decode_basis()).reshape(-1, model.n_landmarks, 3), axis=(0, 2))
    candidates = np.argsort(-spread)[:model.n_landmarks // 4]
    points = model.training_points.mean(axis=0)
    chosen = [int(candidates[0])]
    while len(chosen) < 3:
        gaps = np.min(np.linalg.norm(points[candidates][:, None] - points[chosen][None], axis=2), axis=1)
        chosen.append(int(candidates[int(np.argmax(gaps))]))
    for index in chosen:
        assert bpy.ops.shapegen.pin_add(landmark=index) == {"FINISHED"}
    pins = module("shapegen_addon.pins").pin_objects(scene)
    centre = np.array(live.matrix_world.translation)
    for pin in pins:  # each pin pulled 25 % further from the vase's axis: "wider here"
        offset = np.array(pin.location) - centre
        offset[:2] *= 1.25
        pin.location = tuple(centre + offset)
    scene.shapegen.explore.show_uncertainty = True
    bpy.context.view_layer.update()  # the pin handler: posterior shape, sliders, uncertainty colours
    bpy.context.view_layer.update()
    size = float(max(live.dimensions))
    for pin in pins:
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.025 * size, location=pin.location)
        sphere = bpy.context.active_object.data
        red = sphere.color_attributes.new("pin", "FLOAT_COLOR", "POINT")
        red.data.foreach_set("color", np.tile([0.9, 0.1, 0.08, 1.0], len(sphere.vertices)).astype(np.float32))
        sphere.color_attributes.active_color = red
        sphere.color_attributes.default_color_name = red.name
    for obj in scene.objects:
        obj.hide_render = obj.type not in ("MESH", "CAMERA") or (obj != live and "Sphere" not in obj.name)
    camera_on(live)
    shading = scene.display.shading
    scene.render.engine = "BLENDER_WORKBENCH"
    shading.light, shading.color_type, shading.show_cavity = "STUDIO", "VERTEX", True
    colours = live.data.color_attributes
    colours.active_color = colours[module("shapegen_addon.pins").STD_ATTRIBUTE]
    colours.active_color_name = colours.default_color_name = colours.active_color.name
    scene.world = scene.world or bpy.data.worlds.new("World")
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(args.output)
    bpy.ops.render.render(write_still=True)
    print(f"wrote {args.output}; pin distances: "
          + ", ".join(f"{float(p.get(module('shapegen_addon.pins').PIN_DISTANCE_KEY, 0)):.3g}" for p in pins))
    return 0


if __name__ == "__main__":
    sys.exit(main())
