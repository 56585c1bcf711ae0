"""The README's pipeline lines, run as a new user runs them: a fresh virtual environment,
`pip install .` of this checkout (the newest releases the ranges allow, pinned by
requirements/newest.txt), then `shapegen fit` and `shapegen sample` on a PSB class (the
real collections beside the checkout) and on a procedural class.

It runs in the newest tier (Python 3.13, what newest.txt is resolved for); the oldest tier
skips it with that reason.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

from conftest import psb_class

ROOT = Path(__file__).resolve().parents[2]
NEWEST = ROOT / "requirements" / "newest.txt"
#: the README's lines: `pip install .`, then `shapegen fit meshes/ -o model.npz --up y` and
#: `shapegen sample model.npz -n 100 -o samples/ --format obj` (fewer shapes, landmarks and
#: samples here: the runs only have to end well and write their samples)
FIT_OPTIONS = ["--landmarks", "100", "--model", "ppca", "--jobs", "2"]
FISH_SHAPES = 6

pytestmark = pytest.mark.skipif(sys.version_info[:2] != (3, 13),
                                reason="requirements/newest.txt is resolved for Python 3.13: the newest tier runs this")


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A fresh venv with `pip install . -c requirements/newest.txt` done; its bin folder."""
    folder = tmp_path_factory.mktemp("readme-venv")
    # the checkout's package files, copied: pip builds in the source folder, and a build/
    # left in the checkout would be reused by the next build
    checkout = folder / "checkout"
    checkout.mkdir()
    for name in ("pyproject.toml", "LICENSE"):
        shutil.copy(ROOT / name, checkout)
    shutil.copytree(ROOT / "core", checkout / "core", ignore=shutil.ignore_patterns("__pycache__"))
    venv.EnvBuilder(with_pip=True).create(folder / "venv")
    bin_folder = folder / "venv" / "bin"
    done = subprocess.run([str(bin_folder / "python"), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                           "--no-compile", ".", "-c", str(NEWEST)], cwd=checkout, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return bin_folder


def shapegen(bin_folder: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    done = subprocess.run([str(bin_folder / "shapegen"), *args], cwd=cwd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"shapegen {' '.join(args)} exited {done.returncode}:\n{done.stderr[-3000:]}"
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    return done


def fit_and_sample(bin_folder: Path, meshes: Path, work: Path, *up: str) -> list[Path]:
    shapegen(bin_folder, "fit", str(meshes), "-o", "model.npz", *up, *FIT_OPTIONS, cwd=work)
    shapegen(bin_folder, "sample", "model.npz", "-n", "3", "-o", "samples", "--format", "obj", cwd=work)
    return sorted((work / "samples").glob("*.obj"))


def test_installed_packages_are_the_newest_pins(installed):
    """What `pip install .` put beside the core is what newest.txt pins (the core tests ran on it)."""
    pins = dict(line.split("==") for line in NEWEST.read_text().splitlines() if "==" in line)
    done = subprocess.run([str(installed / "python"), "-m", "pip", "list", "--format=freeze"], capture_output=True,
                          text=True, check=True)
    listed = dict(line.split("==") for line in done.stdout.splitlines() if "==" in line)
    for name in ("numpy", "scipy", "trimesh"):
        assert listed[name] == pins[name], (name, listed[name], pins[name])
    assert "shapegen" in listed and "bpy" not in listed and "matplotlib" not in listed  # the core needs neither


def test_fit_and_sample_a_psb_class(installed, tmp_path):
    fish = psb_class("Fish")
    meshes = tmp_path / "fish"
    meshes.mkdir()
    for off in sorted(fish.glob("*.off"))[:FISH_SHAPES]:  # each with its part labels
        for path in (off, fish / f"{off.stem}_labels.txt"):
            if path.is_file():
                shutil.copy(path, meshes / path.name)
    samples = fit_and_sample(installed, meshes, tmp_path, "--up", "y")
    assert len(samples) == 3 and all(path.stat().st_size > 0 for path in samples)


def test_fit_and_sample_a_procedural_class(installed, tmp_path):
    """Procedural mugs written as OBJ files by the installed package itself."""
    write = ("import sys\nfrom pathlib import Path\nfrom shapegen_core.demo_data import make_handled_mugs\n"
             "from shapegen_core.meshes.writing import write_mesh\n"
             "for shape in make_handled_mugs(8, seed=2, resolution=(16, 24)):\n"
             "    write_mesh(shape.mesh, Path(sys.argv[1]) / f'{shape.mesh.name}.obj')\n")
    (tmp_path / "mugs").mkdir()
    subprocess.run([str(installed / "python"), "-c", write, str(tmp_path / "mugs")], check=True)
    samples = fit_and_sample(installed, tmp_path / "mugs", tmp_path)
    assert len(samples) == 3 and all(path.stat().st_size > 0 for path in samples)
