"""Typed settings: PrepareSettings / FitSettings check themselves, travel as one JSON
string, and files written before that (key/value strings) still load."""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass, replace

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PrepareSettings, PreparedCollection, prepare_meshes
from shapegen_core.correspond import Correspondence, CorrespondenceSettings, correspond
from shapegen_core.correspond.settings import DataTermSettings, IterationSettings, OutlierSettings, StiffnessSettings
from shapegen_core.generate.deform import DeformSettings
from shapegen_core.base.errors import ModelFileError, ShapeGenError
from shapegen_core.app.fit_settings import FitSettings, RunOptions, split_run_options
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.app.pipeline import fit_meshes
from shapegen_core.base.compat import old_model_settings
from shapegen_core.base.settings import Settings, SettingsError, group, option, recorded_settings

#: the correspondence settings of the `corresponded` fixture as files written before the grouped settings
#: record them: one flat JSON object (written by CorrespondenceSettings(alpha_steps=1,
#: max_iterations=3, groupwise_rounds=0).to_json() at de08ccf)
FLAT_JSON = (
    '{"gamma": 2.0, "k_neighbours": 6, "alpha_start": 100.0, "alpha_end": 5.0, "alpha_steps": 1, '
    '"bidirectional_weight": 1.0, "normal_max_angle": 60.0, "matching": "closest", "feature_between": 1.0, '
    '"initialisation": "closest", "distance_weights": false, "snap_to_vertices": false, "update_template": false, '
    '"tolerance": 0.001, "max_iterations_per_alpha": 4, "max_iterations": 3, "ridge": 1e-09, "proxy_faces": 40000, '
    '"groupwise_rounds": 0, "outlier_mad_factor": 3.0, "outlier_min_ratio": 1.5, "max_residual": 0.05, '
    '"max_scale_ratio": 3.0, "loo_mad_factor": 3.0, "loo_min_ratio": 4.0, "loo_variance": 0.9, "refine": "none", '
    '"refine_iterations": 30, "refine_compactness": 1.0, "refine_spread": 1.0, "refine_regulariser": 0.001, '
    '"refine_normals": 1.0, "refine_smooth_fields": 30, "refine_sigma": 1.0, "refine_step": 0.3, '
    '"refine_max_move": 0.5, "refine_alignment": "similarity", "refine_tolerance": 1e-06}')
#: the same settings, nested by subsystem (the start they record, closest points, is no
#: longer the default)
SMALL = CorrespondenceSettings(stiffness=StiffnessSettings(alpha_steps=1), iterations=IterationSettings(max_iterations=3),
                               groupwise_rounds=0, data_term=DataTermSettings(initialisation="closest"))


@pytest.fixture(scope="module")
def prepared(small_vases):
    return prepare_meshes([s.mesh for s in small_vases[:3]], PrepareSettings(n_landmarks=30, up_axis="y", seed=2))


@pytest.fixture(scope="module")
def corresponded(prepared):
    return correspond(prepared, SMALL, jobs=1)


@pytest.fixture(scope="module")
def fitted(small_vases, tmp_path_factory):
    settings = FitSettings(prepare=PrepareSettings(n_landmarks=40), model="ppca", mesh_template="vase_003",
                           correspondence=replace(SMALL, stiffness=StiffnessSettings(alpha_steps=2),
                                                  iterations=IterationSettings(max_iterations=6)))
    model = fit_meshes([s.mesh for s in small_vases[:4]], settings, jobs=1)
    return model, model.save(tmp_path_factory.mktemp("model") / "model.npz")


def _rewrite(path, target, drop=(), **changes):
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files if k not in drop}
    arrays.update(changes)
    np.savez(target, **arrays)
    return target


