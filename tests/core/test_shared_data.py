"""tests/shared_data.py, the one way tests and bench scripts find the real collections: a
missing or empty folder skips a test (or ends a bench script) naming the folder."""

from __future__ import annotations

from pathlib import Path

import pytest

import shared_data
from shared_data import folder_or_exit, folder_or_skip, shared_path


def test_the_data_is_found_beside_the_checkout():
    checkout = Path(__file__).resolve().parents[2]
    assert shared_path("psb", "Vase") == checkout.parent / "shared" / "data" / "psb" / "Vase"


def test_a_missing_or_empty_folder_is_named(tmp_path, monkeypatch):
    monkeypatch.setattr(shared_data, "SHARED_DATA", tmp_path / "data")
    vases = tmp_path / "data" / "psb" / "Vase"
    with pytest.raises(pytest.skip.Exception, match=f"folder {vases} is absent"):
        folder_or_skip("psb", "Vase")
    with pytest.raises(SystemExit, match=f"folder {vases} is absent"):
        folder_or_exit("psb", "Vase")
    vases.mkdir(parents=True)
    with pytest.raises(pytest.skip.Exception, match=f"folder {vases} is empty"):
        folder_or_skip("psb", "Vase")
    (vases / "1.off").write_text("OFF\n0 0 0\n")
    assert folder_or_skip("psb", "Vase") == folder_or_exit("psb", "Vase") == vases
