"""Pose reports and Keep Pose in Blender: a vase turned upside down in the
viewport among upright ones is turned back by Prepare, which says so on its prepared copy,
in the message and in the Data panel; with Keep Pose on that object it keeps its pose and
is flagged instead."""

from __future__ import annotations

import math

import bpy
import numpy as np
from conftest import FAST_FIT, add_vase_collection, addon_module, reused_prepared
from test_panels import _draw_all


def _copies(extension) -> dict:
    """{source name: prepared copy} of the newest prepared collection."""
    keys = addon_module(extension, "shapegen_addon.keys")
    prepared = addon_module(extension, "shapegen_addon.prepared")
    newest = max((c for c in bpy.data.collections if c.get(keys.PREPARED_KEY)), key=lambda c: c.name)
    return {o[keys.SOURCE_KEY]: o for o in prepared.prepared_objects(newest)}


def test_upside_down_object_is_turned_and_reported_or_kept_and_flagged(extension):
    keys = addon_module(extension, "shapegen_addon.keys")
    add_vase_collection(extension, n=8, pose=False)
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = 50
    flipped = bpy.data.objects["vase_002"]
    flipped.rotation_euler = (math.pi, 0.0, 0.0)
    bpy.context.view_layer.update()

    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    assert "1 turned (vase_002), 0 flagged" in settings.job_message
    copies = _copies(extension)
    turned = copies["vase_002"]
    assert turned[keys.POSE_CHANGE_KEY].startswith("turned 180° about x: its hollow opens downwards"), \
        turned[keys.POSE_CHANGE_KEY]
    assert turned[keys.POSE_OUTLIER_KEY] == ""
    np.testing.assert_allclose(np.reshape(turned[keys.POSE_ROTATION_KEY], (3, 3)), np.diag([1.0, -1.0, -1.0]),
                               atol=1e-6)
    for name, copy in copies.items():
        if name != "vase_002":
            assert copy[keys.POSE_CHANGE_KEY] == "" and copy[keys.POSE_OUTLIER_KEY] == ""
            np.testing.assert_array_equal(copy[keys.POSE_ROTATION_KEY], np.eye(3).ravel())
    labels = [text for kind, text in _draw_all(["SHAPEGEN_PT_data"]) if kind == "label"]
    assert any(text.startswith("vase_002: turned 180° about x") for text in labels)

    bpy.context.view_layer.objects.active = flipped
    assert bpy.ops.shapegen.toggle_keep_pose() == {"FINISHED"}
    assert flipped[keys.KEEP_POSE_KEY]
    calls = _draw_all(["SHAPEGEN_PT_data"])
    assert ("operator", "shapegen.toggle_keep_pose") in calls
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    assert "0 turned, 1 flagged (vase_002)" in settings.job_message
    kept = _copies(extension)["vase_002"]
    assert kept[keys.POSE_CHANGE_KEY] == ""
    assert kept[keys.POSE_OUTLIER_KEY].startswith("may be upside down: its hollow opens downwards")
    labels = [text for kind, text in _draw_all(["SHAPEGEN_PT_data"]) if kind == "label"]
    assert any(text.startswith("vase_002: pose looks wrong: may be upside down") for text in labels)

    # Fit reuses a Prepare only when it was made with the objects' Keep Pose flags as they are now
    collection = settings.source_collection
    objects = sorted(collection.objects, key=lambda o: o.name)
    assert reused_prepared(extension, collection, objects, settings.fit_options()).name == "vases Prepared.001"
    assert bpy.ops.shapegen.toggle_keep_pose() == {"FINISHED"}
    assert not flipped[keys.KEEP_POSE_KEY]
    assert reused_prepared(extension, collection, objects, settings.fit_options()).name == "vases Prepared"
    bpy.data.collections.remove(bpy.data.collections["vases Prepared"])
    flipped[keys.KEEP_POSE_KEY] = True
    bpy.data.objects["vase_002 prepared.001"][keys.KEEP_POSE_KEY] = False  # as if prepared without the flag
    assert reused_prepared(extension, collection, objects, settings.fit_options()) is None


def test_fit_worker_keeps_the_flagged_poses(extension, tmp_path):
    """task_fit on raw meshes prepares them with keep_pose, like task_prepare."""
    datasets = addon_module(extension, "core.demo_data")
    meshset = addon_module(extension, "core.meshes.meshset")
    worker = addon_module(extension, "core.app.worker")
    shape_model = addon_module(extension, "core.app.shape_model")
    meshes = [s.mesh for s in datasets.make_vases(8, seed=1, resolution=(14, 20), pose=False)]
    meshes[2] = meshes[2].with_vertices(meshes[2].vertices * [1.0, -1.0, -1.0])
    meshset.save_mesh_set(tmp_path / "meshes.npz", [m.name for m in meshes], [m.vertices for m in meshes],
                          [m.faces for m in meshes])
    fast = {name: value for name, value in FAST_FIT.items() if name != "jobs"}  # jobs: an argument of its own
    options = {**fast, "model": "ppca", "latent_dim": 1, "prepare": {"n_landmarks": 50}}
    fitted = []
    for keep in ([False] * 8, [i == 2 for i in range(8)]):
        output = worker.task_fit({"meshes": str(tmp_path / "meshes.npz"), "keep_pose": keep, "settings": options,
                                  "jobs": FAST_FIT["jobs"], "output": str(tmp_path / f"model{len(fitted)}.npz")},
                                 lambda f, stage: None, None)
        fitted.append(shape_model.GenerativeShapeModel.load(output).meshes)
    turned, kept = fitted
    np.testing.assert_allclose(turned[0].vertices, kept[0].vertices, rtol=0, atol=1e-12)
    # turned back upright, or kept upside down: the same vase mirrored in y and z (up to the floor shift)
    flipped = kept[2].vertices * [1.0, -1.0, -1.0]
    np.testing.assert_allclose(turned[2].vertices, flipped - flipped.min(axis=0) + turned[2].vertices.min(axis=0),
                               atol=1e-6 * np.ptp(turned[2].vertices))
