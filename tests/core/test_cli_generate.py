"""`shapegen fit | info | sample | complete | morph` as a user runs them (subprocesses); the
refusals, which end before any work, and the `info` and `sample` runs that only read back
what a test's run wrote, through `main` in this process (`in_process`)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from shapegen_core.demo_data import make_vases, write_collection
from shapegen_core.base.npzfile import load_npz, save_npz, ArraySpec

from conftest import in_process

SHAPEGEN = str(Path(sys.executable).parent / "shapegen")


def run(*args):
    return subprocess.run([SHAPEGEN, *map(str, args)], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    write_collection(make_vases(6, seed=5, resolution=(14, 18)), folder / "data")
    result = run("fit", folder / "data", "-o", folder / "model.npz", "--model", "ppca", "--landmarks", 60, "--jobs", 1)
    assert result.returncode == 0, result.stderr
    assert "fitted ppca" in result.stdout
    assert "; closest start (the shapes lie " in result.stdout  # the default: the start the collection chose, and why
    return folder / "model.npz"


def test_info_describes_the_model(model_file):
    result = run("info", model_file, "--json")
    assert result.returncode == 0, result.stderr
    info = json.loads(result.stdout)
    assert info["model"] == "ppca" and info["shapes"] == 6 and abs(info["landmarks"] - 60) <= 2


def test_sample_writes_meshes_and_landmarks_that_load_back(model_file, tmp_path):
    out = tmp_path / "samples"
    result = run("sample", model_file, "-n", 3, "-o", out, "--seed", 3, "--format", "ply")
    assert result.returncode == 0, result.stderr
    arrays = load_npz(out / "landmarks.npz", "shapegen.samples", 1, {"landmarks": ArraySpec("f", (3, None, 3))})
    templates = [str(t) for t in np.load(out / "landmarks.npz")["templates"]]
    for i in range(3):
        mesh = trimesh.load(out / f"sample_{i:04d}.ply", process=False)
        # every sample is a deformed training mesh: same counts as its template
        source = trimesh.load(model_file.parent / "data" / f"{templates[i]}.obj", process=False)
        assert len(mesh.vertices) == len(source.vertices) and len(mesh.faces) == len(source.faces)
    again = tmp_path / "again"
    run("sample", model_file, "-n", 3, "-o", again, "--seed", 3, "--format", "ply")
    np.testing.assert_array_equal(np.load(again / "landmarks.npz")["landmarks"], arrays["landmarks"])


def test_sample_reports_the_quality_gate_and_records_seeds(model_file, tmp_path):
    out = tmp_path / "gated"
    result = run("sample", model_file, "-n", 3, "-o", out, "--seed", 3, "--max-redraws", 0)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("quality gate: ")
    saved = np.load(out / "landmarks.npz")
    assert saved["seeds"].tolist() == [3, 4, 5]  # no redraws: sample i keeps seed 3 + i
    assert len(saved["rejected_seed"]) == len(saved["rejected_reasons"]) == len(saved["rejected_sample"])
    assert saved["quality"].shape == (3,)
    result = in_process("sample", model_file, "-n", 2, "-o", tmp_path / "bad", "--max-redraws", -1)
    assert result.returncode == 2 and "--max-redraws must be at least 0" in result.stderr


@pytest.fixture(scope="module")
def exploding_model_file(model_file):
    """The vase model drawing every shape five times the class's size (its mean and modes
    scaled): no draw can pass the quality gate's extent check, as with a model gone wrong."""
    from shapegen_core.app.shape_model import GenerativeShapeModel

    model = GenerativeShapeModel.load(model_file)
    model.model.mean_ = model.model.mean_ * 5.0
    model.model.components_ = model.model.components_ * 5.0
    model.model.noise_variance_ = model.model.noise_variance_ * 25.0
    model.model._prepare()
    return model.save(model_file.parent / "exploding.npz")


def test_a_run_whose_samples_fail_the_gate_writes_nothing_and_exits_2(exploding_model_file, tmp_path):
    """It wrote the last failing draw among the good samples and exited 0."""
    out = tmp_path / "broken"
    result = run("sample", exploding_model_file, "-n", 2, "-o", out, "--max-redraws", 1)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [result.stderr.strip()]  # one line
    assert ("shapegen sample: error: 0 of 2 samples passed the quality gate within the budget of 4 draws; 2 still "
            "fail (commonest reasons over their ") in result.stderr
    assert "extent " in result.stderr and "nothing written" in result.stderr
    assert "2 still fail after 4 draws in all" in result.stdout  # what the gate did, on stdout as for a good run
    assert not out.exists() and not list(tmp_path.glob(".broken*"))


