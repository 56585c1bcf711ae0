"""Gated sampling: a sample whose mesh fails the quality gate is re-meshed on the
next-nearest template or redrawn within the run's pooled draw budget, every refused mesh
is recorded with its seed, template and reasons, and a sample still failing when the
budget is spent is returned failing, never as a good one."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.generate import sampling
from shapegen_core.preprocess.collection import PrepareSettings
from shapegen_core.demo_data import make_vases
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.pipeline import fit_meshes
from shapegen_core.generate.quality import MeshQuality, QualitySettings
from shapegen_core.generate.sampling import (TEMPLATES_TRIED, GatedSample, draw_budget, failed_reasons, gate_summary,
                                             gated_sample, gated_samples, pooled_samples, redraw_seed, shortfall)


@pytest.fixture(scope="module")
def model():
    meshes = [s.mesh for s in make_vases(6, seed=5, resolution=(14, 18))]
    return fit_meshes(meshes, FitSettings(prepare=PrepareSettings(n_landmarks=60), model="ppca"), jobs=1)


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


def test_when_every_draw_fails_the_last_mesh_is_returned_failing_with_its_reasons(model):
    strict = QualitySettings(max_edge_stretch_p99=1e-9, max_redraws=1)
    sample = gated_sample(model, 0, 0, 3, settings=strict)
    assert not sample.quality.ok and sample.quality.reasons[0].startswith("edge stretch:")
    assert len(sample.rejected) == 2 * 2 * min(TEMPLATES_TRIED, len(model.template_candidates()))
    assert {r.seed for r in sample.rejected} == {0, 3} and sample.seed == 3 and sample.draws == 2
    assert "1 still fail after 2 draws in all (sample: edge stretch:" in gate_summary([sample])


def _stub(index, draw, passes):
    """A GatedSample of draw `draw` of sample `index` (run of 10 from seed 0): passing or
    failing on flipped faces, with the refused meshes of this draw's failures."""
    quality = MeshQuality(0, 0.0, 0.1, 0.05, 0, 1.0, 1.0, () if passes else ("flipped: 3 face(s)",))
    return GatedSample(index, sampling.sample_name(index), redraw_seed(0, 10, index, draw), np.zeros((2, 3)),
                       np.zeros(1), 0, None, quality, 1.0)


def pooled(count, budget, passes):
    """`pooled_samples` with a gate passing draw d of sample i when passes(i, d); returns
    the samples and each round's slots as (index, first draw, draws) triples."""
    rounds = []

    def gate(slots):
        rounds.append([(i, draws.start, len(draws)) for i, draws in slots])
        out = []
        for index, draws in slots:
            refused = []
            for draw in draws:
                sample = _stub(index, draw, passes(index, draw))
                sample.rejected = list(refused)
                if sample.quality.ok:
                    break
                refused.append(sampling.Rejection(sample.seed, "t", sample.quality.reasons, 1.0))
            sample.rejected = refused
            out.append(sample)
        return out[::-1]  # a pool may return them in any order

    return pooled_samples(count, budget, gate), rounds


def test_the_draw_budget_is_pooled_over_the_run():
    """Sample 1 fails its own 1 + max_redraws draws; the draws samples 0 and 2 left unused
    go to it, and it passes on its 4th draw."""
    assert draw_budget(3, QualitySettings(max_redraws=1)) == 6 and draw_budget(8) == 8 * 21
    samples, rounds = pooled(3, 6, lambda i, d: i != 1 or d == 3)
    assert rounds == [[(0, 0, 2), (1, 0, 2), (2, 0, 2)], [(1, 2, 2)]]
    assert all(s.quality.ok for s in samples) and [s.index for s in samples] == [0, 1, 2]
    assert samples[1].seed == redraw_seed(0, 10, 1, 3) and samples[1].draws == 4
    assert [r.seed for r in samples[1].rejected] == [redraw_seed(0, 10, 1, d) for d in range(3)]  # every round's
    assert sum(s.draws for s in samples) == 6
    assert shortfall(samples, 6) == ""


def test_a_run_stops_when_its_budget_is_spent_and_says_how_many_passed_and_why():
    samples, rounds = pooled(4, 8, lambda i, d: i % 2 == 0)
    assert rounds == [[(i, 0, 2) for i in range(4)], [(1, 2, 1), (3, 2, 1)]]  # 2 draws left: one each
    assert [s.quality.ok for s in samples] == [True, False, True, False]
    assert [s.draws for s in samples] == [1, 3, 1, 3]
    assert shortfall(samples, 8) == ("2 of 4 samples passed the quality gate within the budget of 8 draws; 2 still "
                                     "fail (commonest reasons over their 6 refused meshes: flipped 6)")
    assert "2 still fail after 8 draws in all (sample_0001: flipped: 3 face(s), sample_0003: " in gate_summary(samples)


def test_draws_too_few_for_every_failing_sample_go_to_the_lowest_index_first():
    samples, rounds = pooled(3, 4, lambda i, d: False)
    assert rounds == [[(0, 0, 1), (1, 0, 1), (2, 0, 1)], [(0, 1, 1)]]
    assert [s.draws for s in samples] == [2, 1, 1] and not any(s.quality.ok for s in samples)


def test_a_model_whose_draws_all_fail_spends_the_budget_and_returns_them_failing(model):
    strict = QualitySettings(max_edge_stretch_p99=1e-9, max_redraws=0, stiffer_remesh=1.0)
    samples = gated_samples(model, 2, 0, settings=strict)
    assert [s.seed for s in samples] == [0, 1] and not any(s.quality.ok for s in samples)
    assert sum(s.draws for s in samples) == draw_budget(2, strict) == 2
    assert failed_reasons(samples)["edge stretch"] == sum(len(s.rejected) for s in samples) > 0
    assert shortfall(samples, 2).startswith("0 of 2 samples passed the quality gate within the budget of 2 draws")
