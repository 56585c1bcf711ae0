"""Write the pinned requirements of the tiers that test the ends of pyproject.toml's ranges.

    python3.11 scripts/refresh_pins.py --python313 PATH   (what `make pins` runs)

- `requirements/oldest.txt`: Python 3.11 with each core dependency at the floor
  pyproject.toml declares (`numpy>=1.26` installs numpy 1.26.0), plus the `test` extra.
- `requirements/newest.txt`: Python 3.13 with the newest releases the ranges allow, the
  `test` extra, and Blender's newest LTS as a module (bpy 5.2.x) for the Blender smoke.
- `requirements/blender-4.2.txt`: Blender 4.2 LTS as a module with the numpy Blender 4.2
  ships (1.26.4), nothing else: the extension brings its own scipy and trimesh.

Each file is the `pip freeze --all` of a fresh virtual environment, so `make test` installs
exactly what was resolved here. Run it when a release should enter the newest tier, or
after changing a floor; then `make test`, and commit the files with what changed.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
REQUIREMENTS = ROOT / "requirements"
#: Blender's newest LTS as a module (Python 3.13 only)
NEWEST_BLENDER = "bpy>=5.2,<5.3"
#: Blender 4.2 LTS, the oldest Blender the manifest claims, and the numpy it ships
OLDEST_BLENDER = ["bpy==4.2.23", "numpy==1.26.4"]


def floors() -> list[str]:
    """`name==floor` for every core dependency of pyproject.toml (`name>=floor`)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pins = []
    for requirement in project["dependencies"]:
        match = re.fullmatch(r"([A-Za-z0-9_.-]+)\s*>=\s*([0-9.]+)", requirement)
        if not match:
            sys.exit(f"pyproject.toml: {requirement!r} is not `name>=floor`")
        pins.append(f"{match.group(1)}=={match.group(2)}")
    return pins


def frozen(python: str, requirements: list[str], editable_project: bool) -> str:
    """`pip freeze --all` of a fresh venv of `python` with `requirements` installed."""
    with tempfile.TemporaryDirectory(prefix="shapegen-pins-") as folder:
        venv = Path(folder) / "venv"
        subprocess.run([python, "-m", "venv", str(venv)], check=True)
        pip = [str(venv / "bin" / "python"), "-m", "pip", "--disable-pip-version-check"]
        subprocess.run([*pip, "install", "-q", "--no-compile", *requirements], check=True, cwd=ROOT)
        text = subprocess.run([*pip, "freeze", "--all", "--exclude", "pip", "--exclude", "shapegen"],
                              check=True, capture_output=True, text=True).stdout
    lines = [line for line in text.splitlines() if line and not line.startswith("-e ")]
    if editable_project:  # the project's build backend, for `pip install --no-build-isolation -e .`
        assert any(line.startswith("setuptools==") for line in lines), "setuptools missing from the freeze"
    return "\n".join(sorted(lines, key=str.lower)) + "\n"


def write(name: str, header: str, body: str) -> None:
    path = REQUIREMENTS / name
    path.write_text(header + body)
    print(f"wrote {path.relative_to(ROOT)} ({len(body.splitlines())} packages)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tiers", nargs="*", default=["oldest", "newest", "blender-4.2"],
                        choices=["oldest", "newest", "blender-4.2"])
    parser.add_argument("--python313", default="python3.13",
                        help="Python 3.13 for the newest tier (make passes the one it found)")
    args = parser.parse_args()
    tiers = args.tiers
    note = "# Written by `make pins` (scripts/refresh_pins.py): a pip freeze of a fresh venv. Do not edit.\n"
    if "oldest" in tiers:
        pins = floors()
        write("oldest.txt", note + f"# Oldest tier: Python 3.11, the floors of pyproject.toml ({', '.join(pins)}), "
              "the test extra.\n", frozen(sys.executable if sys.version_info[:2] == (3, 11) else "python3.11",
                                         [*pins, ".[test]", "setuptools", "wheel"], True))
    if "newest" in tiers:
        write("newest.txt", note + "# Newest tier: Python 3.13, the newest releases pyproject.toml allows, the test "
              f"extra, Blender's newest LTS as a module ({NEWEST_BLENDER}).\n",
              frozen(args.python313, [".[test]", NEWEST_BLENDER, "setuptools", "wheel"], True))
    if "blender-4.2" in tiers:
        write("blender-4.2.txt", note + "# Blender 4.2 LTS as a module (Python 3.11) with the numpy Blender 4.2 ships; "
              "the extension brings scipy and trimesh.\n", frozen("python3.11", OLDEST_BLENDER, False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