def test_keep_failed_writes_only_the_failing_samples_with_their_reasons(exploding_model_file, tmp_path):
    out = tmp_path / "kept"
    result = run("sample", exploding_model_file, "-n", 2, "-o", out, "--max-redraws", 1, "--keep-failed",
                 "--seed", 5)
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert f"the failing ones are in {out / 'failed'}" in result.stderr
    assert sorted(p.name for p in out.iterdir()) == ["failed"]
    failed = out / "failed"
    assert sorted(p.name for p in failed.iterdir()) == ["landmarks.npz", "reasons.txt", "sample_0000.obj",
                                                         "sample_0001.obj"]
    saved = np.load(failed / "landmarks.npz")
    assert saved["names"].tolist() == ["sample_0000", "sample_0001"]
    assert saved["seeds"].tolist() == [5 + 2, 6 + 2]  # each sample's last draw (redraw 1: seed + n)
    assert all(reason.startswith("extent: ") for reason in saved["quality"])
    assert set(saved["rejected_sample"].tolist()) == {0, 1} and len(saved["rejected_reasons"]) == \
        len(saved["rejected_seed"]) == len(saved["rejected_template"])
    lines = (failed / "reasons.txt").read_text().splitlines()
    assert [line.split(":")[0] for line in lines] == ["sample_0000", "sample_0001"]
    stiffness = f"{saved['stiffness'][0]:g}"  # its last mesh: the stiffer re-mesh on its last template
    assert lines[0].startswith(f"sample_0000: seed 7 on {saved['templates'][0]} (stiffness {stiffness}) after 2 "
                               "draw(s): extent: ")
    mesh = trimesh.load(failed / "sample_0000.obj", process=False)
    source = trimesh.load(exploding_model_file.parent / "data" / f"{saved['templates'][0]}.obj", process=False)
    assert len(mesh.faces) == len(source.faces)


def test_a_short_run_writes_none_of_its_passing_samples(model_file, tmp_path, monkeypatch, capsys):
    """One of three samples fails on every draw (a gate refusing its seeds): the two that
    pass are not written either, and --keep-failed writes only the failing one."""
    from shapegen_core.generate import sampling
    from shapegen_core.app.cli import main
    from shapegen_core.generate.quality import MeshQuality

    draw, seeds = sampling._draw, []

    def recording(model, seed):
        seeds.append(seed)
        return draw(model, seed)

    class Gate:
        def check(self, mesh, template_index):
            bad = (seeds[-1] - 1) % 3 == 0  # sample 1 of a run of 3 from seed 0, on every redraw
            return MeshQuality(9 if bad else 0, 0.1, 0.1, 0.05, 0, 1.0, 1.0, ("flipped: 9 face(s)",) if bad else ())

    monkeypatch.setattr(sampling, "_draw", recording)
    monkeypatch.setattr(sampling, "quality_gate", lambda model, settings: Gate())
    assert main(["sample", str(model_file), "-n", "3", "-o", str(tmp_path / "short"), "--max-redraws", "2",
                 "--jobs", "1"]) == 2
    err = capsys.readouterr().err
    assert "2 of 3 samples passed the quality gate within the budget of 9 draws; 1 still fail (commonest reasons " \
           "over their " in err and "flipped " in err
    assert not (tmp_path / "short").exists()
    assert main(["sample", str(model_file), "-n", "3", "-o", str(tmp_path / "kept"), "--max-redraws", "2",
                 "--jobs", "1", "--keep-failed"]) == 2
    assert sorted(p.relative_to(tmp_path / "kept").as_posix() for p in (tmp_path / "kept").rglob("*")) == \
        ["failed", "failed/landmarks.npz", "failed/reasons.txt", "failed/sample_0001.obj"]
    assert (tmp_path / "kept" / "failed" / "reasons.txt").read_text().startswith(
        "sample_0001: seed 19 on ")  # its 7th draw: 3 of its own, then the 4 the others left
    assert "after 7 draw(s): flipped: 9 face(s)" in (tmp_path / "kept" / "failed" / "reasons.txt").read_text()


