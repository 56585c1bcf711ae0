"""The most probable shape given pinned coordinates (`ShapeModel.posterior`, thesis §5.5.3
made soft) and its uncertainty: PPCA against the Gaussian conditional computed directly,
the GP-LVMs' pin objective against finite differences, far pins, and the fitted whole's
`complete_from_pins` / `vertex_std`."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PrepareSettings
from shapegen_core.demo_data import make_vases
from shapegen_core.base.errors import ShapeGenError
from shapegen_core.models import GPLVM, PPCA, BayesianGPLVM
from shapegen_core.models.latent_variable import LatentVariableModel
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.pipeline import fit_meshes

from conftest import central_diff


def curve_rows(rng, n, d=12, noise=0.02):
    """Rows from a 1-D latent through smooth sines, plus noise."""
    freq, phase = rng.uniform(0.5, 1.5, d), rng.uniform(0, 2 * np.pi, d)
    t = rng.uniform(-2, 2, n)
    return np.sin(t[:, None] * freq + phase) + noise * rng.standard_normal((n, d))


@pytest.fixture(scope="module")
def models():
    Y = curve_rows(np.random.default_rng(0), 25)
    return {"ppca": PPCA().fit(Y),
            "gplvm": GPLVM(n_components=2, max_iter=300).fit(Y),
            "bgplvm": BayesianGPLVM(n_components=2, n_inducing=8, max_iter=300, random_state=1).fit(Y)}, Y


# ----------------------------------------------------------------------------- PPCA: closed form

def test_ppca_posterior_is_the_gaussian_conditional_computed_directly():
    """A small Gaussian (D = 9, q = 2): E[f | y_o] and Cov[f | y_o] of f = mu + W z from the
    joint covariance, with dense matrices and no Woodbury; the hidden coordinates' mean is
    also the conditional mean of y_m given y_o."""
    rng = np.random.default_rng(3)
    W0, mu0 = rng.standard_normal((9, 2)), rng.standard_normal(9)
    Y = mu0 + rng.standard_normal((40, 2)) @ W0.T + 0.1 * rng.standard_normal((40, 9))
    model = PPCA(n_components=2, shrinkage=0.0).fit(Y)
    W, mu, s2 = model.components_, model.mean_, model.noise_variance_
    observed = np.zeros(9, bool)
    observed[[1, 4, 5, 7]] = True
    y = rng.standard_normal(9) * 2
    found = model.posterior(y, observed)

    C = W @ W.T + s2 * np.eye(9)
    C_oo = C[np.ix_(observed, observed)]
    cross = (W @ W.T)[:, observed]                                      # Cov(f, y_o)
    mean = mu + cross @ np.linalg.solve(C_oo, y[observed] - mu[observed])
    cov = W @ W.T - cross @ np.linalg.solve(C_oo, cross.T)
    np.testing.assert_allclose(found.mean, mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(found.variance, np.diag(cov), rtol=1e-9, atol=1e-12)
    hidden = ~observed
    y_m = mu[hidden] + C[np.ix_(hidden, observed)] @ np.linalg.solve(C_oo, y[observed] - mu[observed])
    np.testing.assert_allclose(found.mean[hidden], y_m, rtol=1e-10)
    # soft: the shape does not pass through the observations exactly
    assert np.abs(found.mean[observed] - y[observed]).max() > 1e-6
    np.testing.assert_allclose(found.mean, model.decode(found.latent)[0], atol=1e-12)


def test_ppca_std_shrinks_where_observed_and_never_grows_with_more_pins(models):
    model = models[0]["ppca"]
    prior = np.sum(model.components_**2, 1)
    few = np.zeros(model.n_features_, bool)
    few[[0, 5]] = True
    more = few.copy()
    more[[2, 9]] = True
    y = model.mean_ + 0.3
    a, b = model.posterior(y, few), model.posterior(y, more)
    assert np.all(a.variance <= prior + 1e-12)
    assert np.all(b.variance <= a.variance + 1e-12)
    # observed coordinates lose more of their prior variance than the others on average
    assert (a.variance[few] / prior[few]).mean() < (a.variance[~few] / prior[~few]).mean()


# ----------------------------------------------------------------------------- GP-LVMs

@pytest.mark.parametrize("kind", ["gplvm", "bgplvm"])
def test_pin_objective_gradient_matches_finite_differences(models, kind):
    model, Y = models[0][kind], models[1]
    observed = np.zeros(Y.shape[1], bool)
    observed[[0, 3, 4, 8]] = True
    c, R, _, _ = LatentVariableModel._row_setup(model.decode_basis()[:, observed], (Y[2] - model.mean_)[observed])
    for z in (np.array([0.3, -0.2]), np.array([-1.1, 0.7])):
        value, grad = model.pin_objective(z, c, R)
        numeric = central_diff(lambda x: model.pin_objective(x, c, R)[0], z)
        assert np.linalg.norm(grad - numeric) <= 1e-7 * np.linalg.norm(numeric)
        # and the objective is what it says: beta/2 |y_o - m_o(z)|^2 + |z|^2/2 up to a constant
        residual = Y[2][observed] - model.decode(z)[0][observed]
        other = np.array([0.0, 0.1])
        residual0 = Y[2][observed] - model.decode(other)[0][observed]
        expected = (0.5 / model.noise_variance_ * (residual @ residual - residual0 @ residual0)
                    + 0.5 * (z @ z - other @ other))
        assert value - model.pin_objective(other, c, R)[0] == pytest.approx(expected, rel=1e-8, abs=1e-8)


@pytest.mark.parametrize("kind", ["ppca", "gplvm", "bgplvm"])
def test_pinning_every_coordinate_of_a_training_row_gives_that_row(models, kind):
    model, Y = models[0][kind], models[1]
    row = Y[4]
    found = model.posterior(row, np.ones(row.size, bool))
    reconstruction = model.decode(model.encode(row[None]))[0]
    assert np.sqrt(np.mean((found.mean - row) ** 2)) <= 1.5 * np.sqrt(np.mean((reconstruction - row) ** 2)) + 1e-3


@pytest.mark.parametrize("kind", ["gplvm", "bgplvm"])
def test_gp_std_is_smaller_where_pinned(models, kind):
    model, Y = models[0][kind], models[1]
    observed = np.zeros(Y.shape[1], bool)
    observed[[1, 6]] = True
    found = model.posterior(Y[7], observed)
    assert np.all(np.isfinite(found.variance)) and np.all(found.variance >= 0)
    assert found.variance[observed].mean() < found.variance[~observed].mean()


@pytest.mark.parametrize("kind", ["gplvm", "bgplvm"])
def test_a_search_from_a_given_latent_stays_near_it_when_it_explains_the_pins(models, kind):
    """The live path: pins where the shape at z already is keep z (a dragged pin moves the
    shape continuously, it does not jump to another training shape)."""
    model = models[0][kind]
    z = model.encode(models[1][10:11])[0]
    shape = model.decode(z)[0]
    observed = np.zeros(shape.size, bool)
    observed[[0, 2, 7]] = True
    found = model.posterior(shape, observed, start=z)
    assert np.linalg.norm(found.latent - z) < 0.3 * max(np.linalg.norm(z), 1.0)


@pytest.mark.parametrize("kind", ["ppca", "gplvm", "bgplvm"])
def test_a_pin_far_outside_the_class_is_followed_as_far_as_the_model_allows(models, kind):
    model, Y = models[0][kind], models[1]
    observed = np.zeros(Y.shape[1], bool)
    observed[3] = True
    spread = np.ptp(Y, axis=0).max()
    y = model.mean_.copy()
    y[3] += 1000 * spread
    found = model.posterior(y, observed)
    assert np.all(np.isfinite(found.mean)) and np.all(np.isfinite(found.variance))
    moved = found.mean[3] - model.mean_[3]
    assert 0 < moved < 1000 * spread                                    # towards the pin, not onto it
    if kind != "ppca":  # the GP mean is bounded: never beyond the training shapes by much
        assert np.all(np.abs(found.mean - model.mean_) <= 3 * spread)


# ----------------------------------------------------------------------------- the fitted whole

@pytest.fixture(scope="module")
def vase_model():
    shapes = make_vases(6, seed=2, resolution=(14, 18))
    return fit_meshes([s.mesh for s in shapes],
                      FitSettings(prepare=PrepareSettings(n_landmarks=60), model="ppca"), jobs=1)


def test_pins_at_a_training_shape_give_that_shape_within_its_reconstruction_error(vase_model):
    model = vase_model
    target = model.correspondence.points[2]
    pins = {i: target[i] for i in range(0, model.n_landmarks, 3)}
    done = model.complete_from_pins(pins)
    reconstruction = model.decode(model.encode(target[None]))[0]
    error = np.sqrt(np.mean(np.sum((done.landmarks - target) ** 2, 1)))
    assert error <= 1.5 * np.sqrt(np.mean(np.sum((reconstruction - target) ** 2, 1))) + 1e-6
    assert set(done.distances(pins)) == set(pins)
    assert done.std.shape == (model.n_landmarks,) and np.all(done.std >= 0)


def test_vertex_std_follows_the_meshing_weights(vase_model):
    model = vase_model
    index = model.mean_template()
    n_vertices = model.meshes[index].n_vertices
    np.testing.assert_allclose(model.vertex_std(np.full(model.n_landmarks, 0.25), index),
                               np.full(n_vertices, 0.25), atol=1e-8)
    done = model.complete_from_pins({0: model.correspondence.points[0][0] + [0, 0, 0.05]})
    std = model.vertex_std(done.std, index)
    assert std.shape == (n_vertices,) and np.all(std >= 0)
    # vertices near the pinned landmark are surer than the mesh on average
    near = np.linalg.norm(model.meshes[index].vertices - model.correspondence.points[index][0], axis=1)
    assert std[np.argsort(near)[:5]].mean() < std.mean()


def test_bad_pins_are_clear_errors(vase_model):
    model = vase_model
    with pytest.raises(ShapeGenError, match="no pins"):
        model.complete_from_pins({})
    with pytest.raises(ShapeGenError, match="not a landmark index"):
        model.complete_from_pins({model.n_landmarks: [0, 0, 0]})
    with pytest.raises(ShapeGenError, match="3 finite numbers"):
        model.complete_from_pins({0: [0, np.nan, 0]})