# ---------------------------------------------------------------------------- checks
@pytest.mark.parametrize("options,named,message", [
    ({"n_landmarks": 2}, "n_landmarks", "n_landmarks must be at least 4, got 2"),
    ({"n_landmarks": -5}, "n_landmarks", "n_landmarks must be at least 4, got -5"),
    ({"n_landmarks": 80.5}, "n_landmarks", "n_landmarks must be an integer, got 80.5"),
    ({"up_axis": "w"}, "up_axis", "unknown up_axis 'w'; choose from x, y, z, -x, -y, -z"),
    ({"align": "best"}, "align", "unknown align 'best'; choose from consensus, pca, none"),
    ({"scale": "area"}, "scale", "unknown scale 'area'; choose from variance, bbox, none"),
    ({"centre": "middle"}, "centre", "unknown centre 'middle'; choose from centroid, highest, none"),
    ({"seed": -1}, "seed", "seed must be at least 0, got -1"),
])
def test_invalid_prepare_settings_name_the_option_and_what_is_allowed(options, named, message):
    with pytest.raises(ShapeGenError) as caught:
        PrepareSettings(**options)
    assert isinstance(caught.value, SettingsError) and caught.value.option == named
    assert str(caught.value) == message


@pytest.mark.parametrize("options,named", [
    ({"latent_dim": 0}, "latent_dim"),
    ({"mesh_template": ""}, "mesh_template"),
    ({"deform": {"final_alpha": 0.0}}, "deform.final_alpha"),
    ({"deform": {"gamma": -1.0}}, "deform.gamma"),
])
def test_invalid_fit_settings_name_the_option(options, named):
    with pytest.raises(SettingsError, match=f"^{named} must be") as caught:
        FitSettings.from_dict(options)
    assert caught.value.option == named
    with pytest.raises(SettingsError, match=r"^unknown model 'gpr'; choose from ppca, gplvm, bgplvm$"):
        FitSettings(model="gpr")


@pytest.mark.parametrize("options,message", [
    ({"final_alpha": 0.0}, "final_alpha must be greater than 0, got 0.0"),
    ({"start_alpha": -1.0}, "start_alpha must be greater than 0, got -1.0"),
    ({"gamma": 0}, "gamma must be greater than 0, got 0"),
    ({"n_stages": 0}, "n_stages must be at least 1, got 0"),
    ({"k_blend": 0}, "k_blend must be at least 1, got 0"),
])
def test_deform_settings_check_themselves(options, message):
    with pytest.raises(SettingsError) as caught:
        DeformSettings(**options)
    assert str(caught.value) == message and caught.value.option == next(iter(options))


@pytest.mark.parametrize("group_name,options,message", [
    ("stiffness", {"gamma": 0.0}, "gamma must be greater than 0, got 0.0"),
    ("stiffness", {"k_neighbours": 0}, "k_neighbours must be at least 1, got 0"),
    ("stiffness", {"alpha_end": 0.0}, "alpha_end must be greater than 0, got 0.0"),
    ("stiffness", {"alpha_start": 4.0}, "alpha_start must be at least alpha_end (5.0), got 4.0"),
    ("stiffness", {"alpha_steps": 0}, "alpha_steps must be at least 1, got 0"),
    ("data_term", {"bidirectional_weight": -1.0}, "bidirectional_weight must be at least 0, got -1.0"),
    ("data_term", {"snap_to_vertices": 1}, "snap_to_vertices must be true or false, got 1"),
    ("iterations", {"tolerance": -1e-3}, "tolerance must be at least 0, got -0.001"),
    ("iterations", {"ridge": -1.0}, "ridge must be at least 0, got -1.0"),
    ("iterations", {"max_iterations": 0}, "max_iterations must be at least 1, got 0"),
    ("iterations", {"max_iterations_per_alpha": 0}, "max_iterations_per_alpha must be at least 1, got 0"),
    ("outliers", {"loo_variance": 1.5}, "loo_variance must be at most 1, got 1.5"),
])
def test_correspondence_settings_check_themselves(group_name, options, message):
    """Each group checks its own options; nested, an error names the option by its dotted path."""
    group_class = type(getattr(CorrespondenceSettings(), group_name))
    with pytest.raises(SettingsError) as caught:
        CorrespondenceSettings.from_dict({group_name: options})
    name = next(iter(options))
    assert str(caught.value) == f"{group_name}.{message}" and caught.value.option == f"{group_name}.{name}"
    with pytest.raises(SettingsError, match=f"^{re.escape(message)}$"):
        group_class(**options)


