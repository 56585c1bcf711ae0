"""Older files still read (core/base/compat.py): a prepared file, a correspondence file and a
model file in each older layout, written here from a file made now — only the arrays files
of that time held, their settings as those files recorded them — load as today's, silently.

Layouts, oldest first:
- key/value: settings as key/value strings (Prepare's str(), the correspondence's and the
  model's repr()), the correspondence's options flat, a model's Prepare options flat beside
  its own and its meshing settings as numbers by key; none of the arrays added since
  (pose reports, Keep Pose, flags, unreadable files, starts, poses, refinement, feature
  shares, layouts, part labels, latents); model files at format version 1;
- flat JSON: settings as one JSON string, the correspondence's options not yet grouped
  (feature-match knobs since removed among them), a model's run options (jobs, scheduler)
  among its settings.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import replace

import numpy as np
import pytest

from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.pipeline import fit_meshes
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.base.compat import CORRESPONDENCE_MOVED, CORRESPONDENCE_REMOVED
from shapegen_core.correspond import Correspondence, CorrespondenceSettings, correspond
from shapegen_core.correspond.settings import DataTermSettings, IterationSettings, StiffnessSettings
from shapegen_core.demo_data import make_vases
from shapegen_core.generate.deform import DeformSettings
from shapegen_core.preprocess.collection import PreparedCollection, PrepareSettings, prepare_meshes

PREPARE = PrepareSettings(n_landmarks=30, up_axis="z", seed=2)
#: (closest points named: the start those files ran, no longer the default)
SMALL = CorrespondenceSettings(stiffness=StiffnessSettings(alpha_steps=1), iterations=IterationSettings(max_iterations=3),
                               groupwise_rounds=0, data_term=DataTermSettings(initialisation="closest"))
FIT = FitSettings(prepare=PREPARE, model="ppca", correspondence=SMALL)

#: the arrays of the oldest files of each kind (their settings besides)
MESH_ARRAYS = ("vertices", "faces", "vertex_offsets", "face_offsets")
OLDEST_PREPARED = ("names", *MESH_ARRAYS, "transforms", "orientation_changed", "landmarks", "landmark_faces",
                   "landmark_barycentric", "landmark_offsets", "landmark_radius")
OLDEST_CORRESPONDENCE = ("names", "points", "points_input", "face_index", "barycentric", "edges", "template_points",
                         "template_name", "transforms", "residuals", "iterations", "outliers", "outlier_reasons")
OLDEST_MODEL = (*(f"corr__{name}" for name in OLDEST_CORRESPONDENCE), *(f"mesh_{name}" for name in MESH_ARRAYS),
                "metadata_keys", "metadata_values")  # and every model__ array, unchanged since

#: SMALL as the oldest correspondence files record it: the options there were then, flat, by repr()
OLDEST_CORRESPONDENCE_SETTINGS = {
    "gamma": 2.0, "k_neighbours": 6, "alpha_start": 100.0, "alpha_end": 5.0, "alpha_steps": 1,
    "bidirectional_weight": 1.0, "normal_max_angle": 60.0, "distance_weights": False, "snap_to_vertices": False,
    "update_template": False, "tolerance": 1e-3, "max_iterations_per_alpha": 4, "max_iterations": 3, "ridge": 1e-9,
    "groupwise_rounds": 0, "outlier_mad_factor": 3.0, "outlier_min_ratio": 1.5, "max_residual": 0.05,
    "max_scale_ratio": 3.0}
#: ... read now: what those runs did where options were added later (no turning-line feature)
OLDEST_READ = replace(SMALL, data_term=DataTermSettings(feature_between=0.0, initialisation="closest"))

#: SMALL as flat JSON files record it: every option flat, the outlier and refinement ones by
#: their names of then, and the feature-match knobs removed since (constants now)
FLAT_JSON_CORRESPONDENCE_SETTINGS = {
    **OLDEST_CORRESPONDENCE_SETTINGS, "matching": "closest", "feature_between": 1.0, "initialisation": "closest",
    "proxy_faces": 40000, "loo_mad_factor": 3.0, "loo_min_ratio": 4.0, "loo_variance": 0.9, "refine": "none",
    "refine_iterations": 30, "refine_sigma": 1.0, "refine_alignment": "similarity",
    "feature_normals": 1.0, "feature_tilt": 0.5, "feature_up": 1.0, "feature_up_width": 0.2, "feature_stiffness": 0.4,
    "feature_trim": 0.9, "feature_merged_regions": True, "feature_samples": 4000, "feature_fit_check": True,
    "feature_fallback_share": 0.5}


@pytest.fixture(scope="module")
def today(tmp_path_factory):
    """A prepared file, its correspondence file and a model file, written now."""
    folder = tmp_path_factory.mktemp("today")
    meshes = [s.mesh for s in make_vases(3, seed=5, resolution=(12, 16))]
    prepared = prepare_meshes(meshes, PREPARE)
    corr = correspond(prepared, SMALL, jobs=1)
    model = fit_meshes(prepared, FIT, jobs=1)
    return (prepared.save(folder / "prepared.npz"), corr.save(folder / "corr.npz"), model.save(folder / "model.npz"),
            model)


def _old(path, target, keep, version=None, **settings):
    """`path` rewritten as an older file: only the arrays named in `keep` (a name or a
    prefix ending in "__"), the `settings` arrays given, format version `version`."""
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files
                  if k in ("format", "format_version") or k in keep or any(k.startswith(p) for p in keep if p[-2:] == "__")}
    if version is not None:
        arrays["format_version"] = np.asarray(version, dtype=np.int64)
    np.savez(target, **arrays, **{key: np.asarray(value) for key, value in settings.items()})
    return target


def _key_value(prefix: str, data: dict, text=repr) -> dict:
    return {f"{prefix}_keys": np.asarray(list(data), dtype=str),
            f"{prefix}_values": np.asarray([text(v) for v in data.values()], dtype=str)}


def _loaded_quietly(load, path, capsys):
    """`load(path)`, checking it warns and prints nothing."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = load(path)
    assert capsys.readouterr() == ("", "")
    return loaded


