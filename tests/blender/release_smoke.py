"""One artist's pass through the built extension on one Blender release, as its own process.

    PYTHON release_smoke.py ZIP FISH_FOLDER

Run with the Python of an environment that holds that release as a module (`bpy`):
install and enable the zip as a user would, import a folder of PSB fish through Import
Training Collection (OFF files, read by the bundled trimesh), fit a small PPCA model in the
background job, sample two shapes, and leave the extension enabled, as an artist quits
Blender. Prints one `ok ...` line per step and a last line `SMOKE PASSED`; any failure is
an exception (exit 1). tests/blender/test_releases.py runs it and checks the exit code too:
a crash at interpreter exit is a failure like any other.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

# before bpy is imported: the extension is installed there, nothing lands in ~/.config
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="shapegen-release-smoke-"))
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import bpy  # noqa: E402

# as in the other tiers (pyproject.toml): a deprecation met in the extension's own code fails
for _category in (DeprecationWarning, PendingDeprecationWarning, FutureWarning):
    warnings.filterwarnings("error", category=_category, module=r"bl_ext\.user_default\.shapegen")

MODULE = "bl_ext.user_default.shapegen"
#: a short schedule from closest points: the smoke checks that each stage runs on this
#: release, not its quality. The intrinsic start, which the default (auto) weighs on every
#: shape, is core numerics on the same numpy, scipy and libigl as the other tiers (Blender 4.2:
#: numpy 1.26 and the bundled cp311 wheels, as the Blender 5.0 tier; Blender 5.2: numpy 2 and
#: the cp313 wheels, as the newest core tier); here it would be two thirds of the pass.
FAST_FIT = {"jobs": 1, "correspondence": {"alpha_steps": 2, "max_iterations": 6, "groupwise_rounds": 0,
                                          "data_term": {"initialisation": "closest"}}}


def step(message: str) -> None:
    print(f"ok {message}", flush=True)


def install(zip_path: str) -> None:
    result = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                      enable_on_install=True)
    assert result == {"FINISHED"}, result
    assert MODULE in bpy.context.preferences.addons, "the extension is not enabled after installing"
    step(f"Blender {bpy.app.version_string}: installed and enabled {Path(zip_path).name}")


def import_folder(folder: str, n_files: int) -> bpy.types.Collection:
    assert bpy.ops.shapegen.import_collection(directory=folder) == {"FINISHED"}
    collection = bpy.data.collections[Path(folder).name]
    assert len(collection.objects) == n_files, (len(collection.objects), n_files)
    bpy.context.scene.shapegen.source_collection = collection
    step(f"imported {len(collection.objects)} files of {folder}")
    return collection


def fit() -> None:
    settings = bpy.context.scene.shapegen
    settings.prepare.up_axis = "y"  # PSB files are y-up
    settings.prepare.n_landmarks = 100
    settings.fit.model = "ppca"
    settings.fit.latent_dim = 2
    assert bpy.ops.shapegen.fit(extra_settings=json.dumps(FAST_FIT)) == {"FINISHED"}
    poll_fit = sys.modules[f"{MODULE}.shapegen_addon.fitting"].poll_fit
    deadline = time.monotonic() + 600
    status = None
    while time.monotonic() < deadline and not (status is not None and status.finished):
        status = poll_fit()  # what the panel's timer does (timers never fire in the module)
        time.sleep(0.05)
    assert status is not None and status.state == "done", (status, settings.job_message)
    step(f"fitted: {settings.job_message}")


def sample() -> None:
    before = {o.name for o in bpy.data.objects}
    assert bpy.ops.shapegen.sample(count=2, seed=0) == {"FINISHED"}
    new = [bpy.data.objects[name] for name in {o.name for o in bpy.data.objects} - before]
    assert len(new) == 2 and all(len(o.data.polygons) > 0 for o in new), [o.name for o in new]
    step(f"sampled {', '.join(sorted(o.name for o in new))}")


def main(zip_path: str, fish_folder: str) -> None:
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    install(zip_path)
    n_files = len([p for p in Path(fish_folder).iterdir() if p.suffix == ".off"])
    import_folder(fish_folder, n_files)
    fit()
    sample()
    print("SMOKE PASSED", flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:3])
