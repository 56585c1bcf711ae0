"""Unreadable files of a folder: refused as a whole by default, left out with
--skip-unreadable (named on stderr with their reasons and recorded in every file written
from the folder: prepared, correspondence and model .npz, the evaluation report).

The commands that run run as a user runs them (subprocesses); the refusals, which end
before any work, through `main` in this process (`in_process`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PrepareSettings, PreparedCollection, prepare_meshes
from shapegen_core.correspond import Correspondence
from shapegen_core.demo_data import make_vases, write_collection
from shapegen_core.base.errors import CollectionError, MeshFileError, ModelFileError
from shapegen_core.meshes.reading import read_folder, read_readable

from conftest import in_process

SHAPEGEN = Path(sys.executable).parent / "shapegen"

#: two damaged downloads: a NaN coordinate and a face naming a vertex the file lacks
BROKEN = {"cracked.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "a face refers to a vertex that does not exist"),
          "nan.off": ("OFF\n3 1 0\nnan 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "vertex 0 has a NaN")}


def _run(*args, timeout=300):
    if not SHAPEGEN.exists():
        pytest.skip(f"{SHAPEGEN} is not installed in this environment")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    return subprocess.run([str(SHAPEGEN), *map(str, args)], capture_output=True, text=True, timeout=timeout, env=env)


def _with_broken(folder: Path, good: int = 4) -> Path:
    write_collection(make_vases(good, seed=2, resolution=(10, 14)), folder, "obj")
    for name, (content, _) in BROKEN.items():
        (folder / name).write_text(content)
    return folder


@pytest.fixture(scope="module")
def mixed_folder(tmp_path_factory):
    return _with_broken(tmp_path_factory.mktemp("mixed"))


def _assert_names_both(text: str, folder: Path) -> None:
    for name, (_, reason) in BROKEN.items():
        assert f"{folder / name}: {reason}" in text, (name, text)


def _skipped_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("skipped: ")]


# ---------------------------------------------------------------------------- the reader
def test_read_readable_leaves_out_each_unreadable_file_with_the_readers_message(mixed_folder):
    meshes, unreadable = read_readable(mixed_folder)
    assert [m.name for m in meshes] == ["vase_000", "vase_001", "vase_002", "vase_003"]
    assert list(unreadable) == ["cracked.obj", "nan.off"]
    for name, message in unreadable.items():
        assert message.startswith(f"{mixed_folder / name}: ") and BROKEN[name][1] in message
    with pytest.raises(MeshFileError) as refused:  # the same messages read_folder refuses the folder with
        read_folder(mixed_folder)
    assert all(message in str(refused.value) for message in unreadable.values())


def test_read_readable_with_fewer_than_two_readable_files_is_an_error_naming_the_unreadable(tmp_path):
    folder = _with_broken(tmp_path / "in", good=1)
    with pytest.raises(CollectionError) as refused:
        read_readable(folder)
    message = str(refused.value)
    assert "at least 2 meshes" in message and "1 of 3 files could be read" in message and "\n" not in message
    _assert_names_both(message, folder)


# ---------------------------------------------------------------------------- prepare
def test_cli_prepare_without_the_flag_exits_2_naming_both(mixed_folder, tmp_path):
    out = tmp_path / "prepared.npz"
    result = in_process("prepare", mixed_folder, "-o", out, "--landmarks", 40)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "2 of 6 files could not be read" in lines[0], result.stderr
    _assert_names_both(lines[0], mixed_folder)
    assert not out.exists()


def test_cli_prepare_skips_the_unreadable_names_each_and_records_them(mixed_folder, tmp_path):
    out = tmp_path / "prepared.npz"
    result = _run("prepare", mixed_folder, "-o", out, "--landmarks", 40, "--skip-unreadable")
    assert result.returncode == 0, result.stderr
    assert f"prepared 4 shapes -> {out}" in result.stdout
    skipped = _skipped_lines(result.stderr)
    assert len(skipped) == 2, result.stderr  # one line per file, the reader's own message
    _assert_names_both("\n".join(skipped), mixed_folder)
    prepared = PreparedCollection.load(out)
    assert prepared.names == ["vase_000", "vase_001", "vase_002", "vase_003"]
    assert list(prepared.unreadable) == ["cracked.obj", "nan.off"]
    _assert_names_both("\n".join(prepared.unreadable.values()), mixed_folder)


def test_cli_prepare_with_one_readable_file_is_still_an_error(tmp_path):
    folder = _with_broken(tmp_path / "in", good=1)
    out = tmp_path / "prepared.npz"
    result = in_process("prepare", folder, "-o", out, "--skip-unreadable")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "at least 2 meshes" in lines[0], result.stderr
    _assert_names_both(lines[0], folder)
    assert not out.exists()


# ---------------------------------------------------------------------------- correspond, fit, info
@pytest.fixture(scope="module")
def skipped_model(mixed_folder, tmp_path_factory):
    """`shapegen fit` on the mixed folder with --skip-unreadable: (model file, its run)."""
    out = tmp_path_factory.mktemp("fit") / "model.npz"
    result = _run("fit", mixed_folder, "-o", out, "--model", "ppca", "--landmarks", 40, "--jobs", 1,
                  "--skip-unreadable")
    assert result.returncode == 0, result.stderr
    return out, result


def test_cli_fit_skips_the_unreadable_and_info_shows_them(skipped_model, mixed_folder):
    out, result = skipped_model
    assert "fitted ppca" in result.stdout and "on 4 shapes" in result.stdout
    assert len(_skipped_lines(result.stderr)) == 2
    info = _run("info", out, "--json")
    assert info.returncode == 0, info.stderr
    record = json.loads(info.stdout)
    assert record["shapes"] == 4 and list(record["unreadable_files"]) == ["cracked.obj", "nan.off"]
    _assert_names_both("\n".join(record["unreadable_files"].values()), mixed_folder)
    text = _run("info", out)
    line = next(line for line in text.stdout.splitlines() if line.strip().startswith("unreadable_files:"))
    _assert_names_both(line, mixed_folder)


def test_cli_fit_without_the_flag_exits_2_naming_both(mixed_folder, tmp_path):
    result = in_process("fit", mixed_folder, "-o", tmp_path / "model.npz", "--model", "ppca", "--jobs", 1)
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
    _assert_names_both(result.stderr, mixed_folder)
    assert not (tmp_path / "model.npz").exists()


def test_cli_correspond_records_the_skipped_and_fit_from_it_needs_the_flag_for_its_folder(mixed_folder, tmp_path):
    corr_file = tmp_path / "corr.npz"
    result = _run("correspond", mixed_folder, "-o", corr_file, "--landmarks", 40, "--jobs", 1, "--skip-unreadable")
    assert result.returncode == 0, result.stderr
    assert len(_skipped_lines(result.stderr)) == 2
    corr = Correspondence.load(corr_file)
    assert len(corr) == 4 and list(corr.unreadable) == ["cracked.obj", "nan.off"]
    # the folder of its meshes still holds the unreadable files: refused as a whole without the flag
    model = tmp_path / "model.npz"
    refused = in_process("fit", corr_file, "--meshes", mixed_folder, "-o", model, "--model", "ppca")
    assert refused.returncode == 2 and not model.exists()
    _assert_names_both(refused.stderr, mixed_folder)
    result = _run("fit", corr_file, "--meshes", mixed_folder, "-o", model, "--model", "ppca", "--skip-unreadable")
    assert result.returncode == 0, result.stderr
    record = json.loads(_run("info", model, "--json").stdout)["unreadable_files"]
    assert list(record) == ["cracked.obj", "nan.off"]


def test_cli_fit_from_a_correspondence_refuses_a_needed_shape_whose_file_became_unreadable(tmp_path):
    folder = tmp_path / "in"
    write_collection(make_vases(3, seed=2, resolution=(10, 14)), folder, "obj")
    corr_file = tmp_path / "corr.npz"
    assert _run("correspond", folder, "-o", corr_file, "--landmarks", 40, "--jobs", 1).returncode == 0
    (folder / "vase_001.obj").write_text(BROKEN["cracked.obj"][0])
    result = in_process("fit", corr_file, "--meshes", folder, "-o", tmp_path / "model.npz", "--skip-unreadable")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert "could not be read" in lines[-1] and f"{folder / 'vase_001.obj'}: {BROKEN['cracked.obj'][1]}" in lines[-1]
    assert not (tmp_path / "model.npz").exists()


def test_cli_evaluate_skips_the_unreadable_and_its_report_names_them(tmp_path):
    folder = _with_broken(tmp_path / "in", good=6)  # 2 folds need 6 shapes
    report = tmp_path / "report"
    args = ("evaluate", folder, "-o", report, "--no-figures", "--folds", 2, "--samples", 10, "--models", "ppca",
            "--landmarks", 40, "--jobs", 1)
    refused = in_process(*args)
    assert refused.returncode == 2 and not report.exists()
    _assert_names_both(refused.stderr, folder)
    result = _run(*args, "--skip-unreadable")
    assert result.returncode == 0, result.stderr
    assert len(_skipped_lines(result.stderr)) == 2
    data = json.loads((report / "report.json").read_text())["data"]
    assert data["n_shapes"] == 6 and list(data["unreadable_files"]) == ["cracked.obj", "nan.off"]
    summary = next(line for line in (report / "summary.md").read_text().splitlines() if "left out" in line)
    _assert_names_both(summary, folder)


# ---------------------------------------------------------------------------- the record in files
def test_the_record_round_trips_and_files_without_it_load_with_none(small_vases, tmp_path):
    prepared = prepare_meshes([s.mesh for s in small_vases[:3]], PrepareSettings(n_landmarks=30, align="pca"))
    prepared.unreadable = {"bad.obj": "/data/bad.obj: file is empty"}
    saved = prepared.save(tmp_path / "prepared.npz")
    assert PreparedCollection.load(saved).unreadable == prepared.unreadable
    assert prepared.turn_flagged([]).unreadable == prepared.unreadable
    with np.load(saved) as data:
        arrays = {k: data[k] for k in data.files}
    old = {k: v for k, v in arrays.items() if not k.startswith("unreadable_")}
    with open(tmp_path / "old.npz", "wb") as handle:
        np.savez(handle, **old)
    assert PreparedCollection.load(tmp_path / "old.npz").unreadable == {}
    with open(tmp_path / "bad.npz", "wb") as handle:  # names without reasons: refused, naming the file
        np.savez(handle, **{**arrays, "unreadable_reasons": np.asarray([], dtype=str)})
    with pytest.raises(ModelFileError, match="bad.npz.*unreadable_reasons"):
        PreparedCollection.load(tmp_path / "bad.npz")
