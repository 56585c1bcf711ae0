"""Outliers in the Correspondence panel: listed with their reasons, left out of
training by Exclude Outliers and Refit (recorded on the collection, the objects
untouched), taken back by Include Excluded."""

from __future__ import annotations

from dataclasses import replace

import bpy
import numpy as np
from conftest import VASE_RESOLUTION, VASE_SEED, add_vase_collection, addon_module, fast_fit_json, load_model
from test_panels import _draw_all

REASON = "landmarks 6.1× farther from the other shapes' model than the median shape (leave-one-out reconstruction)"


def _model_with_an_outlier(extension, model_files, tmp_path, name: str):
    """The session's small PPCA model with shape `name` flagged, loaded into the scene."""
    shape_model = addon_module(extension, "core.app.shape_model")
    model = shape_model.GenerativeShapeModel.load(model_files["ppca"])
    corr = model.correspondence
    flagged = np.array([n == name for n in corr.names])
    corr = replace(corr, outliers=flagged, outlier_reasons=[REASON if f else "" for f in flagged])
    path = tmp_path / "flagged.npz"
    shape_model.GenerativeShapeModel(model.meshes, corr, model.model, settings=model.settings).save(path)
    load_model("flagged", {"flagged": path})


def test_outliers_are_listed_excluded_and_included_again(extension, model_files, tmp_path):
    collection = add_vase_collection(extension)  # the same vases as the session's models
    datasets = addon_module(extension, "core.demo_data")
    assert [o.name for o in sorted(collection.objects, key=lambda o: o.name)] == [
        s.name for s in datasets.make_vases(6, seed=VASE_SEED, resolution=VASE_RESOLUTION)]
    _model_with_an_outlier(extension, model_files, tmp_path, "vase_002")
    calls = _draw_all(["SHAPEGEN_PT_correspondence"])
    assert ("label", f"vase_002: {REASON}") in calls
    assert ("operator", "shapegen.exclude_outliers") in calls
    assert ("operator", "shapegen.include_excluded") not in calls

    before = {o.name: (o.hide_viewport, o.hide_get(), tuple(o.matrix_world.col[3])) for o in collection.objects}
    assert bpy.ops.shapegen.exclude_outliers(refit=False) == {"FINISHED"}
    assert list(collection["shapegen_excluded"]) == ["vase_002"]
    after = {o.name: (o.hide_viewport, o.hide_get(), tuple(o.matrix_world.col[3])) for o in collection.objects}
    assert after == before  # the artist's objects are neither moved nor hidden
    calls = _draw_all(["SHAPEGEN_PT_correspondence"])
    assert ("label", "Left out of training: vase_002") in calls
    assert ("operator", "shapegen.include_excluded") in calls
    assert ("operator", "shapegen.exclude_outliers") not in calls

    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    prepared = bpy.data.collections["vases Prepared"]
    sources = sorted(o["shapegen_source"] for o in prepared.objects if "shapegen_source" in o)
    assert sources == ["vase_000", "vase_001", "vase_003", "vase_004", "vase_005"]

    assert bpy.ops.shapegen.include_excluded() == {"FINISHED"}
    assert "shapegen_excluded" not in collection
    assert not bpy.ops.shapegen.include_excluded.poll()
    assert ("operator", "shapegen.include_excluded") not in _draw_all(["SHAPEGEN_PT_correspondence"])


def test_exclude_outliers_and_refit_fits_without_them(extension, model_files, tmp_path):
    collection = add_vase_collection(extension)
    _model_with_an_outlier(extension, model_files, tmp_path, "vase_004")
    settings = bpy.context.scene.shapegen
    settings.fit.model = "ppca"
    assert bpy.ops.shapegen.fit.poll()
    bpy.ops.shapegen.exclude_outliers(refit=True, wait=True, extra_settings=fast_fit_json())
    assert list(collection["shapegen_excluded"]) == ["vase_004"]
    assert settings.job_state == "DONE", settings.job_message
    model = addon_module(extension, "shapegen_addon.store").require_model(bpy.context.scene)
    assert "vase_004" not in model.names and len(model.names) == 5
    assert not any("vase_004" in line for kind, line in _draw_all(["SHAPEGEN_PT_correspondence"])
                   if kind == "label" and "outlier" in line)


def test_find_correspondences_reports_reasons_and_skips_excluded_shapes(extension):
    collection = add_vase_collection(extension)
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    prepared = bpy.data.collections["vases Prepared"]
    collection["shapegen_excluded"] = ["vase_001"]
    assert bpy.ops.shapegen.find_correspondences(wait=True, extra_settings='{"groupwise_rounds": 0}') == {"FINISHED"}
    tagged = {o["shapegen_source"]: o for o in prepared.objects if "shapegen_correspondence" in o}
    assert sorted(tagged) == ["vase_000", "vase_002", "vase_003", "vase_004", "vase_005"]
    assert all(o["shapegen_correspondence_outlier"] == "" for o in tagged.values())  # a clean collection
    tagged["vase_003"]["shapegen_correspondence_outlier"] = REASON  # as Find Correspondences records one
    calls = _draw_all(["SHAPEGEN_PT_correspondence"])
    assert ("label", f"vase_003: {REASON}") in calls
    assert bpy.ops.shapegen.exclude_outliers(refit=False) == {"FINISHED"}
    assert list(collection["shapegen_excluded"]) == ["vase_001", "vase_003"]
