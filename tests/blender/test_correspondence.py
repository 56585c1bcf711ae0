"""Find Correspondences on a prepared collection, through the installed extension."""

from __future__ import annotations

import importlib

import bpy
import numpy as np
import pytest
import trimesh


@pytest.fixture
def prepared(extension, tmp_path):
    datasets = importlib.import_module(f"{extension}.core.demo_data")
    folder = tmp_path / "vases"
    folder.mkdir()
    for shape in datasets.make_vases(4, seed=7, resolution=(14, 18)):
        trimesh.Trimesh(shape.mesh.vertices, shape.mesh.faces, process=False).export(folder / f"{shape.name}.obj")
    bpy.ops.shapegen.import_collection(directory=str(folder))
    bpy.context.scene.shapegen.prepare.n_landmarks = 80
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    return bpy.data.collections["vases Prepared"]


def test_find_correspondences_tags_every_prepared_shape_with_index_colours(prepared):
    assert bpy.ops.shapegen.find_correspondences(wait=True, extra_settings='{"groupwise_rounds": 0}') == {"FINISHED"}
    settings = bpy.context.scene.shapegen
    assert settings.job_state == "DONE" and "Corresponded 4 shapes" in settings.job_message
    shapes = [o for o in prepared.objects if "shapegen_correspondence" in o]
    assert len(shapes) == 4
    counts = {len(o["shapegen_correspondence"]) for o in shapes}
    assert len(counts) == 1  # the same landmark count on every shape
    colours = []
    for obj in shapes:
        markers = bpy.data.objects[f"{obj.name} correspondence"]
        assert markers.parent == obj
        attribute = markers.data.color_attributes["landmark_index_colour"]
        values = np.empty(len(attribute.data) * 4, dtype=np.float32)
        attribute.data.foreach_get("color", values)
        colours.append(values.reshape(-1, 4)[::6])  # one colour per landmark (6 marker vertices)
        # the corresponded landmarks lie on this shape's own (object-local) surface
        points = np.asarray(obj["shapegen_correspondence"]).reshape(-1, 3)
        co = np.empty(len(obj.data.vertices) * 3)
        obj.data.vertices.foreach_get("co", co)
        tris = np.array([list(p.vertices) for p in obj.data.polygons])
        surface = trimesh.Trimesh(co.reshape(-1, 3), tris, process=False)
        _, distance, _ = trimesh.proximity.closest_point(surface, points)
        assert distance.max() < 1e-4
    for other in colours[1:]:
        np.testing.assert_array_equal(other, colours[0])  # index i has one colour everywhere
    assert np.ptp(colours[0][:, :3], axis=0).min() > 0.5  # and the colours really vary


def test_find_correspondences_needs_a_prepared_collection(extension):
    collection = bpy.data.collections.new("raw")
    bpy.context.scene.collection.children.link(collection)
    bpy.context.scene.shapegen.source_collection = collection
    assert not bpy.ops.shapegen.find_correspondences.poll()


def test_bad_settings_are_reported_before_any_worker_starts(prepared):
    with pytest.raises(RuntimeError, match="Invalid correspondence settings"):
        bpy.ops.shapegen.find_correspondences(wait=True, extra_settings='{"gamma": -1}')
    assert not any("shapegen_correspondence" in o for o in prepared.objects)


def test_find_correspondences_on_a_named_collection_needs_it_prepared(prepared):
    with pytest.raises(RuntimeError, match="No collection named 'missing'"):
        bpy.ops.shapegen.find_correspondences(collection_name="missing")
    bpy.data.collections.new("raw")
    with pytest.raises(RuntimeError, match="'raw' has no prepared collection"):
        bpy.ops.shapegen.find_correspondences(collection_name="raw")
    assert bpy.context.scene.shapegen.job_state == "DONE"  # Prepare's; no job started


def test_matching_choice_reaches_the_job(prepared, extension, monkeypatch):
    """The panel's Matches choice (Correspondence panel) is passed to the worker's
    CorrespondenceSettings; "closest" (the thesis) is the default."""
    ops = importlib.import_module(f"{extension}.shapegen_addon.ops.correspondence")
    sent = []
    original = ops.BackgroundJob
    monkeypatch.setattr(ops, "BackgroundJob",
                        lambda task, arguments: sent.append(arguments) or original(task, arguments))
    settings = bpy.context.scene.shapegen
    assert settings.correspondence.matching == "closest"
    extra = '{"groupwise_rounds": 0, "max_iterations": 3}'
    assert bpy.ops.shapegen.find_correspondences(wait=True, extra_settings=extra) == {"FINISHED"}
    settings.correspondence.matching = "features"
    assert bpy.ops.shapegen.find_correspondences(wait=True, extra_settings=extra) == {"FINISHED"}
    assert settings.job_state == "DONE"
    assert [arguments["settings"]["matching"] for arguments in sent] == ["closest", "features"]
    assert sent[1]["settings"]["max_iterations"] == 3
    assert settings.fit_options()["correspondence"]["matching"] == "features"