def test_from_dict_refuses_unknown_names_and_wrong_types():
    with pytest.raises(SettingsError, match="has no option 'landmarks'"):
        PrepareSettings.from_dict({"landmarks": 100})
    with pytest.raises(SettingsError, match="^n_landmarks must be an integer"):
        PrepareSettings.from_dict({"n_landmarks": "100"})
    with pytest.raises(SettingsError, match=r"^correspondence\.stiffness\.gamma must be greater than 0"):  # nested
        FitSettings.from_dict({"correspondence": {"stiffness": {"gamma": -1}}})


# ---------------------------------------------------------------------------- round trips
def test_prepare_settings_round_trip_through_json_and_the_prepared_file(prepared, tmp_path):
    settings = PrepareSettings(n_landmarks=30, up_axis="y", seed=2)
    assert PrepareSettings.from_json(settings.to_json()) == settings
    back = PreparedCollection.load(prepared.save(tmp_path / "prepared.npz"))
    assert back.settings == settings
    with np.load(tmp_path / "prepared.npz") as data:
        assert data["settings"].shape == () and "settings_keys" not in data.files


def test_fit_settings_round_trip_nested_and_old_files_flat(fitted):
    model, path = fitted
    assert FitSettings.from_json(model.settings.to_json()) == model.settings
    assert GenerativeShapeModel.load(path).settings == model.settings
    flat = {"n_landmarks": 40, "up_axis": "y", "align": "pca", "scale": "bbox", "centre": "none", "seed": 3,
            "model": "ppca", "latent_dim": None, "correspondence": {"alpha_end": 3.0}, "deform": {"final_alpha": 2.5}}
    with pytest.raises(SettingsError, match="has no option 'align'"):  # Prepare options nest under "prepare"
        FitSettings.from_dict(flat)
    # model files of the key/value layout record them so, deformation settings as numbers by key
    keys = {"n_landmarks": "40", "up_axis": "'y'", "align": "pca", "scale": "'bbox'", "centre": "none", "seed": "3",
            "model": "'ppca'", "latent_dim": "None", "correspondence.alpha_end": "3.0"}
    arrays = {"settings_keys": np.asarray(list(keys)), "settings_values": np.asarray(list(keys.values())),
              "deform_keys": np.asarray(["final_alpha", "n_stages"]), "deform_values": np.asarray([2.5, 8.0])}
    nested = FitSettings.from_dict(old_model_settings(arrays, "old.npz"), recorded=True)
    assert isinstance(nested.deform.n_stages, int)
    assert nested.prepare == PrepareSettings(n_landmarks=40, up_axis="y", align="pca", scale="bbox", centre="none",
                                             seed=3)
    assert nested.correspondence.stiffness.alpha_end == 3.0 and nested.deform.final_alpha == 2.5
    assert FitSettings.from_dict(nested.as_dict()) == nested


def test_correspondence_files_record_their_settings_and_the_prepare_settings(prepared, corresponded, tmp_path):
    path = corresponded.save(tmp_path / "corr.npz")
    loaded = Correspondence.load(path)
    assert loaded.settings == SMALL
    assert loaded.prepare == prepared.settings == PrepareSettings(n_landmarks=30, up_axis="y", seed=2)
    with np.load(path) as data:
        assert data["settings"].shape == () and data["prepare_settings"].shape == ()
        assert "settings_keys" not in data.files
    unrecorded = replace(corresponded, settings=None, prepare=None)
    back = Correspondence.load(unrecorded.save(tmp_path / "unrecorded.npz"))
    assert back.settings is None and back.prepare is None


