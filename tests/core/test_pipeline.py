"""The fitted whole: fit → save → load → sample / complete / mesh."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PrepareSettings
from shapegen_core.demo_data import make_vases
from shapegen_core.base.errors import ModelFileError, ShapeGenError
from shapegen_core.models import PPCA
from shapegen_core.base.npzfile import save_npz
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.app.pipeline import fit_meshes


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    shapes = make_vases(6, seed=2, resolution=(14, 18))
    model = fit_meshes([s.mesh for s in shapes], FitSettings(prepare=PrepareSettings(n_landmarks=80), model="ppca"), jobs=1)
    path = tmp_path_factory.mktemp("model") / "model.npz"
    model.save(path)
    return model, path


def test_round_trip_reproduces_samples_and_meshes(fitted):
    model, path = fitted
    loaded = GenerativeShapeModel.load(path)
    assert loaded.names == model.names and loaded.model_type == "ppca"
    a, za = model.sample(3, np.random.default_rng(4))
    b, zb = loaded.sample(3, np.random.default_rng(4))
    np.testing.assert_allclose(a, b, atol=1e-12)
    np.testing.assert_allclose(za, zb)
    np.testing.assert_allclose(model.mesh_from_landmarks(a[0]).vertices,
                               loaded.mesh_from_landmarks(b[0]).vertices, atol=1e-9)


def test_sampling_follows_the_models_noise_setting(fitted, tmp_path):
    """PPCA(sample_noise=True) adds its isotropic noise in the fitted whole too (the pipeline
    used to decode the sampled latents itself, dropping the noise); the default stays noise-free."""
    model, _ = fitted
    arrays = model.model.to_arrays()
    arrays["param_sample_noise"] = np.array(1)
    noisy = GenerativeShapeModel(model.meshes, model.correspondence, PPCA.from_arrays(arrays),
                                 settings=model.settings)
    landmarks, latents = noisy.sample(3, np.random.default_rng(4))
    expected = noisy.model.sample(3, np.random.default_rng(4)).reshape(landmarks.shape)
    np.testing.assert_array_equal(landmarks, expected)
    smooth, smooth_latents = model.sample(3, np.random.default_rng(4))
    np.testing.assert_array_equal(latents, smooth_latents)
    np.testing.assert_array_equal(smooth.reshape(3, -1), model.model.decode(smooth_latents))
    assert np.abs(landmarks - smooth).max() > 0.1 * np.sqrt(noisy.model.noise_variance_)
    noisy.save(tmp_path / "noisy.npz")
    again, _ = GenerativeShapeModel.load(tmp_path / "noisy.npz").sample(3, np.random.default_rng(4))
    np.testing.assert_array_equal(again, landmarks)


def test_a_training_shape_meshes_to_its_own_mesh(fitted):
    model, _ = fitted
    for index in (0, 3):
        name = model.names[index]
        mesh = model.mesh_from_landmarks(model.correspondence.points[index], template=name)
        np.testing.assert_allclose(mesh.vertices, model.meshes[index].vertices, atol=1e-9)
        assert model.choose_template(model.correspondence.points[index], "nearest-data") == index


def test_completion_keeps_observed_landmarks(fitted):
    model, _ = fitted
    partial = model.correspondence.points[:2].copy()
    top = partial[..., 2] > np.median(partial[..., 2])
    partial[top] = np.nan
    done = model.complete(partial)
    assert np.isfinite(done).all()
    np.testing.assert_allclose(done[~top], model.correspondence.points[:2][~top])


def test_bad_template_and_bad_landmarks_are_clear_errors(fitted):
    model, _ = fitted
    with pytest.raises(ShapeGenError, match="no training shape named 'nope'"):
        model.mesh_from_landmarks(model.correspondence.points[0], template="nope")
    with pytest.raises(ShapeGenError, match="landmarks"):
        model.mesh_from_landmarks(model.correspondence.points[0][:-3])


def test_foreign_and_truncated_model_files_are_refused(fitted, tmp_path):
    _, path = fitted
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[: 2000])
    with pytest.raises(ModelFileError, match="truncated.npz"):
        GenerativeShapeModel.load(truncated)
    foreign = tmp_path / "foreign.npz"
    save_npz(foreign, "shapegen.prepared", 1, {"a": np.zeros(3)})
    with pytest.raises(ModelFileError, match="expected 'shapegen.model'"):
        GenerativeShapeModel.load(foreign)
    plain = tmp_path / "plain.npz"
    np.savez(plain, x=np.zeros(3))
    with pytest.raises(ModelFileError, match="no format tag"):
        GenerativeShapeModel.load(plain)


def test_fit_progress_runs_through_its_stages_forward_and_cancel_stops_any_of_them():
    """One progress over the whole fit: prepare 0–0.15, correspondence 0.15–0.75, model
    0.75–1, never decreasing, ending at 1.0; a cancel (here an Event) stops it in any stage."""
    import threading

    from shapegen_core.base.errors import Cancelled

    meshes = [s.mesh for s in make_vases(4, seed=5, resolution=(12, 16))]
    settings = FitSettings(prepare=PrepareSettings(n_landmarks=60), model="ppca")
    events = []
    fit_meshes(meshes, settings, progress=lambda f, m: events.append((f, m)), jobs=1)
    fractions = [f for f, _ in events]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and events[-1][1] == "fitted"
    stages = [m.split(":")[0] for _, m in events]
    assert stages.index("prepare") < stages.index("correspondence") < stages.index("ppca")
    assert all(f <= 0.15 for f, m in events if m.startswith("prepare: "))
    assert all(0.15 <= f <= 0.75 for f, m in events if m.startswith("correspondence: "))
    assert any(m.startswith(f"correspondence: registering {meshes[0].name} (round 1 of 2") for _, m in events)
    for stage in ("prepare: ", "correspondence: registering", "ppca: "):
        stop, seen = threading.Event(), []

        def progress(fraction, message, stage=stage):
            seen.append(message)
            if message.startswith(stage):
                stop.set()

        with pytest.raises(Cancelled):
            fit_meshes(meshes, settings, progress=progress, should_cancel=stop, jobs=1)
        assert seen[-1].startswith(stage)  # stopped at the next check, before another report


def test_the_model_file_holds_the_training_latents_and_slider_units(fitted, tmp_path, monkeypatch):
    """Encoded once where the model is fitted and saved: loading never encodes; a file
    written before these arrays existed still loads, and computes them on load."""
    from shapegen_core.base.npzfile import load_npz
    from shapegen_core.app.shape_model import MODEL_FILE_FORMAT, MODEL_FILE_VERSION

    model, path = fitted
    expected = model.model.encode(model.training_matrix())
    np.testing.assert_allclose(model.training_latents(), expected)
    with monkeypatch.context() as patch:
        patch.setattr(PPCA, "encode", lambda *_: pytest.fail("a model file's load encoded the training shapes"))
        loaded = GenerativeShapeModel.load(path)
        np.testing.assert_array_equal(loaded.training_latents(), model.training_latents())
        np.testing.assert_array_equal(loaded.latent_units().scale, model.latent_units().scale)
        np.testing.assert_array_equal(loaded.latent_units().centre, model.latent_units().centre)

    arrays = load_npz(path, MODEL_FILE_FORMAT, MODEL_FILE_VERSION, {})
    older = tmp_path / "older.npz"
    save_npz(older, MODEL_FILE_FORMAT, MODEL_FILE_VERSION,
             {k: v for k, v in arrays.items() if k not in ("training_latents", "latent_centre", "latent_scale")})
    loaded = GenerativeShapeModel.load(older)
    np.testing.assert_allclose(loaded.training_latents(), expected)
    np.testing.assert_allclose(loaded.latent_units().scale, model.latent_units().scale)

    wrong = tmp_path / "wrong.npz"
    save_npz(wrong, MODEL_FILE_FORMAT, MODEL_FILE_VERSION, {**arrays, "training_latents": expected[:-1]})
    with pytest.raises(ModelFileError, match="training_latents"):
        GenerativeShapeModel.load(wrong)
