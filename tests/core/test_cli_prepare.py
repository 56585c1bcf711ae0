"""PreparedCollection persistence (safe .npz) and the `shapegen prepare` command (its runs
as a user runs them, in subprocesses; its refusals through `main` in this process)."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PREPARED_FORMAT, PrepareSettings, PreparedCollection, prepare_meshes
from shapegen_core.demo_data import make_vases, write_collection
from shapegen_core.base.errors import CollectionError, ModelFileError
from shapegen_core.base.npzfile import save_npz

from conftest import in_process

SHAPEGEN = Path(sys.executable).parent / "shapegen"


@pytest.fixture(scope="module")
def prepared(small_vases):
    return prepare_meshes([s.mesh for s in small_vases[:3]], PrepareSettings(n_landmarks=50, align="pca", seed=4))


@pytest.fixture(scope="module")
def saved(prepared, tmp_path_factory):
    return prepared.save(tmp_path_factory.mktemp("saved") / "prepared.npz")


# ---------------------------------------------------------------------------- round trip
def test_save_load_round_trip(prepared, saved):
    back = PreparedCollection.load(saved)
    assert back.names == prepared.names
    for a, b in zip(prepared.shapes, back.shapes):
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
        np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
        np.testing.assert_allclose(a.transform.matrix, b.transform.matrix, rtol=0, atol=1e-15)
        assert a.orientation_changed == b.orientation_changed
    for i, (a, b) in enumerate(zip(prepared.landmarks, back.landmarks)):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.face_index, b.face_index)
        np.testing.assert_array_equal(a.barycentric, b.barycentric)
        assert a.radius == b.radius
        np.testing.assert_allclose(back.landmarks_input(i), prepared.landmarks_input(i), atol=1e-12)
    assert back.settings.align == "pca" and back.settings.n_landmarks == 50
    assert [p.name for p in saved.parent.iterdir()] == ["prepared.npz"]  # no temporary left


def test_prepare_meshes_needs_two_unique_shapes(small_vases):
    with pytest.raises(CollectionError, match=r"at least 2 meshes.*\(vase_000\)"):
        prepare_meshes([small_vases[0].mesh], PrepareSettings(n_landmarks=20))
    with pytest.raises(CollectionError, match="repeated"):
        prepare_meshes([small_vases[0].mesh, small_vases[0].mesh], PrepareSettings(n_landmarks=20))


# ---------------------------------------------------------------------------- refused files
def _rewrite(saved: Path, target: Path, **changes) -> Path:
    with np.load(saved) as data:
        arrays = {k: data[k] for k in data.files}
    arrays.update(changes)
    with open(target, "wb") as handle:
        np.savez(handle, **arrays)
    return target


def test_truncated_file_refused(saved, tmp_path):
    raw = saved.read_bytes()
    for cut in (0, 10, len(raw) // 2, len(raw) - 5):
        path = tmp_path / f"cut{cut}.npz"
        path.write_bytes(raw[:cut])
        with pytest.raises(ModelFileError, match=f"^{path}: "):
            PreparedCollection.load(path)


def test_corrupted_member_refused(saved, tmp_path):
    raw = bytearray(saved.read_bytes())
    middle = len(raw) // 3
    raw[middle:middle + 8] = bytes(8)
    path = tmp_path / "corrupt.npz"
    path.write_bytes(bytes(raw))
    with pytest.raises(ModelFileError, match=f"^{path}: "):
        PreparedCollection.load(path)


def test_foreign_npz_refused(tmp_path):
    path = tmp_path / "foreign.npz"
    np.savez(path, weights=np.zeros((3, 3)))
    with pytest.raises(ModelFileError, match="not a ShapeGen file"):
        PreparedCollection.load(path)
    other = save_npz(tmp_path / "model.npz", "shapegen.model", 1, {"x": np.zeros(2)})
    with pytest.raises(ModelFileError, match="is a 'shapegen.model' file, expected 'shapegen.prepared'"):
        PreparedCollection.load(other)


def test_pickled_object_array_refused(saved, tmp_path):
    path = _rewrite(saved, tmp_path / "pickled.npz", names=np.array([{"evil": 1}, None, 3], dtype=object))
    with pytest.raises(ModelFileError, match="needs pickle to load; refused"):
        PreparedCollection.load(path)
    with pytest.raises(TypeError, match="refusing to write a pickle"):
        save_npz(tmp_path / "x.npz", PREPARED_FORMAT, 1, {"a": np.array([None], dtype=object)})


def test_wrong_version_refused(saved, tmp_path):
    path = _rewrite(saved, tmp_path / "v2.npz", format_version=np.asarray(2))
    with pytest.raises(ModelFileError, match="version 2 is not supported"):
        PreparedCollection.load(path)
    path = _rewrite(saved, tmp_path / "vtext.npz", format_version=np.asarray("one"))
    with pytest.raises(ModelFileError, match="not an integer version"):
        PreparedCollection.load(path)


def test_inconsistent_or_bad_content_refused(saved, tmp_path):
    with np.load(saved) as data:
        faces, offsets = data["faces"].copy(), data["vertex_offsets"].copy()
    faces[0, 0] = 10**6
    with pytest.raises(ModelFileError, match="is invalid"):
        PreparedCollection.load(_rewrite(saved, tmp_path / "faces.npz", faces=faces))
    offsets[-1] += 1
    with pytest.raises(ModelFileError, match="inconsistent"):
        PreparedCollection.load(_rewrite(saved, tmp_path / "offsets.npz", vertex_offsets=offsets))
    with pytest.raises(ModelFileError, match="missing array 'landmarks'"):
        with np.load(saved) as data:
            arrays = {k: data[k] for k in data.files if k != "landmarks"}
        np.savez(tmp_path / "missing.npz", **arrays)
        PreparedCollection.load(tmp_path / "missing.npz")
    np.save(tmp_path / "array.npy", np.zeros(3))
    with pytest.raises(ModelFileError, match="single .npy array"):
        PreparedCollection.load(tmp_path / "array.npy")
    with pytest.raises(ModelFileError, match="no such file"):
        PreparedCollection.load(tmp_path / "absent.npz")


# ---------------------------------------------------------------------------- CLI
def _run(*args, timeout=120):
    if not SHAPEGEN.exists():
        pytest.skip(f"{SHAPEGEN} is not installed in this environment")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    return subprocess.run([str(SHAPEGEN), *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.fixture(scope="module")
def vase_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("vases")
    write_collection(make_vases(3, seed=2, resolution=(10, 14)), folder, "obj")
    return folder


def test_cli_prepare_writes_the_file(vase_folder, tmp_path):
    out = tmp_path / "out" / "prepared.npz"
    result = _run("prepare", vase_folder, "-o", out, "--landmarks", "40", "--align", "pca",
                  "--scale", "bbox", "--seed", "3")
    assert result.returncode == 0, result.stderr
    assert f"prepared 3 shapes -> {out}" in result.stdout
    loaded = PreparedCollection.load(out)
    assert loaded.names == ["vase_000", "vase_001", "vase_002"]
    assert all(abs(len(l) - 40) <= 1 for l in loaded.landmarks)
    assert loaded.settings.scale == "bbox" and loaded.settings.seed == 3
    assert sorted(p.name for p in out.parent.iterdir()) == ["prepared.npz"]


@pytest.mark.parametrize("problem,fragment", [
    ("nan", "vertex 0 has a NaN or infinite coordinate"),
    ("empty", "file is empty"),
    ("range", "a face refers to a vertex that does not exist"),
])
def test_cli_bad_file_exits_2_with_one_line_naming_it(vase_folder, tmp_path, problem, fragment):
    folder = tmp_path / "in"
    folder.mkdir()
    for path in vase_folder.iterdir():
        (folder / path.name).write_bytes(path.read_bytes())
    content = {"nan": "v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "empty": "",
               "range": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n"}[problem]
    (folder / "broken.obj").write_text(content)
    out = tmp_path / "prepared.npz"
    out.write_bytes(b"previous good result")
    result = in_process("prepare", folder, "-o", out, "--landmarks", "40")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert str(folder / "broken.obj") in lines[0] and fragment in lines[0]
    assert "Traceback" not in result.stderr
    # the previous output is untouched and nothing half-written is left beside it
    assert out.read_bytes() == b"previous good result"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "prepared.npz"]


@pytest.mark.parametrize("content,fragment", [(None, "no mesh files found"), ("one", "at least 2 meshes")])
def test_cli_bad_folder_exits_2(vase_folder, tmp_path, content, fragment):
    folder = tmp_path / "in"
    folder.mkdir()
    if content == "one":
        first = sorted(vase_folder.iterdir())[0]
        (folder / first.name).write_bytes(first.read_bytes())
    out = tmp_path / "prepared.npz"
    result = in_process("prepare", folder, "-o", out)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and str(folder) in lines[0] and fragment in lines[0], result.stderr
    assert not out.exists()


def test_cli_interrupted_save_leaves_no_file(prepared, tmp_path, monkeypatch):
    """A failure while writing (here: streaming the meshes in raising half-way) leaves
    neither the output nor a temporary file."""
    import shapegen_core.base.npzfile as npzfile

    def broken(self, handle):
        handle.write(b"\x93NUMPY partial")
        raise OSError("disk full")

    monkeypatch.setattr(npzfile.Concatenation, "write", broken)
    with pytest.raises(OSError, match="disk full"):
        prepared.save(tmp_path / "prepared.npz")
    assert list(tmp_path.iterdir()) == []


def test_cli_usage_error_exits_2(tmp_path):
    result = _run("prepare", tmp_path)  # missing -o (argparse's exit, through the installed command)
    assert result.returncode == 2 and "-o/--output" in result.stderr


@pytest.mark.parametrize("count", ["2", "-5"])
def test_cli_too_few_landmarks_is_one_line_naming_the_option(vase_folder, tmp_path, count):
    """It was a traceback (select_landmarks' ValueError); now PrepareSettings refuses it."""
    out = tmp_path / "prepared.npz"
    result = in_process("prepare", vase_folder, "-o", out, "--landmarks", count)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [f"shapegen prepare: error: --landmarks must be at least 4, got {count}"]
    assert not out.exists()


# ---------------------------------------------------------------------------- pose report
UPSIDE_DOWN = np.diag([1.0, -1.0, -1.0])


@pytest.fixture(scope="module")
def upright_vases():
    """Five upright vases, vase_003 turned upside down."""
    meshes = [v.mesh for v in make_vases(5, seed=2, resolution=(12, 16), pose=False)]
    meshes[3] = meshes[3].with_vertices(meshes[3].vertices @ UPSIDE_DOWN.T)
    return meshes


@pytest.fixture(scope="module")
def upright_folder(upright_vases, tmp_path_factory):
    from shapegen_core.meshes.writing import write_mesh

    folder = tmp_path_factory.mktemp("upright")
    for mesh in upright_vases:
        write_mesh(mesh, folder / f"{mesh.name}.obj")
    return folder


def test_pose_report_saved_and_loaded(upright_vases, tmp_path):
    prepared = prepare_meshes(upright_vases, PrepareSettings(n_landmarks=30))
    turned = prepared.shapes[3]
    assert turned.pose_change.startswith("turned") and not np.allclose(turned.pose_rotation, np.eye(3))
    back = PreparedCollection.load(prepared.save(tmp_path / "prepared.npz"))
    for a, b in zip(prepared.shapes, back.shapes):
        assert (a.pose_change, a.pose_outlier, a.orientation_changed) == (b.pose_change, b.pose_outlier,
                                                                         b.orientation_changed)
        np.testing.assert_array_equal(a.pose_rotation, b.pose_rotation)


def test_file_without_pose_report_loads_as_kept(saved, tmp_path):
    with np.load(saved) as data:
        arrays = {k: data[k] for k in data.files if not k.startswith("pose_")}
    old = tmp_path / "old.npz"
    with open(old, "wb") as handle:
        np.savez(handle, **arrays)
    back = PreparedCollection.load(old)
    assert all(s.pose_change == "" and s.pose_outlier == "" and np.array_equal(s.pose_rotation, np.eye(3))
               for s in back.shapes)
    with pytest.raises(ModelFileError, match="pose_rotation"):
        PreparedCollection.load(_rewrite(saved, tmp_path / "bad.npz", pose_rotation=np.zeros((2, 3, 3))))


def test_keep_pose_by_name_or_flags(upright_vases):
    settings = PrepareSettings(n_landmarks=30)
    by_name = prepare_meshes(upright_vases, settings, keep_pose=["vase_003"])
    by_flags = prepare_meshes(upright_vases, settings, keep_pose=[i == 3 for i in range(5)])
    for prepared in (by_name, by_flags):
        kept = prepared.shapes[3]
        assert kept.pose_change == "" and np.array_equal(kept.pose_rotation, np.eye(3))
        assert "upside down" in kept.pose_outlier
    with pytest.raises(CollectionError, match="no shape named 'vase_999'"):
        prepare_meshes(upright_vases, settings, keep_pose=["vase_003", "vase_999"])


def test_cli_prints_pose_lines_and_keeps_poses_by_name(upright_folder, tmp_path):
    result = _run("prepare", upright_folder, "-o", tmp_path / "a.npz", "--landmarks", "30")
    assert result.returncode == 0, result.stderr
    assert "vase_003: turned 180° about" in result.stderr
    assert "poses: 4 kept, 1 turned, 0 flagged" in result.stderr
    result = _run("prepare", upright_folder, "-o", tmp_path / "b.npz", "--landmarks", "30", "--keep-pose", "vase_003")
    assert result.returncode == 0, result.stderr
    assert "vase_003: pose looks wrong: may be upside down" in result.stderr
    assert "poses: 5 kept, 0 turned, 1 flagged" in result.stderr
    assert PreparedCollection.load(tmp_path / "b.npz").shapes[3].pose_outlier.startswith("may be upside down")


def test_cli_keep_pose_unknown_name_or_file_source_exits_2(upright_folder, saved, tmp_path):
    result = in_process("correspond", upright_folder, "-o", tmp_path / "c.npz", "--keep-pose", "jug_1")
    assert result.returncode == 2
    assert "no shape named 'jug_1'" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    result = in_process("correspond", saved, "-o", tmp_path / "c.npz", "--keep-pose", "vase_000")
    assert result.returncode == 2 and "--keep-pose applies to a folder of meshes" in result.stderr
