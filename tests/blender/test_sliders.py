"""Explore's sliders and Randomise stay within the training shapes' range, and a collection of
20 shapes gets a small automatic latent dimension."""

from __future__ import annotations

import bpy
import numpy as np
import pytest
from conftest import addon_module, fit_vase_models, load_model

MODEL_TYPES = ("ppca", "gplvm", "bgplvm")


@pytest.mark.parametrize("kind", MODEL_TYPES)
def test_randomise_stays_within_three_training_standard_deviations(extension, model_files, kind):
    load_model(kind, model_files)
    scene = bpy.context.scene
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    latent = addon_module(extension, "shapegen_addon.latent")
    model = addon_module(extension, "shapegen_addon.store").get_model(scene)
    soft = type(scene.shapegen.latents[0]).bl_rna.properties["value"]
    units = latent.slider_units(scene)
    training = units.to_values(model.training_latents())
    assert np.abs(training).max() <= 3.0 + 1e-6                # the range covers every training shape
    assert soft.soft_min <= -3.0 and soft.soft_max >= 3.0
    for _ in range(25):
        assert bpy.ops.shapegen.explore_randomise() == {"FINISHED"}
        values = np.array([item.value for item in scene.shapegen.latents])
        assert np.abs(values).max() <= 3.0 + 1e-6
        assert np.all((values >= soft.soft_min) & (values <= soft.soft_max))
        z = latent.current_latent(scene)
        np.testing.assert_allclose(units.to_values(z), values, atol=1e-5)


@pytest.fixture(scope="module")
def twenty_vase_models(extension):
    """PPCA and Bayesian GP-LVM on one correspondence of 20 vases, latent_dim automatic."""
    return fit_vase_models(extension, ("ppca", "bgplvm"), n=20, latent_dim=None)


@pytest.mark.parametrize("kind", ["ppca", "bgplvm"])
def test_the_automatic_latent_dimension_of_twenty_shapes_gives_few_sliders(extension, twenty_vase_models, tmp_path, kind):
    base = addon_module(extension, "core.models.base")
    path = twenty_vase_models[kind].save(tmp_path / f"vases20_{kind}.npz")
    assert bpy.ops.shapegen.load_model(filepath=str(path)) == {"FINISHED"}
    model = addon_module(extension, "shapegen_addon.store").get_model(bpy.context.scene)
    Y = model.training_matrix()
    assert model.latent_dim == base.default_latent_dim(Y - Y.mean(0)) <= 8
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    assert len(bpy.context.scene.shapegen.latents) == model.latent_dim