def test_sample_refuses_a_non_empty_folder_and_unknown_template_writes_nothing(model_file, tmp_path):
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "keep.txt").write_text("mine")
    result = in_process("sample", model_file, "-n", 2, "-o", busy)
    assert result.returncode == 2 and "not empty" in result.stderr
    assert sorted(p.name for p in busy.iterdir()) == ["keep.txt"]
    fresh = tmp_path / "fresh"
    result = in_process("sample", model_file, "-n", 2, "-o", fresh, "--template", "no_such_vase")
    assert result.returncode == 2 and "no_such_vase" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert not fresh.exists() and not list(tmp_path.glob(".fresh*"))


def test_complete_fills_missing_landmarks(model_file, tmp_path):
    from shapegen_core.app.shape_model import GenerativeShapeModel

    model = GenerativeShapeModel.load(model_file)
    partial = model.correspondence.points[:2].copy()
    partial[:, :10] = np.nan
    save_npz(tmp_path / "partial.npz", "shapegen.partial", 1, {"landmarks": partial})
    result = run("complete", model_file, tmp_path / "partial.npz", "-o", tmp_path / "done")
    assert result.returncode == 0, result.stderr
    done = np.load(tmp_path / "done" / "completed.npz")["landmarks"]
    assert np.isfinite(done).all()
    np.testing.assert_allclose(done[:, 10:], partial[:, 10:])
    assert (tmp_path / "done" / "completed_0001.obj").is_file()


def test_morph_ends_at_the_two_training_shapes(model_file, tmp_path):
    from shapegen_core.app.shape_model import GenerativeShapeModel

    model = GenerativeShapeModel.load(model_file)
    a, b = model.names[0], model.names[4]
    result = run("morph", model_file, a, b, "-n", 4, "-o", tmp_path / "morph")
    assert result.returncode == 0, result.stderr
    landmarks = np.load(tmp_path / "morph" / "landmarks.npz")["landmarks"]
    assert landmarks.shape[0] == 4
    ends = model.decode(model.training_latents()[[0, 4]])
    np.testing.assert_allclose(landmarks[[0, -1]], ends, atol=1e-9)


def test_a_latent_path_holds_its_ends_and_even_steps_between():
    from shapegen_core.app.shape_model import PATH_SHAPES, GenerativeShapeModel
    from shapegen_core.base.errors import ShapeGenError

    a, b = np.array([1.0, -2.0, 0.5]), np.array([-3.0, 2.0, 4.5])
    weights, path = GenerativeShapeModel.latent_path(a, b)
    assert len(path) == PATH_SHAPES == 8
    np.testing.assert_array_equal(path[[0, -1]], [a, b])
    np.testing.assert_allclose(weights, np.arange(8) / 7, atol=1e-15)
    np.testing.assert_allclose(np.diff(path, axis=0), np.tile((b - a) / 7, (7, 1)), atol=1e-14)
    with pytest.raises(ShapeGenError, match="at least 2 shapes"):
        GenerativeShapeModel.latent_path(a, b, 1)


def _morph_meshes(folder: Path, steps: int):
    return [trimesh.load(folder / f"morph_{k:03d}.obj", process=False, force="mesh") for k in range(steps)]


def test_a_morph_keeps_one_mesh_and_moves_evenly(model_file, tmp_path):
    """Every step of a morph is one template's mesh (one face list), so the path has no jump:
    no step moves more than 2.5x the median step. The ends are the two training shapes
    farthest apart in latent space, whose nearest templates differ."""
    from shapegen_core.app.shape_model import GenerativeShapeModel

    model = GenerativeShapeModel.load(model_file)
    latents = model.training_latents()
    distance = ((latents[:, None] - latents[None]) ** 2).sum(axis=2)
    a, b = np.unravel_index(np.argmax(distance), distance.shape)
    ends = model.decode(latents[[a, b]])
    assert model.choose_template(ends[0], None) != model.choose_template(ends[1], None)
    steps = 8
    result = run("morph", model_file, model.names[a], model.names[b], "-n", steps, "-o", tmp_path / "morph")
    assert result.returncode == 0, result.stderr
    meshes = _morph_meshes(tmp_path / "morph", steps)
    for mesh in meshes[1:]:
        np.testing.assert_array_equal(mesh.faces, meshes[0].faces)
    moves = [np.sqrt(((later.vertices - earlier.vertices) ** 2).sum(axis=1).mean())
             for earlier, later in zip(meshes, meshes[1:])]
    assert max(moves) <= 2.5 * np.median(moves), moves
    template = model.names[model.path_template(latents[a], latents[b], None)]
    assert f"all on template {template}" in result.stdout


