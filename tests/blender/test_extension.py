"""The extension validates, builds (make build did), installs, registers and unregisters."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import addon_utils
import bpy

ROOT = Path(__file__).resolve().parents[2]
OPERATORS = ("import_collection", "prepare", "find_correspondences", "fit", "fit_cancel", "load_model", "export_model", "sample",
             "interpolate", "modes_to_shape_keys", "explore", "explore_randomise", "explore_reset",
             "explore_snap", "explore_bake", "latent_map")
PANELS = ("SHAPEGEN_PT_data", "SHAPEGEN_PT_correspondence", "SHAPEGEN_PT_model", "SHAPEGEN_PT_generate",
          "SHAPEGEN_PT_explore", "SHAPEGEN_PT_data_advanced", "SHAPEGEN_PT_correspondence_advanced",
          "SHAPEGEN_PT_model_advanced", "SHAPEGEN_PT_generate_advanced")


def test_manifest_validates_with_blenders_own_builder():
    scripts = Path(bpy.utils.system_resource("SCRIPTS"))
    builder = scripts / "addons_core/bl_pkg/cli/blender_ext.py"
    tags = scripts / "modules/_bpy_internal/extensions/tags.py"
    result = subprocess.run([sys.executable, str(builder), "validate", str(ROOT), "--valid-tags", str(tags)],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_installed_extension_is_registered(extension):
    assert extension in bpy.context.preferences.addons
    for name in OPERATORS:
        assert hasattr(bpy.ops.shapegen, name)
        assert getattr(bpy.ops.shapegen, name).get_rna_type() is not None
    assert hasattr(bpy.types.Scene, "shapegen")
    for name in PANELS:
        assert name in dir(bpy.types)
    # the installed copy is the one running, not the source tree
    module = importlib.import_module(extension)
    assert "extensions" in Path(module.__file__).parts


def test_bundled_core_never_imports_bpy(extension):
    core_dir = Path(importlib.import_module(f"{extension}.core").__file__).parent
    for path in core_dir.rglob("*.py"):
        text = path.read_text()
        assert "import bpy" not in text and "from bpy" not in text, path


def test_unregister_and_register_again_cleanly(extension):
    addon_utils.disable(extension, default_set=True)
    assert extension not in bpy.context.preferences.addons
    assert not hasattr(bpy.types.Scene, "shapegen")
    assert "SHAPEGEN_PT_data" not in dir(bpy.types)
    # no handler of the add-on stays behind (it would run on every file load)
    for handlers in (bpy.app.handlers.load_post, bpy.app.handlers.load_pre):
        assert not [h for h in handlers if "shapegen" in getattr(h, "__module__", "")]
    addon_utils.enable(extension, default_set=True)
    assert extension in bpy.context.preferences.addons
    assert hasattr(bpy.types.Scene, "shapegen")
