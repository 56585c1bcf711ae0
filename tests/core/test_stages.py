"""`stages.plan_stages`: the one decision of which stages run and which earlier output is
reused, for the CLI's given files and Blender's found Prepare and model (every row of the
table in core/app/stages.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PreparedCollection, PrepareSettings, prepare_meshes
from shapegen_core.correspond import CorrespondenceSettings
from shapegen_core.demo_data import make_vases
from shapegen_core.app.fit_settings import RUN_OPTIONS, FitSettings
from shapegen_core.app.stages import Offered, SettingsConflict, _leaves, plan_stages, read_offered, same_shapes

ASKED = FitSettings(prepare=PrepareSettings(n_landmarks=60), template=None)
OTHER_PREPARE = PrepareSettings(n_landmarks=60, seed=4)
OTHER_CORRESPONDENCE = CorrespondenceSettings.from_dict({"max_iterations": 5})


def found_prepared(label="'vases Prepared'", settings=ASKED.prepare, current=True):
    return Offered("prepare", label, prepare=settings, current=lambda _: current)


def found_correspondence(settings=ASKED.correspondence, prepare=ASKED.prepare, template=None, current=True):
    asked = []
    offered = Offered("correspond", "the correspondence of model 'vases'", prepare=prepare, correspondence=settings,
                      template=template, current=lambda prepared: asked.append(prepared) or current)
    return offered, asked


def test_nothing_offered_runs_every_stage():
    plan = plan_stages(ASKED)
    assert plan.run == ("prepare", "correspond", "fit") and plan.reused == () and plan.settings == ASKED
    assert plan.reason == "preparing, corresponding and fitting: no earlier result to reuse"
    assert plan_stages(ASKED, last="correspond").run == ("prepare", "correspond")


def test_an_unchanged_prepare_is_reused_and_correspondence_and_fit_run():
    prepared = found_prepared()
    plan = plan_stages(ASKED, [prepared])
    assert plan.run == ("correspond", "fit") and plan.reused == (prepared,)
    assert plan.reused_labels == "'vases Prepared'" and plan.reused_stage("prepare") is prepared
    assert plan.reason.startswith("reusing 'vases Prepared': same shapes and Prepare settings")
    assert plan_stages(ASKED, [prepared], last="prepare").run == ()


def test_changed_prepare_settings_run_prepare_and_everything_after():
    checked = []
    prepared = Offered("prepare", "'vases Prepared'", prepare=OTHER_PREPARE, current=lambda p: checked.append(p))
    correspondence, _ = found_correspondence(prepare=OTHER_PREPARE)
    plan = plan_stages(ASKED, [prepared, correspondence])
    assert plan.run == ("prepare", "correspond", "fit") and plan.reused == ()
    assert plan.reason == ("preparing, corresponding and fitting: 'vases Prepared' was made with other Prepare "
                           "settings (seed 4, now 0)")
    assert checked == []  # the shapes are not compared (scene reading) when the settings already differ


def test_changed_correspondence_settings_keep_prepare_and_run_correspondence_again():
    prepared = found_prepared()
    correspondence, _ = found_correspondence(settings=OTHER_CORRESPONDENCE)
    plan = plan_stages(ASKED, [prepared, correspondence])
    assert plan.run == ("correspond", "fit") and plan.reused == (prepared,)
    assert plan.reason == ("reusing 'vases Prepared': same shapes and Prepare settings; corresponding and fitting: "
                           "the correspondence of model 'vases' was made with other correspondence settings "
                           f"(iterations.max_iterations 5, now {ASKED.correspondence.iterations.max_iterations})")
    other_template, _ = found_correspondence(template="vase_003")
    assert "made on template vase_003, now the medoid" in plan_stages(ASKED, [prepared, other_template]).reason


def test_unchanged_correspondence_on_the_reused_prepare_leaves_only_the_fit():
    prepared = found_prepared()
    correspondence, asked = found_correspondence()
    plan = plan_stages(replace(ASKED, model="ppca", latent_dim=2), [prepared, correspondence])
    assert plan.run == ("fit",) and plan.reused == (prepared, correspondence)
    assert plan.reused_labels == "'vases Prepared' and the correspondence of model 'vases'"
    assert plan.reason.endswith("same shapes, Prepare and correspondence settings; fitting only")
    assert asked == [prepared]  # its shapes are compared with the prepared collection reused under it


@pytest.mark.parametrize("stale", ["prepare", "correspond"])
def test_changed_files_are_not_reused(stale):
    prepared = found_prepared(current=stale != "prepare")
    correspondence, _ = found_correspondence(current=stale != "correspond")
    plan = plan_stages(ASKED, [prepared, correspondence])
    if stale == "prepare":  # a stale Prepare: nothing after it counts either
        assert plan.run == ("prepare", "correspond", "fit") and plan.reused == ()
        assert plan.reason.endswith("'vases Prepared' is out of date: its shapes changed since")
    else:
        assert plan.run == ("correspond", "fit") and plan.reused == (prepared,)
        assert plan.reason.endswith("the correspondence of model 'vases' was made from other shapes")


def test_the_first_current_candidate_is_reused():
    newest_stale, older = found_prepared("'vases Prepared.001'", current=False), found_prepared()
    assert plan_stages(ASKED, [newest_stale, older]).reused == (older,)


def test_run_options_never_prevent_reuse():
    """How a run was scheduled is not what it made: no settings an output records name a run
    option, and a model whose file recorded some (as model files did) offers its
    correspondence to a fit that runs otherwise."""
    assert not {name.split(".")[-1] for name in _leaves(ASKED)} & set(RUN_OPTIONS)
    had = FitSettings.from_dict({**ASKED.as_dict(), "jobs": 4, "scheduler": "tcp://host:8786"}, recorded=True)
    assert had == ASKED
    correspondence, _ = found_correspondence(settings=had.correspondence, prepare=had.prepare, template=had.template)
    assert plan_stages(ASKED, [found_prepared(), correspondence]).run == ("fit",)


def test_found_outputs_without_recorded_settings_are_not_reused():
    plan = plan_stages(ASKED, [found_prepared(settings=None)])
    assert plan.run == ("prepare", "correspond", "fit")
    assert plan.reason.endswith("'vases Prepared' records no Prepare settings")
    correspondence, _ = found_correspondence(settings=None)
    plan = plan_stages(ASKED, [found_prepared(), correspondence])
    assert plan.run == ("correspond", "fit") and plan.reason.endswith("records no correspondence settings")


def test_a_given_file_is_used_with_its_recorded_settings():
    prepared = Offered("prepare", "p.npz", prepare=OTHER_PREPARE, given=True)
    plan = plan_stages(ASKED, [prepared], {"prepare": {"n_landmarks": 60}})
    assert plan.run == ("correspond", "fit") and plan.settings.prepare == OTHER_PREPARE
    assert plan.settings.model == ASKED.model
    assert plan.reason == "using p.npz as given (with the settings it records); corresponding and fitting"
    corr = Offered("correspond", "c.npz", prepare=OTHER_PREPARE, correspondence=OTHER_CORRESPONDENCE, given=True)
    plan = plan_stages(ASKED, [corr])
    assert plan.run == ("fit",) and plan.settings.correspondence == OTHER_CORRESPONDENCE
    assert plan_stages(ASKED, [corr], last="correspond").run == ()


def test_a_given_file_without_recorded_settings_takes_the_asked_ones():
    plan = plan_stages(ASKED, [Offered("correspond", "old.npz", given=True)])
    assert plan.settings == ASKED and plan.run == ("fit",)
    assert plan.reason == "using old.npz as given (it records no Prepare or correspondence settings: taken as asked)" \
                          "; fitting"


def test_an_option_contradicting_a_given_file_is_a_conflict_naming_both():
    prepared = Offered("prepare", "p.npz", prepare=OTHER_PREPARE, given=True)
    with pytest.raises(SettingsConflict) as caught:
        plan_stages(ASKED, [prepared], {"prepare": {"seed": 0}})
    assert (caught.value.group, caught.value.option, caught.value.value, caught.value.recorded) == ("prepare", "seed",
                                                                                                   0, 4)
    assert str(caught.value) == "seed 0 conflicts with p.npz, prepared with seed 4; leave it out to use the file's"
    corr = Offered("correspond", "c.npz", prepare=OTHER_PREPARE, correspondence=OTHER_CORRESPONDENCE, given=True)
    with pytest.raises(SettingsConflict, match="iterations.max_iterations 7 conflicts with c.npz, corresponded with"):
        plan_stages(ASKED, [corr], {"correspondence": {"iterations.max_iterations": 7}})


@pytest.fixture(scope="module")
def prepared():
    meshes = [shape.mesh for shape in make_vases(3, seed=2, resolution=(8, 10))]
    return prepare_meshes(meshes, PrepareSettings(n_landmarks=20, align="pca"))


def test_read_offered_records_a_files_settings(prepared, tmp_path):
    prepared.save(tmp_path / "p.npz")
    offered = read_offered(tmp_path / "p.npz", "prepare")
    assert offered.given and offered.stage == "prepare" and offered.prepare == prepared.settings
    assert isinstance(offered.data, PreparedCollection) and offered.data.names == prepared.names


class _Model:
    """What `same_shapes` reads of a fitted model (no shape posed by its landmarks)."""

    def __init__(self, prepared):
        self.names = list(prepared.names)
        self.meshes = [s.mesh for s in prepared.shapes]
        self.correspondence = type("C", (), {"transforms": np.stack([s.transform.matrix for s in prepared.shapes]),
                                             "model_poses": np.tile(np.eye(4), (len(prepared), 1, 1))})


def test_same_shapes_compares_names_meshes_and_transforms(prepared):
    model = _Model(prepared)
    assert same_shapes(model, prepared)
    model.meshes[1] = model.meshes[1].with_vertices(model.meshes[1].vertices * 1.01)
    assert not same_shapes(model, prepared)
    model = _Model(prepared)
    model.correspondence.transforms = model.correspondence.transforms.copy()
    model.correspondence.transforms[0, 0, 3] += 0.1
    assert not same_shapes(model, prepared)
    model = _Model(prepared)
    model.names = model.names[::-1]
    assert not same_shapes(model, prepared)