def test_a_morph_on_a_named_template_uses_its_mesh(model_file, tmp_path):
    from shapegen_core.app.shape_model import GenerativeShapeModel

    model = GenerativeShapeModel.load(model_file)
    result = run("morph", model_file, model.names[0], model.names[1], "-n", 3, "--template", model.names[5],
                 "-o", tmp_path / "morph")
    assert result.returncode == 0, result.stderr
    for mesh in _morph_meshes(tmp_path / "morph", 3):
        assert len(mesh.faces) == len(model.meshes[5].faces)


def test_a_corrupt_model_file_is_one_line_naming_it(tmp_path):
    bad = tmp_path / "model.npz"
    bad.write_bytes(b"not a zip")
    result = in_process("sample", bad, "-n", 1, "-o", tmp_path / "out")
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and str(bad) in result.stderr


def test_fit_from_a_correspondence_file_needs_and_uses_the_mesh_folder(model_file, tmp_path):
    data = model_file.parent / "data"
    corr = tmp_path / "corr.npz"
    # closest points named: the start is not what this test checks (the automatic one would
    # first compute every shape's spectrum)
    result = run("correspond", data, "-o", corr, "--landmarks", 60, "--initialisation", "closest", "--jobs", 1)
    assert result.returncode == 0, result.stderr
    result = in_process("fit", corr, "-o", tmp_path / "m.npz", "--model", "ppca")
    assert result.returncode == 2 and "--meshes" in result.stderr
    assert not (tmp_path / "m.npz").exists()
    result = run("fit", corr, "-o", tmp_path / "m.npz", "--model", "ppca", "--meshes", data)
    assert result.returncode == 0, result.stderr
    info = json.loads(in_process("info", tmp_path / "m.npz", "--json").stdout)
    assert info["model"] == "ppca" and info["shapes"] == 6 and info["metadata"]["n_shapes"] == "6"
    assert info["settings"]["prepare"]["n_landmarks"] == 60  # the file records how it was prepared
    assert "note:" not in result.stderr
    assert f"[fit] using {corr} as given (with the settings it records); fitting" in result.stderr
    result = in_process("fit", corr, "-o", tmp_path / "m2.npz", "--meshes", data, "--landmarks", 100)
    assert result.returncode == 2 and f"--landmarks 100 conflicts with {corr}" in result.stderr
    result = in_process("fit", corr, "-o", tmp_path / "m2.npz", "--meshes", data, "--matching", "features")
    assert result.returncode == 2  # the model records the file's correspondence settings: others cannot be asked for
    assert f"--matching features conflicts with {corr}, corresponded with --matching closest" in result.stderr


# ---------------------------------------------------------------------------- settings on the command line
def test_every_source_command_takes_the_same_prepare_options(tmp_path):
    from shapegen_core.app.cli import build_parser
    from shapegen_core.preprocess.collection import PrepareSettings
    from shapegen_core.app.cli_common import settings_from_args

    options = ["--landmarks", "50", "--up", "y", "--align", "pca", "--scale", "bbox", "--centre", "none", "--seed", "3"]
    expected = PrepareSettings(n_landmarks=50, up_axis="y", align="pca", scale="bbox", centre="none", seed=3)
    for command in ("prepare", "correspond", "fit", "evaluate"):
        args = build_parser().parse_args([command, str(tmp_path), "-o", str(tmp_path / "out"), *options])
        assert settings_from_args(PrepareSettings, args) == expected, command


@pytest.mark.parametrize("option,message", [
    (["--landmarks", "2"], "--landmarks must be at least 4, got 2"),
    (["--stiffness", "0"], "--stiffness must be greater than 0, got 0.0"),
    (["--latent-dim", "0"], "--latent-dim must be at least 1, got 0"),
])
def test_fit_refuses_bad_settings_in_one_line_before_any_work(model_file, tmp_path, option, message):
    """--stiffness 0 was saved, and `sample` then failed with "Factor is exactly singular"."""
    result = in_process("fit", model_file.parent / "data", "-o", tmp_path / "m.npz", *option)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [f"shapegen fit: error: {message}"]
    assert not (tmp_path / "m.npz").exists()


