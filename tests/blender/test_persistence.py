"""The fitted model travels with the .blend: save, reopen in a fresh Python process that
installs and enables the extension, move a slider, the live mesh changes."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import bpy
import numpy as np
from conftest import _platform_zip, addon_module, load_model, vertices

REOPEN = textwrap.dedent("""
    import atexit, importlib, json, os, shutil, sys, tempfile
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="shapegen-reopen-")
    atexit.register(shutil.rmtree, os.environ["BLENDER_USER_RESOURCES"], True)  # before bpy: runs after its exit
    import bpy
    import numpy as np

    zip_path, blend = sys.argv[1], sys.argv[2]
    assert bpy.ops.extensions.package_install_files(
        filepath=zip_path, repo="user_default", enable_on_install=True) == {"FINISHED"}
    bpy.ops.wm.open_mainfile(filepath=blend)
    store = importlib.import_module("bl_ext.user_default.shapegen.shapegen_addon.store")
    latent = importlib.import_module("bl_ext.user_default.shapegen.shapegen_addon.latent")
    scene = bpy.context.scene
    settings = scene.shapegen
    restored = settings.model_text["shapegen_model_id"] in store._CACHE  # by the load_post handler

    def co(obj):
        out = np.empty(len(obj.data.vertices) * 3)
        obj.data.vertices.foreach_get("co", out)
        return out.reshape(-1, 3)

    live = settings.live_object
    opened = co(live).copy()
    values = [item.value for item in settings.latents]
    settings.latents[1].value = -1.25  # move a slider
    moved = co(live)
    model = store.get_model(scene)
    z = latent.current_latent(scene)
    expected = model.mesh_from_landmarks(model.decode(z)[0], template=live["shapegen_template"]).vertices
    print("RESULT " + json.dumps({
        "restored_on_load": restored, "values": values, "opened": opened.tolist(),
        "change": float(np.abs(moved - opened).max()), "error": float(np.abs(moved - expected).max()),
        "model_type": model.model_type,
    }))
    import addon_utils
    addon_utils.disable("bl_ext.user_default.shapegen", default_set=True)
""")


def test_save_reopen_in_a_fresh_process_and_the_sliders_still_work(extension, model_files, tmp_path):
    load_model("bgplvm", model_files)
    settings = bpy.context.scene.shapegen
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    settings.latents[0].value = 0.8
    saved = vertices(settings.live_object).copy()
    blend = tmp_path / "explore.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    script = tmp_path / "reopen.py"
    script.write_text(REOPEN)

    result = subprocess.run([sys.executable, str(script), str(_platform_zip()), str(blend)],
                            capture_output=True, text=True, timeout=300)
    lines = [line for line in result.stdout.splitlines() if line.startswith("RESULT ")]
    assert result.returncode == 0 and lines, result.stdout[-3000:] + result.stderr[-3000:]
    reopened = json.loads(lines[-1][len("RESULT "):])
    assert reopened["restored_on_load"]
    assert reopened["model_type"] == "bgplvm"
    np.testing.assert_allclose(reopened["values"], [0.8, 0.0], atol=1e-6)
    np.testing.assert_allclose(reopened["opened"], saved, atol=1e-6)
    assert reopened["change"] > 1e-3  # the slider re-meshed the live object
    assert reopened["error"] < 1e-4


def test_reopening_in_the_same_process_restores_the_model_from_the_file(extension, model_files, tmp_path):
    store = addon_module(extension, "shapegen_addon.store")
    load_model("ppca", model_files)
    bpy.ops.shapegen.explore()
    key = bpy.context.scene.shapegen.model_text["shapegen_model_id"]
    blend = tmp_path / "same.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    store.forget_cache()
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    assert key in store._CACHE  # load_post decoded the packed model again
    settings = bpy.context.scene.shapegen
    before = vertices(settings.live_object).copy()
    settings.latents[0].value = 2.0
    assert np.abs(vertices(settings.live_object) - before).max() > 1e-3


def test_panel_settings_saved_before_they_were_grouped_move_into_their_sections(extension, tmp_path):
    """A .blend saved before scene.shapegen was grouped by panel section holds the settings
    flat (enums as item numbers, booleans as 0/1); opening it keeps the artist's values."""
    settings = bpy.context.scene.shapegen
    collection = bpy.data.collections.new("vases")
    old = {"n_landmarks": 77, "up_axis": 1, "use_base_mesh": 1, "fit_model": 0, "latent_dim": 3, "stiffness": 7.5,
           "differ_in_pose": 1, "interpolate_steps": 9, "explore_seed": 4, "map_size": 10, "sample_count": "six"}
    for name, value in old.items():
        settings[name] = value
    settings.source_collection = collection
    blend = tmp_path / "flat.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    settings = bpy.context.scene.shapegen
    prepare, fit = settings.prepare, settings.fit
    assert (prepare.n_landmarks, prepare.up_axis, prepare.use_base_mesh) == (77, "y", True)
    assert (fit.model, fit.latent_dim, settings.correspondence.stiffness) == ("ppca", 3, 7.5)
    assert settings.correspondence.differ_in_pose == "ON" and settings.generate.interpolate_steps == 9
    assert settings.explore.seed == 4 and settings.explore.map_size == 64  # clamped to its minimum, as Blender does
    assert settings.generate.sample_count == 6  # text where a number belongs: dropped, the default stays
    assert not set(old) & set(settings.keys()) and settings.source_collection.name == "vases"


def test_shapes_differ_in_pose_saved_as_a_checkbox_reads_as_on_or_off(extension, tmp_path):
    """Shapes Differ in Pose was a checkbox (stored 0/1) before it became Auto / On / Off: a
    .blend saved with it ticked opens On, unticked Off; one that never set it has the default."""
    for stored, expected in ((1, "ON"), (0, "OFF")):
        bpy.ops.wm.read_homefile(use_empty=True)
        bpy.context.scene.shapegen.correspondence["differ_in_pose"] = stored  # as the checkbox saved it
        blend = tmp_path / f"checkbox_{stored}.blend"
        bpy.ops.wm.save_as_mainfile(filepath=str(blend))
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        correspondence = bpy.context.scene.shapegen.correspondence
        assert correspondence.differ_in_pose == expected
        assert correspondence.options()["initialisation"] == {"ON": "spectral", "OFF": "closest"}[expected]
    bpy.ops.wm.read_homefile(use_empty=True)
    default = addon_module(extension, "core.correspond").CorrespondenceSettings().data_term.initialisation
    assert bpy.context.scene.shapegen.correspondence.options()["initialisation"] == default == "auto"
    assert bpy.context.scene.shapegen.correspondence.differ_in_pose == "AUTO"  # the core's default, not the add-on's
