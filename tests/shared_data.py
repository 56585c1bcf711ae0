"""Where the real mesh collections are: the folder `shared` beside the checkout
(`../shared`), never copied into the repository. It holds data/psb/<Class> (Vase, Cup,
Fish, Airplane), data/tosca/<animal> (cat, centaur, dog, horse) and data/tosca/people;
data/README.md there describes them.

Tests and bench scripts find it here and nowhere else, always relative to this checkout:

    shared_path("psb", "Vase")       the path, whether or not it is there (a default, a listing)
    folder_or_skip("psb", "Vase")    a test: the folder, or the test is skipped naming it
    folder_or_exit("psb", "Vase")    a bench script: the folder, or it exits with one line naming it

tests/core/conftest.py and tests/blender/conftest.py put this folder (tests/) on sys.path;
a bench or helper script does `sys.path.insert(0, str(ROOT / "tests"))`. It lives here,
beside the tests, because the tests must run from the checkout alone; the bench scripts
already depend on the checkout's layout.
"""

from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["SHARED_DATA", "shared_path", "missing", "folder_or_skip", "folder_or_exit"]

#: ../shared/data: beside the checkout (this file is <checkout>/tests/shared_data.py)
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared_path(*parts: str) -> Path:
    """`../shared/data/<parts...>`, whether or not it is there."""
    return SHARED_DATA.joinpath(*parts)


def missing(folder: Path) -> str | None:
    """Why `folder` cannot serve as data (absent, or empty), or None."""
    if not folder.is_dir():
        return f"the shared data folder {folder} is absent"
    if not any(folder.iterdir()):
        return f"the shared data folder {folder} is empty"
    return None


def folder_or_skip(*parts: str) -> Path:
    """The folder `../shared/data/<parts...>` for a test; the test is skipped, naming the
    folder, when it is missing (inside a test or fixture; at a module's top the module is skipped)."""
    folder = shared_path(*parts)
    reason = missing(folder)
    if reason:
        import pytest

        pytest.skip(reason, allow_module_level=True)
    return folder


def folder_or_exit(*parts: str) -> Path:
    """The folder `../shared/data/<parts...>` for a bench script; the script exits (status 1)
    with one line naming the folder when it is missing."""
    folder = shared_path(*parts)
    reason = missing(folder)
    if reason:
        raise SystemExit(f"{Path(sys.argv[0]).name}: {reason}")
    return folder
