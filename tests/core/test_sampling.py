"""Gated sampling (issue 14): a sample whose mesh fails the quality gate is re-meshed on the
next-nearest template or redrawn, and every refused mesh is recorded with its seed,
template and reasons."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core import sampling
from shapegen_core.collection import PrepareSettings
from shapegen_core.datasets import make_vases
from shapegen_core.pipeline import FitSettings, fit_meshes
from shapegen_core.quality import MeshQuality, QualitySettings
from shapegen_core.sampling import TEMPLATES_TRIED, gate_summary, gated_sample, gated_samples, redraw_seed


@pytest.fixture(scope="module")
def model():
    meshes = [s.mesh for s in make_vases(6, seed=5, resolution=(14, 18))]
    return fit_meshes(meshes, FitSettings(prepare=PrepareSettings(n_landmarks=60), model="ppca", jobs=1))


class FailingGate:
    """Fails the first `failures` checks with a flipped-faces reason, then passes."""

    def __init__(self, failures: int):
        self.failures = failures
        self.checked = []

    def check(self, mesh, template_index):
        self.checked.append(int(template_index))
        reasons = ("flipped: 3 face(s) turned against the template's (0.100 %)",) if self.failures > 0 else ()
        self.failures -= 1
        return MeshQuality(3 if reasons else 0, 0.001, 0.1, 0.05, 0, 1.0, 1.0, reasons)


def test_samples_pass_and_are_reproducible_one_by_one(model):
    samples = gated_samples(model, 4, 7)
    assert [s.seed for s in samples] == [7, 8, 9, 10]
    assert all(s.quality.ok and not s.rejected and s.redraws == 0 for s in samples), gate_summary(samples)
    alone = gated_sample(model, 2, 7, 4)
    np.testing.assert_array_equal(alone.landmarks, samples[2].landmarks)
    np.testing.assert_array_equal(alone.mesh.vertices, samples[2].mesh.vertices)
    assert gate_summary(samples) == "quality gate: all 4 passed at the first draw"


def test_a_failing_mesh_is_meshed_on_the_next_template_first(model, monkeypatch):
    gate = FailingGate(1)
    monkeypatch.setattr(sampling, "quality_gate", lambda model, settings: gate)
    sample = gated_sample(model, 1, 20, 5)
    order = model.template_order(sample.landmarks, None)
    assert gate.checked == [order[0], order[1]]
    assert sample.seed == 21 and sample.redraws == 0 and sample.template_index == order[1]
    assert [(r.seed, r.template) for r in sample.rejected] == [(21, model.names[order[0]])]
    assert sample.rejected[0].reasons[0].startswith("flipped:")


def test_a_draw_failing_on_every_template_is_meshed_stiffer_then_redrawn(model, monkeypatch):
    alpha = model.deform_settings.final_alpha
    gate = FailingGate(TEMPLATES_TRIED)
    monkeypatch.setattr(sampling, "quality_gate", lambda model, settings: gate)
    sample = gated_sample(model, 1, 20, 5)
    order = model.template_order(sample.landmarks, None)[:TEMPLATES_TRIED]
    assert gate.checked == [*order, order[0]]
    assert sample.seed == 21 and sample.redraws == 0 and sample.stiffer and sample.stiffness == 2 * alpha
    stiff = model.mesh_from_landmarks(sample.landmarks, template=model.names[order[0]], stiffness=2 * alpha)
    np.testing.assert_allclose(sample.mesh.vertices, stiff.vertices)
    assert "0 passed on another template, 1 meshed stiffer, 0 redrawn" in gate_summary([sample])

    gate = FailingGate(2 * TEMPLATES_TRIED)
    monkeypatch.setattr(sampling, "quality_gate", lambda model, settings: gate)
    sample = gated_sample(model, 1, 20, 5)
    assert sample.seed == redraw_seed(20, 5, 1, 1) == 26
    assert sample.redraws == 1 and sample.quality.ok and not sample.stiffer
    assert [r.seed for r in sample.rejected] == [21] * (2 * TEMPLATES_TRIED)
    assert [r.stiffer for r in sample.rejected] == [False] * TEMPLATES_TRIED + [True] * TEMPLATES_TRIED
    assert sample.rejected[-1].describe().startswith(f"seed 21 on {sample.rejected[-1].template} "
                                                     f"(stiffness {2 * alpha:g}): flipped:")
    assert "1 of 1 first meshes failed (flipped 6); 0 passed on another template, 0 meshed stiffer, 1 redrawn" \
        in gate_summary([sample])
    gate = FailingGate(TEMPLATES_TRIED)
    monkeypatch.setattr(sampling, "quality_gate", lambda model, settings: gate)
    assert gated_sample(model, 1, 20, 5, settings=QualitySettings(stiffer_remesh=1.0)).redraws == 1


def test_a_named_template_is_kept_and_the_sample_redrawn(model, monkeypatch):
    gate = FailingGate(1)
    monkeypatch.setattr(sampling, "quality_gate", lambda model, settings: gate)
    name = model.names[2]
    sample = gated_sample(model, 0, 3, 2, template=name, settings=QualitySettings(stiffer_remesh=1.0))
    assert gate.checked == [2, 2]
    assert [(r.seed, r.template) for r in sample.rejected] == [(3, name)]
    assert sample.seed == 5 and sample.template_index == 2


def test_when_every_redraw_fails_the_last_is_kept_and_reported(model):
    strict = QualitySettings(max_edge_stretch_p99=1e-9, max_redraws=1)
    sample = gated_sample(model, 0, 0, 3, settings=strict)
    assert not sample.quality.ok and sample.quality.reasons[0].startswith("edge stretch:")
    assert len(sample.rejected) == 2 * 2 * min(TEMPLATES_TRIED, len(model.template_candidates()))
    assert {r.seed for r in sample.rejected} == {0, 3} and sample.seed == 3
    assert "1 still fail after every redraw (kept: sample: edge stretch:" in gate_summary([sample])