def test_oldest_prepared_files_read(today, tmp_path, capsys):
    path = today[0]
    prepare = {"n_landmarks": 30, "up_axis": "z", "align": "consensus", "scale": "variance", "centre": "centroid",
               "seed": 2}
    old = _old(path, tmp_path / "prepared.npz", OLDEST_PREPARED, **_key_value("settings", prepare, text=str))
    loaded, now = _loaded_quietly(PreparedCollection.load, old, capsys), PreparedCollection.load(path)
    assert loaded.settings == PREPARE and loaded.unreadable == {}
    assert [s.pose_change for s in loaded.shapes] == [""] * 3 and loaded.flagged() == []
    assert not any(s.pose_kept for s in loaded.shapes)
    for a, b in zip(loaded.landmarks, now.landmarks):
        np.testing.assert_array_equal(a.points, b.points)


def test_oldest_correspondence_files_read(today, tmp_path, capsys):
    path = today[1]
    old = _old(path, tmp_path / "corr.npz", OLDEST_CORRESPONDENCE,
               **_key_value("settings", OLDEST_CORRESPONDENCE_SETTINGS))
    loaded, now = _loaded_quietly(Correspondence.load, old, capsys), Correspondence.load(path)
    assert loaded.settings == OLDEST_READ and loaded.prepare is None
    assert loaded.recorded.refinement == "none" and loaded.start_used == "closest" and loaded.unreadable == {}
    np.testing.assert_array_equal(loaded.points, now.points)
    np.testing.assert_array_equal(loaded.model_points(), now.model_points())  # no poses: the prepared frame


def test_flat_json_correspondence_files_read(today, tmp_path, capsys):
    """Settings as one JSON string before they were grouped: every option flat (the renamed
    outlier and refinement ones by their names of then), the removed knobs among them."""
    flat = FLAT_JSON_CORRESPONDENCE_SETTINGS
    assert set(flat) <= set(CORRESPONDENCE_MOVED) | set(CORRESPONDENCE_REMOVED) | {"proxy_faces", "groupwise_rounds"}
    old = _old(today[1], tmp_path / "corr.npz", OLDEST_CORRESPONDENCE, settings=json.dumps(flat),
               prepare_settings=PREPARE.to_json())
    loaded = _loaded_quietly(Correspondence.load, old, capsys)
    assert loaded.settings == SMALL and loaded.prepare == PREPARE


def test_oldest_model_files_read(today, tmp_path, capsys):
    path, model = today[2], today[3]
    fit = {**PREPARE.as_dict(), "model": "ppca", "latent_dim": None, "template": None, "jobs": 1,
           **{f"correspondence.{k}": v for k, v in OLDEST_CORRESPONDENCE_SETTINGS.items()},
           **{f"deform.{k}": v for k, v in DeformSettings().as_dict().items()}}
    deform = DeformSettings().as_dict()
    old = _old(path, tmp_path / "model.npz", (*OLDEST_MODEL, "model__"), version=1, **_key_value("settings", fit),
               **_key_value("corr__settings", OLDEST_CORRESPONDENCE_SETTINGS),
               deform_keys=np.asarray(list(deform)), deform_values=np.asarray([float(v) for v in deform.values()]))
    loaded = _loaded_quietly(GenerativeShapeModel.load, old, capsys)
    assert loaded.settings == replace(FIT, correspondence=OLDEST_READ)
    assert isinstance(loaded.settings.deform.n_stages, int) and loaded.part_labels is None
    assert loaded.correspondence.settings == OLDEST_READ
    np.testing.assert_allclose(loaded.training_latents(), model.training_latents(), atol=1e-10)  # computed on load
    assert loaded.meshes[0].report.layout is None  # version 1: no layouts


def test_flat_json_model_files_read(today, tmp_path, capsys):
    """A model file's settings as one JSON string while its correspondence options were flat
    and it recorded how its run was scheduled (jobs, scheduler)."""
    path, model = today[2], today[3]
    fit = {**FIT.as_dict(), "correspondence": FLAT_JSON_CORRESPONDENCE_SETTINGS, "jobs": 2, "scheduler": None}
    with np.load(path) as data:
        others = [k for k in data.files if k not in ("settings", "corr__settings")]
    old = _old(path, tmp_path / "model.npz", others, settings=json.dumps(fit),
               corr__settings=json.dumps(FLAT_JSON_CORRESPONDENCE_SETTINGS))
    loaded = _loaded_quietly(GenerativeShapeModel.load, old, capsys)
    assert loaded.settings == model.settings == FIT