def test_fit_of_a_prepared_file_records_its_settings_and_refuses_conflicts(model_file, tmp_path):
    """It recorded the CLI's defaults (800 landmarks, up z) instead of the file's."""
    from shapegen_core.app.shape_model import GenerativeShapeModel

    prepared = tmp_path / "prepared.npz"
    assert run("prepare", model_file.parent / "data", "-o", prepared, "--landmarks", 50, "--up", "y").returncode == 0
    # closest points named: the start is not what this test checks (the automatic one would
    # first compute every shape's spectrum)
    result = run("fit", prepared, "-o", tmp_path / "m.npz", "--model", "ppca", "--initialisation", "closest",
                 "--jobs", 1)
    assert result.returncode == 0, result.stderr
    assert f"[fit] using {prepared} as given (with the settings it records); corresponding and fitting" \
        in result.stderr
    recorded = GenerativeShapeModel.load(tmp_path / "m.npz").settings.prepare
    assert (recorded.n_landmarks, recorded.up_axis) == (50, "y")
    info = json.loads(in_process("info", tmp_path / "m.npz", "--json").stdout)
    assert info["settings"]["prepare"]["up_axis"] == "y"
    # samples are written in the files' axes: a vase whose files stand along Z (read
    # "Y up", so it lies along the model's x) is written standing along Z again
    assert in_process("sample", tmp_path / "m.npz", "-n", 1, "-o", tmp_path / "samples").returncode == 0
    written = trimesh.load(tmp_path / "samples" / "sample_0000.obj", process=False).extents
    given = trimesh.load(next((model_file.parent / "data").glob("*.obj")), process=False).extents
    assert np.argmax(written) == np.argmax(given) == 2
    result = in_process("fit", prepared, "-o", tmp_path / "m2.npz", "--model", "ppca", "--up", "z")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert f"--up z conflicts with {prepared}, prepared with --up y" in result.stderr
    assert not (tmp_path / "m2.npz").exists()


# ---------------------------------------------------------------------------- parallel sample
def test_parallel_sample_gives_workers_contiguous_template_runs_and_one_blas_thread(monkeypatch, tmp_path):
    """Items were dealt round-robin (every worker built every template's mesh map), and
    OPENBLAS_NUM_THREADS was set in the workers only after numpy had loaded."""
    import argparse
    import os
    from concurrent.futures import Future

    from shapegen_core.app import cli_sample
    from shapegen_core.generate.quality import MeshQuality
    from shapegen_core.generate.sampling import GatedSample, sample_name

    submitted, seen = [], {}

    class RecordingPool:
        def __init__(self, jobs, **kwargs):
            seen["jobs"], seen["blas"] = jobs, os.environ.get("OPENBLAS_NUM_THREADS")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def submit(self, fn, run, chunk):
            submitted.append(chunk)
            future = Future()
            future.set_result([passing(index) for index, _ in chunk])
            return future

    def passing(index):
        quality = MeshQuality(0, 0.0, 0.1, 0.05, 0, 1.0, 1.0)
        return GatedSample(index, sample_name(index), index, np.zeros((2, 3)), np.zeros(1), 0, None, quality, 1.0)

    monkeypatch.setattr(cli_sample, "ProcessPoolExecutor", RecordingPool)
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "4")
    templates = [["vase_a", "vase_b", "vase_c"][i % 3] for i in range(90)]
    args = argparse.Namespace(jobs=3, model=tmp_path / "model.npz", scheduler=None)
    run = cli_sample.SampleRun(90, 0, None, str(tmp_path), "obj", 0, False, "{}")
    samples = cli_sample._write_samples(args, None, run, templates)
    assert seen == {"jobs": 3, "blas": "1"} and os.environ["OPENBLAS_NUM_THREADS"] == "4"
    assert [sorted({templates[i] for i, _ in chunk}) for chunk in submitted] == [["vase_a"], ["vase_b"], ["vase_c"]]
    assert sorted(i for chunk in submitted for i, _ in chunk) == list(range(90))
    assert {draws for chunk in submitted for _, draws in chunk} == {range(21)}  # round 0: 1 + max_redraws each
    assert [s.index for s in samples] == list(range(90))
