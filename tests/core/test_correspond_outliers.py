"""Correspondence outlier flags that catch a wrong pose: a shape turned upside
down after Prepare is flagged with a reason a user understands, a clean collection flags
nobody, and no outlier is ever chosen as a template (correspondence medoid, nearest-data,
nearest-latent)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PrepareSettings, PreparedCollection, prepare_meshes
from shapegen_core.correspond import CorrespondenceSettings, correspond, flag_outliers, leave_one_out_errors
from shapegen_core.correspond.settings import OutlierSettings
from shapegen_core.correspond import groupwise
from shapegen_core.demo_data import make_vases
from shapegen_core.preprocess.landmarks import Landmarks
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.app.pipeline import fit_shape_model

UPSIDE_DOWN = np.diag([1.0, -1.0, -1.0])  # a half turn about x: +z up becomes -z up
FLIPPED = 3


def _prepared(seed: int, n: int = 10) -> PreparedCollection:
    shapes = make_vases(n, seed=seed, resolution=(14, 18))
    return prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=120, seed=seed))


def _turn_upside_down(prepared: PreparedCollection, index: int) -> PreparedCollection:
    """Shape `index` turned upside down AFTER Prepare, so consensus cannot put it right."""
    shapes, landmarks = list(prepared.shapes), list(prepared.landmarks)
    shape, points = shapes[index], landmarks[index]
    shapes[index] = replace(shape, mesh=shape.mesh.with_vertices(shape.mesh.vertices @ UPSIDE_DOWN.T))
    landmarks[index] = Landmarks(points.points @ UPSIDE_DOWN.T, points.face_index, points.barycentric, points.radius)
    return PreparedCollection(shapes, landmarks, prepared.settings)


@pytest.fixture(scope="module")
def upside_down():
    return _turn_upside_down(_prepared(0), FLIPPED)


@pytest.mark.quality
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_clean_collection_flags_nobody(seed):
    result = correspond(_prepared(seed), jobs=1)
    assert not result.outliers.any(), [r for r in result.outlier_reasons if r]


def test_a_shape_turned_upside_down_after_prepare_is_flagged_with_its_reason(upside_down):
    result = correspond(upside_down, jobs=1)
    assert result.outliers.tolist() == [i == FLIPPED for i in range(len(result))]
    reason = result.outlier_reasons[FLIPPED]
    assert "farther from the other shapes' model than the median shape (leave-one-out reconstruction" in reason
    assert result.template_name != result.names[FLIPPED]


def test_the_leave_one_out_rule_flags_on_its_own(upside_down):
    """With the residual and size rules switched off, the leave-one-out rule alone
    catches the upside-down shape (the residual rule missed such shapes on jugs)."""
    rules = OutlierSettings(residual_min_ratio=1e6, max_residual=1e6, max_scale_ratio=1e6)
    settings = CorrespondenceSettings(outliers=rules)
    result = correspond(upside_down, settings, jobs=1)
    assert result.outliers.tolist() == [i == FLIPPED for i in range(len(result))]
    assert result.outlier_reasons[FLIPPED].startswith("landmarks ")


def test_a_medoid_template_that_is_an_outlier_gives_way(upside_down, monkeypatch):
    """The first round flags the medoid template: the medoid of the shapes that fit becomes
    the template and the rounds start again; progress stays monotone and says why."""
    real = groupwise.chamfer_medoid
    monkeypatch.setattr(groupwise, "chamfer_medoid",
                        lambda sets: FLIPPED if len(sets) == len(upside_down) else real(sets))
    events = []
    # closest points named: measured against an upside-down template, every shape lies far
    # from it in space and not in its spectrum, so the automatic start would take the
    # intrinsic one, whose maps reach the template however it lies (nothing flagged)
    closest = CorrespondenceSettings.from_dict({"initialisation": "closest"})
    result = correspond(upside_down, closest, jobs=1, progress=lambda f, m: events.append((f, m)))
    assert result.template_name != result.names[FLIPPED]
    assert result.outliers[FLIPPED] and result.outliers.sum() == 1
    fractions = [f for f, _ in events]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert any(f"({result.names[FLIPPED]} is an outlier: " in m for _, m in events)
    assert events[0][1] == f"template {result.names[FLIPPED]}"


def test_a_template_given_by_name_is_kept_even_when_flagged(upside_down):
    name = upside_down.names[FLIPPED]
    # closest points named: with them the upside-down template is flagged (the automatic
    # start would take the intrinsic one, whose maps reach the template however it lies:
    # nothing flagged)
    settings = CorrespondenceSettings.from_dict({"initialisation": "closest", "groupwise_rounds": 0})
    result = correspond(upside_down, settings, template=name, jobs=1)
    assert result.template_name == name
    assert result.outliers[FLIPPED]


def test_leave_one_out_error_is_zero_inside_the_model_and_large_outside():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(50, 3))
    modes = rng.normal(size=(2, 50, 3))
    points = base + np.einsum("mk,kld->mld", rng.normal(size=(10, 2)), modes)
    np.testing.assert_allclose(leave_one_out_errors(points, 0.999), 0.0, atol=1e-9)
    points += 0.05 * rng.normal(size=points.shape)
    points[4] = points[4] @ UPSIDE_DOWN.T
    errors = leave_one_out_errors(points, 0.9)
    assert np.argmax(errors) == 4 and errors[4] > 4 * np.median(errors)
    reasons = flag_outliers(np.full(10, 0.01), np.ones(10), CorrespondenceSettings(), points)
    assert [bool(r) for r in reasons] == [i == 4 for i in range(10)]
    assert reasons[4].startswith("landmarks ") and "× farther" in reasons[4]
    assert flag_outliers(np.full(10, 0.01), np.ones(10), CorrespondenceSettings()) == [""] * 10  # no points given


def test_mesh_templates_skip_outliers(upside_down):
    """nearest-data, nearest-latent and the mean template never pick a flagged shape,
    not even for the flagged shape's own landmarks; a template given by name is used."""
    corr = correspond(upside_down, CorrespondenceSettings(groupwise_rounds=0), jobs=1)
    assert corr.outliers[FLIPPED]
    model = fit_shape_model([s.mesh for s in upside_down.shapes], corr,
                            FitSettings(prepare=upside_down.settings, model="ppca", latent_dim=2))
    own = corr.points[FLIPPED]
    assert FLIPPED not in model.template_candidates()
    assert model.choose_template(own, "nearest-data") != FLIPPED
    assert model.choose_template(own, "nearest-latent") != FLIPPED
    assert model.mean_template() != FLIPPED
    assert model.choose_template(own, corr.names[FLIPPED]) == FLIPPED
    everyone = replace(corr, outliers=np.ones(len(corr), dtype=bool))
    unflagged = GenerativeShapeModel(model.meshes, everyone, model.model, settings=model.settings)
    assert unflagged.choose_template(own, "nearest-data") == FLIPPED  # all flagged: choose among all


def test_a_pose_prepare_flagged_is_a_correspondence_outlier_and_never_the_medoid():
    """A shape Prepare could not put right (Align "none", one vase upside down) carries
    Prepare's pose flag into the correspondence's reasons and is no medoid candidate."""
    shapes = make_vases(6, seed=4, resolution=(14, 18))
    meshes = [s.mesh for s in shapes]
    meshes[FLIPPED] = meshes[FLIPPED].with_vertices(meshes[FLIPPED].vertices @ UPSIDE_DOWN.T)
    prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=120, align="none", seed=4))
    assert prepared.shapes[FLIPPED].pose_outlier
    result = correspond(prepared, jobs=1)
    for shape, outlier, reason in zip(prepared.shapes, result.outliers, result.outlier_reasons):
        if shape.pose_outlier:
            assert outlier and f"Prepare: {shape.pose_outlier}" in reason
    template = result.names.index(result.template_name)
    assert not prepared.shapes[template].pose_outlier
