"""Blender tier: the real extension zip, built by Blender's own builder (`make build`),
installed into a throwaway user-resources folder and enabled as a user would.

BLENDER_USER_RESOURCES must be set before bpy is imported, so this conftest does it at
import time. Every test starts from an empty factory scene (`clean_scene`, autouse).
"""

from __future__ import annotations

import atexit
import glob
import os
import platform
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DIST = ROOT / "dist"
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: where the real mesh collections are
MODULE = "bl_ext.user_default.shapegen"

_USER_RESOURCES = tempfile.mkdtemp(prefix="shapegen-blender-user-")
# registered before bpy is imported, so it runs after bpy's own exit handlers (atexit runs
# last-registered first): the folder (~74 MB once the extension is installed) goes at exit
atexit.register(shutil.rmtree, _USER_RESOURCES, True)
os.environ["BLENDER_USER_RESOURCES"] = _USER_RESOURCES
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Python keeps what it compiles (__pycache__), here and in the processes the tests start
# (the Blender 4.2 and 5.2 smokes): the environments are installed without compiling
# (Makefile), and where PYTHONDONTWRITEBYTECODE is set every process compiled anew all it
# imported (bpy's scripts, numpy, scipy, trimesh, the core)
sys.dont_write_bytecode = False
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

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


# ---------------------------------------------------------------- workflow fixtures
import importlib  # noqa: E402
import json  # noqa: E402
from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402

#: tiny fits keep the Blender tier fast: 6 coarse vases, 100 landmarks, a short ICP schedule
FAST_FIT = {"jobs": 1, "correspondence": {"alpha_steps": 2, "max_iterations": 6, "groupwise_rounds": 0}}
VASE_SEED = 1
VASE_RESOLUTION = (14, 20)


def addon_module(extension: str, name: str):
    """A module of the installed extension, e.g. addon_module(extension, "shapegen_addon.store")."""
    return importlib.import_module(f"{extension}.{name}")


def add_vase_collection(extension: str, n: int = 6, name: str = "vases", pose: bool = True) -> bpy.types.Collection:
    """n procedural vases as mesh objects (named like the core's shapes) in a new collection,
    chosen as the panel's training collection; `pose` False: all upright, facing +x."""
    datasets = addon_module(extension, "core.demo_data")
    convert = addon_module(extension, "shapegen_addon.convert")
    collection = bpy.data.collections.new(name)
    bpy.context.scene.collection.children.link(collection)
    for shape in datasets.make_vases(n, seed=VASE_SEED, resolution=VASE_RESOLUTION, pose=pose):
        obj = bpy.data.objects.new(shape.name, convert.mesh_data_from_arrays(shape.name, shape.mesh.vertices,
                                                                             shape.mesh.faces))
        collection.objects.link(obj)
    bpy.context.scene.shapegen.source_collection = collection
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = 100
    settings.fit.latent_dim = 2
    return collection


@pytest.fixture(scope="session")
def model_files(extension, tmp_path_factory):
    """One small fitted model file per model type, fitted in-process with the extension's
    core (the worker path is tested separately): {"ppca": path, "gplvm": ..., "bgplvm": ...}.
    The three share one correspondence (what fit_meshes would compute for each)."""
    folder = tmp_path_factory.mktemp("models")
    return {kind: model.save(folder / f"vases_{kind}.npz")
            for kind, model in fit_vase_models(extension, ("ppca", "gplvm", "bgplvm"), n=6, latent_dim=2).items()}


def fit_vase_models(extension: str, kinds, n: int, latent_dim: int | None) -> dict:
    """{kind: GenerativeShapeModel} of n procedural vases with the FAST_FIT settings: one
    prepare and one correspondence, then each model type fitted on it (fit_shape_model,
    the stage fit_meshes ends with)."""
    datasets = addon_module(extension, "core.demo_data")
    pipeline = addon_module(extension, "core.app.pipeline")
    fit_settings = addon_module(extension, "core.app.fit_settings")
    correspond = addon_module(extension, "core.correspond")
    collection = addon_module(extension, "core.preprocess.collection")
    meshes = [s.mesh for s in datasets.make_vases(n, seed=VASE_SEED, resolution=VASE_RESOLUTION)]
    settings = fit_settings.FitSettings(prepare=collection.PrepareSettings(n_landmarks=100), latent_dim=latent_dim,
                                    correspondence=correspond.CorrespondenceSettings.from_dict(FAST_FIT["correspondence"]))
    prepared = collection.prepare_meshes(meshes, settings.prepare)
    corr = correspond.correspond(prepared, settings.correspondence, template=settings.template, jobs=1)
    shapes = [s.mesh for s in prepared.shapes]
    return {kind: pipeline.fit_shape_model(shapes, corr, replace(settings, model=kind)) for kind in kinds}


def load_model(kind: str, model_files) -> None:
    assert bpy.ops.shapegen.load_model(filepath=str(model_files[kind])) == {"FINISHED"}


def vertices(obj, evaluated: bool = False) -> np.ndarray:
    if evaluated:
        obj = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def reused_prepared(extension: str, collection, objects, options: dict, evaluated: bool = True):
    """The "<name> Prepared" collection Fit would start from (`fitting.plan_fit`, the
    operator's own decision), or None when Fit prepares again."""
    plan = addon_module(extension, "shapegen_addon.fitting").plan_fit(bpy.context.scene, collection, objects,
                                                                        options, evaluated)
    reused = plan.reused_stage("prepare")
    return None if reused is None else reused.data.collection


def fast_fit_json(**more) -> str:
    return json.dumps({**FAST_FIT, **more})
