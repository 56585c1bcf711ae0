"""The oldest and the newest Blender the manifest claims: the smoke pass (release_smoke.py)
in a process of their own, exit code included.

The rest of the Blender tier runs on Blender 5.0 in this process. `make test` names the
other releases' interpreters in SHAPEGEN_BLENDER_RELEASES ("4.2=/path/python 5.2=/path/python":
Blender 4.2 LTS on Python 3.11 with numpy 1.26, Blender 5.2 LTS on Python 3.13 with numpy 2).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import _platform_zip
from shared_data import folder_or_skip

SMOKE = Path(__file__).with_name("release_smoke.py")
RELEASES = ("4.2", "5.2")
#: the smoke imports and fits the first 6 of the 20 PSB fish: the pass has only to end well
FISH_SHAPES = 6


def release_pythons() -> dict[str, str]:
    named = dict(item.split("=", 1) for item in os.environ.get("SHAPEGEN_BLENDER_RELEASES", "").split())
    return {release: named.get(release, "") for release in RELEASES}


@pytest.mark.parametrize("release", RELEASES)
def test_install_import_fit_sample_and_exit_cleanly(release, tmp_path):
    python = release_pythons()[release]
    if not python or not Path(python).is_file():
        pytest.skip(f"no Python with Blender {release} as a module (make test sets SHAPEGEN_BLENDER_RELEASES)")
    psb_fish = folder_or_skip("psb", "Fish")
    fish = tmp_path / "Fish"  # FISH_SHAPES of the class: the pass has only to end well
    fish.mkdir()
    for off in sorted(psb_fish.glob("*.off"))[:FISH_SHAPES]:
        shutil.copy(off, fish / off.name)
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "user"), "PYTHONFAULTHANDLER": "1"}
    env.pop("PYTHONPATH", None)
    done = subprocess.run([python, str(SMOKE), str(_platform_zip()), str(fish)], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=900)
    output = done.stdout + done.stderr
    assert f"Blender {release}" in done.stdout, output[-3000:]
    assert "SMOKE PASSED" in done.stdout, output[-3000:]
    assert done.returncode == 0, f"exit code {done.returncode} after the smoke passed:\n{output[-3000:]}"
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    print(done.stdout, file=sys.stderr)