def test_an_invalid_recorded_setting_is_a_clear_file_error(prepared, tmp_path):
    path = prepared.save(tmp_path / "prepared.npz")
    bad = _rewrite(path, tmp_path / "bad.npz", settings=np.asarray('{"n_landmarks": 2}'))
    with pytest.raises(ModelFileError, match=f"^{bad}: recorded settings are invalid: n_landmarks must be"):
        PreparedCollection.load(bad)


# ---------------------------------------------------------------------------- older files
def test_prepared_files_of_the_previous_version_still_load(prepared, tmp_path):
    """Before: settings as str() values by key (and none at all from the add-on's copies)."""
    path = prepared.save(tmp_path / "prepared.npz")
    old = _rewrite(path, tmp_path / "old.npz", drop=("settings",),
                   settings_keys=np.asarray(["n_landmarks", "up_axis", "align", "scale", "centre", "seed"]),
                   settings_values=np.asarray(["30", "y", "consensus", "variance", "centroid", "2"]))
    assert PreparedCollection.load(old).settings == prepared.settings
    empty = _rewrite(path, tmp_path / "empty.npz", drop=("settings",), settings_keys=np.zeros(0, dtype=str),
                     settings_values=np.zeros(0, dtype=str))
    assert PreparedCollection.load(empty).settings is None


def test_correspondence_files_of_the_previous_version_still_load(corresponded, tmp_path):
    """Before: settings as repr() values by (flat) key, the Prepare settings not recorded."""
    path = corresponded.save(tmp_path / "corr.npz")
    recorded = json.loads(FLAT_JSON)
    old = _rewrite(path, tmp_path / "old.npz", drop=("settings", "prepare_settings"),
                   settings_keys=np.asarray(list(recorded)),
                   settings_values=np.asarray([repr(v) for v in recorded.values()]))
    loaded = Correspondence.load(old)
    assert loaded.settings == corresponded.settings and loaded.prepare is None
    np.testing.assert_array_equal(loaded.points, corresponded.points)


def test_flat_correspondence_settings_of_before_read_into_their_groups(corresponded, tmp_path):
    """Files written before the grouped settings record CorrespondenceSettings flat (one JSON object, or
    before that key/value strings); `FIELDS_MOVED` reads them into the groups, renamed
    options (outlier_mad_factor → outliers.residual_mad_factor) included, and files written now
    nest them; the refinement options they record (an option since removed) are read past."""
    assert CorrespondenceSettings.from_json(FLAT_JSON, recorded=True) == SMALL
    flat = json.loads(FLAT_JSON)
    legacy = {"settings_keys": np.asarray(list(flat)), "settings_values": np.asarray([repr(v) for v in flat.values()])}
    assert recorded_settings(CorrespondenceSettings, legacy, "old.npz") == SMALL
    path = corresponded.save(tmp_path / "corr.npz")
    old = _rewrite(path, tmp_path / "old.npz", settings=np.asarray(FLAT_JSON))
    assert Correspondence.load(old).settings == SMALL
    with np.load(path) as data:  # written now: nested by subsystem
        assert json.loads(str(data["settings"]))["stiffness"]["alpha_steps"] == 1
    fit = FitSettings(correspondence=SMALL).as_dict()
    fit["correspondence"] = flat  # a model file's FitSettings before the grouped settings
    assert FitSettings.from_json(json.dumps(fit), recorded=True).correspondence == SMALL
    # a model file written before the start was an option: closest points, not today's default
    fit["correspondence"] = {k: v for k, v in flat.items() if k != "initialisation"}
    assert FitSettings.from_json(json.dumps(fit), recorded=True).correspondence.data_term.initialisation == "closest"
    assert FitSettings().correspondence.data_term.initialisation == "auto"
    renamed = {"outlier_mad_factor": 4.0}
    assert CorrespondenceSettings.from_dict(renamed) == CorrespondenceSettings(
        outliers=OutlierSettings(residual_mad_factor=4.0))


