"""Latent vectors in training standard deviations and random draws within ±3."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.base.errors import ShapeGenError
from shapegen_core.models.latent_units import SLIDER_LIMIT, LatentUnits
from shapegen_core.models import make_model


def test_units_are_training_standard_deviations_and_cover_every_training_latent():
    rng = np.random.default_rng(0)
    latents = rng.standard_normal((20, 3)) * [2.0, 0.1, 1.0] + [1.0, -3.0, 0.0]
    latents[7, 2] = 9.0                      # one outlier, > 3 sd in dimension 3
    latents[:, 1] -= latents[:, 1].mean()
    units = LatentUnits.from_training(latents)
    np.testing.assert_allclose(units.centre, latents.mean(0))
    np.testing.assert_allclose(units.scale[:2], latents[:, :2].std(0))
    values = units.to_values(latents)
    assert np.abs(values).max() <= SLIDER_LIMIT + 1e-12
    assert np.abs(values[:, 2]).max() == pytest.approx(SLIDER_LIMIT)   # widened to reach the outlier
    np.testing.assert_allclose(units.to_latent(values), latents)
    assert LatentUnits.from_training(np.ones((5, 2))).scale.tolist() == [1.0, 1.0]


def test_random_draws_come_from_the_density_within_the_limit():
    units = LatentUnits(np.zeros(4), np.full(4, 0.5))   # the density is twice as wide as the units

    def sample_latents(n, rng):
        return rng.standard_normal((n, 4))

    draws = [units.random(sample_latents, np.random.default_rng(seed)) for seed in range(200)]
    values = np.array([d.values for d in draws])
    assert np.abs(values).max() <= SLIDER_LIMIT and not any(d.clipped for d in draws)
    assert sum(d.redraws for d in draws) > 0                         # |2 N(0, 1)| > 3 happens
    # the truncated density: the first draw within ±3 of the model's own stream
    first = draws[0]
    stream = sample_latents(first.redraws + 1, np.random.default_rng(0)) / 0.5
    np.testing.assert_allclose(first.values, stream[first.redraws])
    assert np.all(np.abs(stream[: first.redraws]).max(axis=1) > SLIDER_LIMIT)
    again = units.random(sample_latents, np.random.default_rng(0))
    np.testing.assert_array_equal(again.values, first.values)


def test_random_clips_when_no_draw_falls_within_the_limit():
    units = LatentUnits(np.zeros(2), np.ones(2))
    drawn = units.random(lambda n, rng: np.full((n, 2), [10.0, -0.5]), np.random.default_rng(0), max_draws=120)
    assert drawn.clipped and drawn.redraws == 119
    np.testing.assert_array_equal(drawn.values, [SLIDER_LIMIT, -0.5])
    with pytest.raises(ShapeGenError, match="at least 1"):
        units.random(lambda n, rng: np.zeros((n, 2)), np.random.default_rng(0), max_draws=0)


@pytest.mark.parametrize("name", ["ppca", "gplvm", "bgplvm"])
def test_every_models_random_latents_stay_within_its_training_range(name):
    rng = np.random.default_rng(3)
    Y = rng.standard_normal((12, 2)) @ rng.standard_normal((2, 30)) + 0.05 * rng.standard_normal((12, 30))
    options = {} if name == "ppca" else {"max_iter": 30}
    model = make_model(name, **options).fit(Y)
    units = LatentUnits.from_training(model.encode(Y))
    for seed in range(20):
        drawn = units.random(model.sample_latents, np.random.default_rng(seed))
        assert drawn.values.shape == (model.latent_dim,)
        assert np.abs(drawn.values).max() <= SLIDER_LIMIT
