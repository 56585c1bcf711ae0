"""Blender tier: the real extension zip, built by Blender's own builder (`make build`),
installed into a throwaway user-resources folder and enabled as a user would.

BLENDER_USER_RESOURCES must be set before bpy is imported, so this conftest does it at
import time. Every test starts from an empty factory scene (`clean_scene`, autouse).
"""

from __future__ import annotations

import glob
import os
import platform
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DIST = ROOT / "dist"
MODULE = "bl_ext.user_default.shapegen"

_USER_RESOURCES = tempfile.mkdtemp(prefix="shapegen-blender-user-")
os.environ["BLENDER_USER_RESOURCES"] = _USER_RESOURCES
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import bpy  # noqa: E402  (after the environment is set)


def _platform_zip() -> Path:
    machine = {"x86_64": "x64", "amd64": "x64", "arm64": "arm64", "aarch64": "arm64"}[platform.machine().lower()]
    system = {"linux": "linux", "darwin": "macos", "windows": "windows"}[platform.system().lower()]
    matches = sorted(glob.glob(str(DIST / f"shapegen-*-{system}_{machine}.zip")))
    if not matches:
        pytest.exit(f"no extension zip for {system}_{machine} in {DIST}: run `make build` first", returncode=2)
    return Path(matches[-1])


def install_extension() -> str:
    """Install + enable the built zip (idempotent). Returns the add-on module name."""
    import addon_utils

    if MODULE not in bpy.context.preferences.addons:
        result = bpy.ops.extensions.package_install_files(
            filepath=str(_platform_zip()), repo="user_default", enable_on_install=True
        )
        assert result == {"FINISHED"}, result
    if MODULE not in bpy.context.preferences.addons:
        addon_utils.enable(MODULE, default_set=True)
    assert MODULE in bpy.context.preferences.addons
    return MODULE


@pytest.fixture(scope="session")
def extension():
    """The installed, enabled extension's module name; disabled again at session end so
    nothing stays registered when the interpreter exits."""
    module = install_extension()
    yield module
    import addon_utils

    if module in bpy.context.preferences.addons:
        addon_utils.disable(module, default_set=True)


@pytest.fixture(autouse=True)
def clean_scene(extension):
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    if extension not in bpy.context.preferences.addons:
        install_extension()
    yield


@pytest.fixture
def core(extension):
    """The core package as shipped inside the installed extension."""
    return sys.modules[f"{extension}.core"] if f"{extension}.core" in sys.modules else __import__(
        f"{extension}.core", fromlist=["*"])
