"""`shapegen complete --pins` and `shapegen sample --labels` round trips on the PSB
Vase class (meshes with part labels beside them), as a user runs them (subprocesses); the
refusals, which end before any work, through `main` in this process (`in_process`)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shapegen_core.base.npzfile import load_npz, save_npz
from shapegen_core.app.shape_model import GenerativeShapeModel

from conftest import in_process, psb_class

SHAPEGEN = str(Path(sys.executable).parent / "shapegen")


def run(*args):
    return subprocess.run([SHAPEGEN, *map(str, args)], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def vase(tmp_path_factory):
    """A small PPCA model of the 5 smallest PSB vases (40 landmarks) fitted from a folder
    that holds their part labels; returns (model file, data folder, loaded model). Closest
    points named: the round trips below do not depend on where registration starts (the
    automatic start would first compute every shape's spectrum)."""
    vases = psb_class("Vase")
    folder = tmp_path_factory.mktemp("vase")
    data = folder / "data"
    data.mkdir()
    for off in sorted(vases.glob("*.off"), key=lambda path: (path.stat().st_size, path.name))[:5]:
        shutil.copy(off, data / off.name)
        shutil.copy(vases / f"{off.stem}_labels.txt", data / f"{off.stem}_labels.txt")
    result = run("fit", data, "-o", folder / "model.npz", "--model", "ppca", "--landmarks", 40, "--up", "y",
                 "--initialisation", "closest", "--jobs", 1)
    assert result.returncode == 0, result.stderr
    assert "part labels of 5 shape(s)" in result.stdout
    return folder / "model.npz", data, GenerativeShapeModel.load(folder / "model.npz")


def _obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    lines = path.read_text().splitlines()
    vertices = np.array([[float(v) for v in line.split()[1:4]] for line in lines if line.startswith("v ")])
    faces = np.array([[int(c.split("/")[0]) - 1 for c in line.split()[1:]] for line in lines if line.startswith("f ")])
    return vertices, faces


def _labels(path: Path) -> dict[str, np.ndarray]:
    lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    return {name: np.asarray(ids.split(), dtype=np.int64) for name, ids in zip(lines[0::2], lines[1::2])}


# ----------------------------------------------------------------------------- --pins

def test_complete_from_pins_round_trip(vase, tmp_path):
    model_file, _, model = vase
    target = model.correspondence.points[1]
    chosen = range(0, model.n_landmarks, 4)
    pins = [{"landmark": i, "position": (target[i] @ model.file_axes).tolist()} for i in chosen]
    (tmp_path / "pins.json").write_text(json.dumps(pins))
    out = tmp_path / "done"
    result = run("complete", model_file, "--pins", tmp_path / "pins.json", "-o", out, "--std")
    assert result.returncode == 0, result.stderr
    assert f"from {len(pins)} pin(s)" in result.stdout

    expected = model.complete_from_pins({i: target[i] for i in chosen})
    arrays = np.load(out / "completed.npz", allow_pickle=False)
    np.testing.assert_allclose(arrays["landmarks"][0], expected.landmarks, atol=1e-9)
    np.testing.assert_allclose(arrays["landmark_std"][0], expected.std, atol=1e-9)
    np.testing.assert_array_equal(arrays["pin_landmarks"], list(chosen))
    # the pins are the shape's own landmarks: the model reaches them within its reconstruction error
    reconstruction = model.decode(model.encode(target[None]))[0]
    assert arrays["pin_distances"].max() <= 2 * np.linalg.norm(reconstruction - target, axis=1).max() + 1e-9

    # the mesh is written in the files' axes, on the template the command names
    template = str(arrays["templates"][0])
    vertices, _ = _obj(out / "completed_0000.obj")
    meshed = model.mesh_from_landmarks(expected.landmarks, template=template).vertices @ model.file_axes
    np.testing.assert_allclose(vertices, meshed, atol=1e-6)
    std = load_npz(out / "completed_0000_std.npz", "shapegen.vertex_std", 1, {})["vertex_std"]
    assert std.shape == (len(vertices),) and np.all(np.isfinite(std)) and np.all(std >= 0)
    np.testing.assert_allclose(std, model.vertex_std(expected.std, model.shape_index(template)), atol=1e-12)


@pytest.mark.parametrize("pins, message", [
    ("not json", "not a JSON pins file"),
    ("[]", "non-empty JSON list"),
    ('[{"landmark": 0}]', "pin 0: must be"),
    ('[{"landmark": 100000, "position": [0, 0, 0]}]', "landmark must be an integer from 0"),
    ('[{"landmark": 1, "position": [0, "a", 0]}]', "position must be 3 finite numbers"),
    ('[{"landmark": 1, "position": [0, 0, 0]}, {"landmark": 1, "position": [1, 0, 0]}]', "pinned twice"),
])
def test_bad_pins_files_are_one_line_errors(vase, tmp_path, pins, message):
    (tmp_path / "pins.json").write_text(pins)
    result = in_process("complete", vase[0], "--pins", tmp_path / "pins.json", "-o", tmp_path / "out")
    assert result.returncode == 2 and message in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_partial_and_pins_exclude_each_other_and_std_needs_pins(vase, tmp_path):
    (tmp_path / "pins.json").write_text('[{"landmark": 0, "position": [0, 0, 0]}]')
    both = in_process("complete", vase[0], tmp_path / "partial.npz", "--pins", tmp_path / "pins.json",
                      "-o", tmp_path / "a")
    neither = in_process("complete", vase[0], "-o", tmp_path / "b")
    std = in_process("complete", vase[0], tmp_path / "partial.npz", "--std", "-o", tmp_path / "c")
    for result, message in ((both, "not both"), (neither, "give PARTIAL"), (std, "--std needs --pins")):
        assert result.returncode == 2 and message in result.stderr


# ----------------------------------------------------------------------------- --labels

def test_sample_labels_cover_every_face_with_the_templates_parts(vase, tmp_path):
    model_file, data, model = vase
    assert model.part_labels is not None and set(model.part_labels.names) >= {"body"}
    out = tmp_path / "samples"
    result = run("sample", model_file, "-n", 3, "-o", out, "--seed", 2, "--labels")
    assert result.returncode == 0, result.stderr
    templates = [str(t) for t in np.load(out / "landmarks.npz")["templates"]]
    for i, template in enumerate(templates):
        _, faces = _obj(out / f"sample_{i:04d}.obj")
        written = _labels(out / f"sample_{i:04d}_labels.txt")
        ids = np.sort(np.concatenate(list(written.values())))
        np.testing.assert_array_equal(ids, np.arange(1, len(faces) + 1))        # every face, once
        # independently: each written face is a face of the template's file, whose labels say its part
        lines = (data / f"{template}.off").read_text().split("\n")
        n_vertices, n_faces = map(int, lines[1].split()[:2])
        file_faces = np.array([[int(v) for v in line.split()[1:4]] for line in lines[2 + n_vertices: 2 + n_vertices + n_faces]])
        part_of = {}
        for name, file_ids in _labels(data / f"{template}_labels.txt").items():
            for face in file_faces[file_ids - 1]:
                part_of[tuple(sorted(face))] = name
        for name, face_ids in written.items():
            for face in faces[face_ids - 1]:
                assert part_of[tuple(sorted(face))] == name


def test_models_without_labels_load_and_refuse_sample_labels(vase, tmp_path):
    """A model file written before part labels were saved (no label arrays) still loads;
    asking it for labels is a one-line error."""
    model_file = vase[0]
    with np.load(model_file, allow_pickle=False) as stored:
        arrays = {key: stored[key] for key in stored.files
                  if key not in ("label_names", "mesh_face_labels", "format", "format_version")}
        version = int(stored["format_version"])
    old = tmp_path / "old.npz"
    save_npz(old, "shapegen.model", version, arrays)
    assert GenerativeShapeModel.load(old).part_labels is None
    result = in_process("sample", old, "-n", 1, "-o", tmp_path / "out", "--labels")
    assert result.returncode == 2 and "records no part labels" in result.stderr
    assert not (tmp_path / "out").exists()
