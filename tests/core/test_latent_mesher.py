"""LatentMesher: the live-slider path of the Blender add-on (vertices as an affine
function of the decode features) equals the core's own meshing of decode(z)."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PrepareSettings
from shapegen_core.correspond import CorrespondenceSettings
from shapegen_core.correspond.settings import IterationSettings, StiffnessSettings
from shapegen_core.demo_data import make_vases
from shapegen_core.models import MODEL_TYPES
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.app.pipeline import fit_meshes


@pytest.fixture(scope="module")
def fitted():
    shapes = make_vases(6, seed=1, resolution=(12, 16))
    settings = FitSettings(prepare=PrepareSettings(n_landmarks=80), model="ppca", latent_dim=2,
                           correspondence=CorrespondenceSettings(stiffness=StiffnessSettings(alpha_steps=2),
                                                                 iterations=IterationSettings(max_iterations=6),
                                                                 groupwise_rounds=0))
    return fit_meshes([s.mesh for s in shapes], settings, jobs=1)


@pytest.mark.parametrize("kind", ["ppca", "gplvm", "bgplvm"])
def test_latent_mesher_equals_meshing_the_decoded_landmarks(fitted, kind):
    model = fitted if kind == "ppca" else GenerativeShapeModel(
        fitted.meshes, fitted.correspondence, MODEL_TYPES[kind](n_components=2).fit(fitted.training_matrix()),
        settings=fitted.settings)
    index = model.mean_template()
    mesher = model.latent_mesher(index, dtype=np.float64)
    assert mesher.n_vertices == model.meshes[index].n_vertices and mesher.template_name == model.names[index]
    for z in (np.zeros(2), np.array([1.3, -0.7]), model.training_latents()[2]):
        expected = model.mesh_from_landmarks(model.decode(z)[0], template=model.names[index]).vertices
        np.testing.assert_allclose(mesher.vertices(z), expected, atol=1e-9 * np.ptp(expected) + 1e-12)
    single = model.latent_mesher(index)  # float32 by default, what Blender stores
    assert single.flat_vertices(np.zeros(2)).dtype == np.float32


def test_mean_template_is_the_training_shape_nearest_the_mean(fitted):
    mean = fitted.model.mean_.reshape(-1, 3)
    distances = ((fitted.correspondence.points - mean) ** 2).sum(axis=(1, 2))
    assert fitted.mean_template() == int(np.argmin(distances))