def test_population_refinement_files_still_read_and_settings_naming_it_now_say_it_went():
    """Groupwise refinement after NICP was removed: settings files recorded naming it, flat or
    nested, read as today's settings; settings given now that name it are refused, saying why."""
    nested = json.loads(SMALL.to_json())
    nested["refinement"] = {"method": "population", "iterations": 30, "sigma": 1.0}
    assert CorrespondenceSettings.from_json(json.dumps(nested), recorded=True) == SMALL
    flat = {**json.loads(FLAT_JSON), "refine": "population"}
    assert CorrespondenceSettings.from_dict(flat, recorded=True) == SMALL
    fit = FitSettings(correspondence=SMALL).as_dict()
    fit["correspondence"]["refinement"] = {"method": "population"}  # a model file's settings
    assert FitSettings.from_json(json.dumps(fit), recorded=True).correspondence == SMALL
    for given in ({"refine": "population"}, {"refine_sigma": 2.0}, {"refinement": {"method": "none"}}):
        with pytest.raises(SettingsError, match="was removed: groupwise refinement after NICP"):
            CorrespondenceSettings.from_dict(given)


def test_options_given_flat_are_accepted_beside_nested_ones():
    """The add-on and the worker pass options as flat dicts: accepted beside nested ones; an
    option named both ways (the panel's flat one, Extra Settings' nested one) takes the
    nested value."""
    mixed = CorrespondenceSettings.from_dict({"alpha_end": 10.0, "data_term": {"matching": "features"}, "gamma": 3.0})
    assert mixed.stiffness.alpha_end == 10.0 and mixed.data_term.matching == "features"
    both = CorrespondenceSettings.from_dict({"alpha_end": 10.0, "alpha_steps": 2, "stiffness": {"alpha_end": 3.0}})
    assert both.stiffness == StiffnessSettings(alpha_end=3.0, alpha_steps=2)
    with pytest.raises(SettingsError, match=r"^stiffness\.alpha_end must be greater than 0"):  # named where it lives
        CorrespondenceSettings.from_dict({"alpha_end": 0.0})
    with pytest.raises(SettingsError, match="has no option 'sigma'"):  # only the names of before, flat
        CorrespondenceSettings.from_dict({"sigma": 2.0})
    with pytest.raises(SettingsError, match="^groupwise_rounds must be at least 0, got -1$"):
        CorrespondenceSettings.from_dict({"groupwise_rounds": -1})


@dataclass(frozen=True)
class _Inner(Settings):
    FIELDS_ADDED_LATER = {"late": 2}
    depth: int = option(1, "", minimum=0)
    late: int = option(3, "")


@dataclass(frozen=True)
class _Middle(Settings):
    inner: _Inner = group(_Inner)


@dataclass(frozen=True)
class _Outer(Settings):
    FIELDS_MOVED = {"old_depth": "middle.inner.depth", "kept": "kept"}
    middle: _Middle = group(_Middle)
    kept: str = option("a", "")


def test_fields_moved_is_a_general_mechanism():
    """Any depth, renamed or not; the caller's data is left as it was; a file that records
    the flat name reads the added-later values of the group it moved to."""
    data = {"old_depth": 4, "middle": {"inner": {}}}
    assert _Outer.from_dict(data) == _Outer(_Middle(_Inner(depth=4)))
    assert data == {"old_depth": 4, "middle": {"inner": {}}}
    assert _Outer.from_dict({"old_depth": 4}, recorded=True).middle.inner == _Inner(depth=4, late=2)
    assert _Outer.from_dict({}, recorded=True).middle.inner.late == 2  # a group left out entirely: as recorded too
    assert _Outer.from_dict({"old_depth": 4}).middle.inner.late == 3  # given now: today's default
    with pytest.raises(SettingsError, match=r"^middle\.inner\.depth must be at least 0"):
        _Outer.from_dict({"old_depth": -1})
    with pytest.raises(SettingsError, match="cannot be given flat beside 'middle' given as settings"):
        _Outer.from_dict({"old_depth": 4, "middle": _Middle()})


