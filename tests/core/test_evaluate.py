"""Evaluation metrics (core/evaluation) on cases with known answers, and the
`shapegen evaluate` report: reproducible byte for byte, clear errors on bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
from shapegen_core.correspond import correspond
from shapegen_core.demo_data import make_vases, write_collection
from shapegen_core.evaluation import (EvaluationError, EvaluationSettings, TrainingSetModel, choose_morph_endpoints,
                                    completion_errors,
                                    coverage, generalisation_curve, hidden_coordinates, kfold_indices,
                                    landmark_rms_matrix, latent_outlier_scores, mmd, novelty, one_nna,
                                    one_nna_chance_level, parse_model_names, ppca_nll_curve, procrustes_align,
                                    procrustes_rms_matrix, region_mask, run_evaluation, specificity)
from shapegen_core.models import PPCA

from conftest import in_process

SHAPEGEN = Path(sys.executable).parent / "shapegen"


def shape_set(rng, n, n_landmarks=12, spread=0.3):
    """n shapes: a fixed base cloud plus independent Gaussian perturbations, rows (n, 3L)."""
    base = np.random.default_rng(0).normal(size=(n_landmarks, 3))
    return (base[None] + spread * rng.normal(size=(n, n_landmarks, 3))).reshape(n, -1)


# ---------------------------------------------------------------------------- distances
def test_procrustes_distance_ignores_similarity_transforms(rng):
    b = rng.normal(size=(30, 3))
    a = 2.5 * b @ Rotation.random(random_state=3).as_matrix().T + [1.0, -2.0, 0.5]
    # the closed form subtracts two nearly equal terms: zero to about 1e-8 of b's size (its
    # docstring), how close depends on the LAPACK behind the SVD; the alignment itself is exact
    size = np.sqrt(np.mean(np.sum((b - b.mean(0)) ** 2, 1)))
    assert procrustes_rms_matrix(a[None], b[None])[0, 0] < 1e-7 * size
    np.testing.assert_allclose(procrustes_align(a, b), b, atol=1e-12)
    # rigid alignment cannot undo the scale: residual = RMS of (2.5 - 1) * centred b
    rigid = procrustes_rms_matrix(a[None], b[None], scaling=False)[0, 0]
    bc = b - b.mean(0)
    assert rigid == pytest.approx(1.5 * np.sqrt(np.mean(np.sum(bc**2, 1))), rel=1e-10)


def test_procrustes_distance_matches_explicit_alignment(rng):
    A, B = rng.normal(size=(3, 20, 3)), rng.normal(size=(4, 20, 3))
    D = procrustes_rms_matrix(A, B)
    for i in range(3):
        for j in range(4):
            aligned = procrustes_align(A[i], B[j])
            assert D[i, j] == pytest.approx(np.sqrt(np.mean(np.sum((aligned - B[j]) ** 2, 1))), rel=1e-9)
            assert D[i, j] <= landmark_rms_matrix(A[i][None], B[j][None])[0, 0] + 1e-12


# ---------------------------------------------------------------------------- sample metrics
def test_identical_sets_have_zero_mmd_full_coverage_and_memorised_1nna(rng):
    X = shape_set(rng, 15)
    assert mmd(X, X) == 0.0
    assert coverage(X, X) == 1.0
    assert one_nna(X, X.copy()) == 0.0          # every sample has a reference twin


def test_two_large_draws_of_one_distribution_are_indistinguishable():
    X, R = shape_set(np.random.default_rng(1), 400, 5), shape_set(np.random.default_rng(2), 400, 5)
    assert one_nna(X, R) == pytest.approx(0.5, abs=0.05)
    assert one_nna_chance_level(400) == pytest.approx(0.5, abs=1e-3)
    shifted = X + 0.5                          # another distribution: separable, larger MMD
    assert one_nna(shifted, R) > 0.9
    assert mmd(shifted, R) > 5 * mmd(X, R)
    assert coverage(X, R) > 0.2


def test_coverage_of_a_collapsed_sampler_is_one_over_n(rng):
    R = shape_set(rng, 10)
    collapsed = np.repeat(R[3:4], 10, axis=0) + 1e-6
    assert coverage(collapsed, R) == pytest.approx(0.1)


def test_memorising_model_has_zero_novelty_and_specificity(rng):
    Y = shape_set(rng, 12)
    model = TrainingSetModel().fit(Y)
    samples = model.sample(12, np.random.default_rng(0))
    result = novelty(samples, Y)
    np.testing.assert_allclose(result["distance"], 0.0, atol=1e-7)   # closed form: 0 up to rounding
    np.testing.assert_array_equal(Y[result["nearest"]], samples)
    assert specificity(samples, Y) == pytest.approx(0.0, abs=1e-7)
    # a sampler that adds structure-free noise is measurably novel
    assert specificity(samples + 0.2 * rng.normal(size=samples.shape), Y) > 0.05


def test_one_nna_needs_balanced_sets(rng):
    with pytest.raises(EvaluationError, match="equally many"):
        one_nna(shape_set(rng, 4), shape_set(rng, 5))


# ---------------------------------------------------------------------------- completion
def test_region_masks_select_thirds_of_the_extent():
    z = np.linspace(0.0, 3.0, 31)
    points = np.stack([3.0 - z, np.zeros_like(z), z], 1)       # x runs opposite to z
    top = region_mask(points, "top")
    np.testing.assert_array_equal(top, z > 2.0)
    np.testing.assert_array_equal(region_mask(points, "middle"), (z >= 1.0) & (z <= 2.0))
    np.testing.assert_array_equal(region_mask(points, "rear"), 3.0 - z < 1.0)
    np.testing.assert_array_equal(hidden_coordinates(top)[::3], top)
    with pytest.raises(EvaluationError, match="unknown completion region"):
        region_mask(points, "left")


def test_completion_error_is_the_summed_squared_error_of_hidden_coordinates():
    truth = np.zeros((2, 6))
    guess = truth.copy()
    guess[0, 3:] = [1.0, 2.0, 2.0]               # hidden landmark 2 of shape 0 off by 3
    guess[1, :3] = 5.0                           # a visible coordinate: does not count
    hidden = hidden_coordinates(np.array([False, True]))
    np.testing.assert_allclose(completion_errors(truth, guess, hidden), [9.0, 0.0])


def test_a_perfect_oracle_completes_with_zero_error(rng):
    Y = shape_set(rng, 10)
    test = Y[7:]
    oracle = TrainingSetModel().fit(Y)           # it has seen the test shapes: an oracle
    hidden = hidden_coordinates(region_mask(Y.mean(0), "top"))
    observed = np.broadcast_to(~hidden, test.shape).copy()
    completed = oracle.complete(np.where(observed, test, np.nan), observed)
    np.testing.assert_array_equal(completion_errors(test, completed, hidden), 0.0)
    # and a real model that never saw them does worse than that, better than the mean shape
    model = PPCA().fit(Y[:7])
    errors = completion_errors(test, model.complete(np.where(observed, test, np.nan), observed), hidden)
    assert np.all(errors > 0)


# ---------------------------------------------------------------------------- curves, map
def test_generalisation_is_zero_once_the_modes_span_the_data(rng):
    basis = rng.normal(size=(2, 30))
    Y = 1.0 + rng.normal(size=(9, 2)) @ basis           # a 2-D affine subspace
    curve = generalisation_curve(Y)
    assert curve["mean"][0] > 1e-3
    np.testing.assert_allclose(curve["mean"][1:], 0.0, atol=1e-10)


def test_ppca_nll_curve_prefers_the_true_dimension(rng):
    basis = rng.normal(size=(3, 60))
    Y = rng.normal(size=(30, 3)) @ basis + 0.01 * rng.normal(size=(30, 60))
    folds = kfold_indices(30, 5, np.random.default_rng(0))
    curve = ppca_nll_curve(Y, folds, max_latent_dim=8)
    assert curve["latent_dims"] == list(range(1, 9))
    assert np.all(np.diff(curve["train_nll"]) < 0)
    test = curve["test_nll"]
    assert test[2] < test[1] < test[0]                   # large gains up to q = 3 ...
    assert abs(test[7] - test[2]) < 0.05 * abs(test[0] - test[2])   # ... then a plateau


def test_latent_outlier_score_flags_a_far_point(rng):
    Z = rng.normal(size=(20, 2))
    Z[5] = [12.0, -9.0]
    result = latent_outlier_scores(Z, bandwidth=1.0)
    assert np.argmax(result["robust_z"]) == 5
    assert result["flagged"][5] and result["flagged"].sum() <= 2


def test_morph_endpoints_do_not_cross_empty_latent_space():
    line = np.stack([np.linspace(0.0, 2.0, 9), np.zeros(9)], 1)      # a dense cluster along x
    Z = np.vstack([line, [[10.0, 10.0]]])                             # and one far, lonely point
    assert choose_morph_endpoints(Z, bandwidth=0.3) == (0, 8)         # the ends of the cluster


# ---------------------------------------------------------------------------- settings
def test_kfold_partitions_and_bad_fold_counts():
    folds = kfold_indices(11, 4, np.random.default_rng(0))
    assert sorted(np.concatenate(folds).tolist()) == list(range(11))
    assert sorted(len(f) for f in folds) == [2, 3, 3, 3]
    with pytest.raises(EvaluationError, match="5 folds need at least 5 shapes"):
        kfold_indices(4, 5, np.random.default_rng(0))
    with pytest.raises(EvaluationError, match=">= 2"):
        kfold_indices(4, 1, np.random.default_rng(0))


def test_unknown_model_names_are_refused():
    assert parse_model_names("PPCA, bgplvm,ppca") == ["ppca", "bgplvm"]
    with pytest.raises(EvaluationError, match=r"unknown model name\(s\) 'vae' \(known: ppca, gplvm, bgplvm\)"):
        parse_model_names("ppca,vae")


def test_run_evaluation_refuses_more_folds_than_shapes(rng):
    with pytest.raises(EvaluationError, match="--folds 9 is more than the 8 shapes"):
        run_evaluation(shape_set(rng, 8), [str(i) for i in range(8)], EvaluationSettings(folds=9))


def test_run_evaluation_numbers_on_a_small_set(rng):
    Y = shape_set(rng, 10, 10, spread=0.1)
    settings = EvaluationSettings(models=["ppca", "gplvm"], folds=3, n_samples=10, latent_map=False)
    result = run_evaluation(Y, [f"s{i}" for i in range(10)], settings)
    models = result.report["models"]
    assert list(models) == ["ppca", "gplvm", "training-set", "mean-shape"]
    for name in ("ppca", "gplvm", "training-set"):
        for region in settings.regions:
            assert models[name]["completion"][region]["mean_sse"] > 0
    assert all(models["mean-shape"]["completion"][r]["relative_to_mean_shape"] == pytest.approx(1.0)
               for r in settings.regions)
    assert 0 <= models["ppca"]["heldout_samples"]["coverage"]["mean"] <= 1
    assert len(models["ppca"]["all_shapes"]["novelty"]["per_sample"]) == 10


# ---------------------------------------------------------------------------- the command
@pytest.fixture(scope="module")
def tiny_collection(tmp_path_factory):
    """Eight coarse procedural vases: a folder of meshes and its correspondence .npz."""
    folder = tmp_path_factory.mktemp("vases")
    shapes = make_vases(8, seed=5, resolution=(12, 16))
    write_collection(shapes, folder / "meshes")
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=60, seed=0))
    corr = correspond(prepared, jobs=1)
    return folder / "meshes", corr.save(folder / "corr.npz")


def run_cli(*args):
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.run([str(SHAPEGEN), "evaluate", *map(str, args)], capture_output=True, text=True, env=env,
                          timeout=300)


def test_report_is_byte_for_byte_reproducible(tiny_collection, tmp_path):
    _, corr = tiny_collection
    outputs = [tmp_path / "a", tmp_path / "b"]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    runs = [subprocess.Popen([str(SHAPEGEN), "evaluate", str(corr), "--folds", "2", "--samples", "20", "--seed", "3",
                              "-o", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            for out in outputs]                  # both at once: two cores, half the wait
    for run in runs:
        _, stderr = run.communicate(timeout=300)
        assert run.returncode == 0, stderr
    files = sorted(p.name for p in outputs[0].iterdir())
    assert files == sorted(p.name for p in outputs[1].iterdir())
    assert {"report.json", "summary.md", "samples.png", "nearest.png", "completion_top.png",
            "ppca_curves.png", "latent_map.png", "morph.png"} <= set(files)
    for name in files:
        assert (outputs[0] / name).read_bytes() == (outputs[1] / name).read_bytes(), name
    report = json.loads((outputs[0] / "report.json").read_text())
    assert report["settings"]["seed"] == 3
    assert set(report["models"]) == {"ppca", "gplvm", "bgplvm", "training-set", "mean-shape"}
    assert "| BGP-LVM |" in (outputs[0] / "summary.md").read_text()


def test_cli_from_a_folder_and_its_errors(tiny_collection, tmp_path):
    folder, corr = tiny_collection
    result = run_cli(folder, "--models", "ppca", "--folds", 2, "--landmarks", 60, "--jobs", 1,
                     "--no-figures", "-o", tmp_path / "r")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["report.json", "summary.md"]

    # the refusals, before any work: through `main` in this process
    bad = in_process("evaluate", corr, "--folds", 20, "-o", tmp_path / "x")
    assert bad.returncode == 2
    assert "--folds 20 is more than the 8 shapes" in bad.stderr
    bad = in_process("evaluate", folder, "--models", "ppca,vae", "-o", tmp_path / "x")
    assert bad.returncode == 2
    assert "unknown model name(s) 'vae'" in bad.stderr
    bad = in_process("evaluate", tmp_path / "missing.npz", "-o", tmp_path / "x")
    assert bad.returncode == 2 and "no such folder or correspondence file" in bad.stderr
    assert not (tmp_path / "x").exists()