def test_model_files_of_the_previous_version_still_load(fitted, tmp_path):
    """Before: settings as repr() values by (dotted) key, deformation settings as numbers."""
    model, path = fitted
    s = model.settings
    corr = {**json.loads(FLAT_JSON), "alpha_steps": 2, "max_iterations": 6}  # flat, as these files recorded them
    keys = ([f"{k}" for k in s.prepare.as_dict()] + ["model", "latent_dim", "template", "jobs"]
            + [f"correspondence.{k}" for k in corr])
    values = ([repr(v) for v in s.prepare.as_dict().values()] + [repr(s.model), "None", "None", "1"]
              + [repr(v) for v in corr.values()])
    deform = s.deform.__dataclass_fields__
    old = _rewrite(path, tmp_path / "old.npz", drop=("settings", "corr__settings", "corr__prepare_settings"),
                   settings_keys=np.asarray(keys), settings_values=np.asarray(values),
                   deform_keys=np.asarray(list(deform)),
                   deform_values=np.asarray([float(getattr(s.deform, k)) for k in deform]),
                   corr__settings_keys=np.asarray(list(corr)),
                   corr__settings_values=np.asarray([repr(v) for v in corr.values()]))
    loaded = GenerativeShapeModel.load(old)
    assert loaded.settings == replace(s, mesh_template="nearest-data")
    assert isinstance(loaded.deform_settings.n_stages, int)


def test_run_options_are_options_of_the_run_never_recorded(fitted, tmp_path, capsys):
    """How a run is scheduled (`RunOptions`: jobs, scheduler) is not what the model is: a
    model file records neither; a file that records them (as model files did) reads as if
    it had not, without a word; named among the model's settings now they are refused,
    saying where they go."""
    model, path = fitted
    with np.load(path) as data:
        recorded = json.loads(str(data["settings"]))
    assert not {"jobs", "scheduler"} & set(recorded)
    old = _rewrite(path, tmp_path / "old.npz",
                   settings=np.asarray(json.dumps({**recorded, "jobs": 3, "scheduler": "local:2"})))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert GenerativeShapeModel.load(old).settings == model.settings
    assert capsys.readouterr() == ("", "")
    with pytest.raises(SettingsError, match=r"^jobs was removed: .*an option of the run \(--jobs, --scheduler"):
        FitSettings.from_dict({"jobs": 1})
    assert split_run_options({"jobs": 2, "model": "ppca"}) == (RunOptions(jobs=2), {"model": "ppca"})
    assert split_run_options({}) == (RunOptions(), {})
    with pytest.raises(SettingsError, match="^jobs must be at least 1, got 0$"):
        split_run_options({"jobs": 0})


# ---------------------------------------------------------------------------- defaults it records
def test_choose_template_reads_the_recorded_mesh_template(fitted):
    """The default meshing template is a recorded setting (it read a key nothing wrote)."""
    model, path = fitted
    loaded = GenerativeShapeModel.load(path)
    assert loaded.settings.mesh_template == "vase_003"
    fits = int(np.flatnonzero(~loaded.correspondence.outliers)[0])  # outliers are never templates
    own = loaded.correspondence.points[fits]
    assert loaded.choose_template(own, "nearest-data") == fits
    assert loaded.choose_template(own, None) == loaded.names.index("vase_003")


def test_an_unknown_mesh_template_is_refused_before_fitting(small_vases):
    with pytest.raises(SettingsError, match="no shape is named 'vase_999'"):
        fit_meshes([s.mesh for s in small_vases[:2]], FitSettings(mesh_template="vase_999"))


def test_a_prepared_collection_fits_with_its_own_settings(prepared):
    """The model records how its shapes were prepared, not FitSettings' defaults."""
    settings = FitSettings(model="ppca", correspondence=SMALL)
    model = fit_meshes(prepared, settings, jobs=1)
    assert model.settings.prepare == PrepareSettings(n_landmarks=30, up_axis="y", seed=2)
    unrecorded = PreparedCollection(prepared.shapes, prepared.landmarks)
    assert fit_meshes(unrecorded, settings, jobs=1).settings.prepare == settings.prepare
