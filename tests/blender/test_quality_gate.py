"""The quality gate in Blender: Sample refuses an exploded mesh, says so in its message and
records it on the sample, and never adds a sample that still fails once the run's draws
are spent; Explore keeps the gate's reasons on the live object and the panel shows them."""

from __future__ import annotations

import bpy
import numpy as np
import pytest
from conftest import addon_module, load_model, vertices
from test_panels import _draw_all


@pytest.fixture
def store(extension):
    return addon_module(extension, "shapegen_addon.store")


def test_sample_gate_rejects_an_exploded_mesh_and_reports_it(extension, model_files, store, capfd):
    load_model("ppca", model_files)
    model = store.get_model(bpy.context.scene)
    real = model.mesh_from_landmarks
    templates = []

    def exploding(landmarks, template=None, **options):
        mesh = real(landmarks, template=template, **options)
        templates.append(template)
        if len(templates) == 1:  # the first mesh: a flat disc five times the class's size (a broken mug sample)
            return mesh.with_vertices(mesh.vertices * np.array([5.0, 5.0, 0.05]))
        return mesh

    model.mesh_from_landmarks = exploding
    capfd.readouterr()
    try:
        assert bpy.ops.shapegen.sample(count=3, seed=4) == {"FINISHED"}
    finally:
        del model.mesh_from_landmarks
    out = capfd.readouterr().out
    assert "quality gate: 1 of 3 first meshes failed (edge stretch 1, extent 1); 1 passed on another template, " \
           "0 meshed stiffer, 0 redrawn" in out
    samples = sorted(bpy.data.collections["ShapeGen Samples"].objects, key=lambda o: o["shapegen_seed"])
    assert [o["shapegen_seed"] for o in samples] == [4, 5, 6]
    refused = [o for o in samples if "shapegen_rejected" in o]
    assert refused == [samples[0]]
    record = list(samples[0]["shapegen_rejected"])
    assert len(record) == 1 and record[0].startswith(f"seed 4 on {templates[0]}: ") and "extent: " in record[0]
    assert samples[0]["shapegen_template"] != templates[0]  # meshed on the next-nearest template
    assert all("shapegen_quality" not in o and "shapegen_stiffness" not in o for o in samples)
    largest = max(np.ptp(m.vertices, axis=0).max() for m in model.meshes)
    assert all(np.ptp(vertices(o), axis=0).max() < 1.5 * largest for o in samples)


def _explode_draws(extension, model, monkeypatch, broken):
    """Every mesh of a draw whose seed satisfies `broken(seed)` comes out a flat disc five
    times the class's size (the real gate refuses it on extent); other draws mesh as usual."""
    sampling = addon_module(extension, "core.generate.sampling")
    draw, real, seeds = sampling._draw, model.mesh_from_landmarks, []

    def recording(model, seed):
        seeds.append(seed)
        return draw(model, seed)

    def exploding(landmarks, template=None, **options):
        mesh = real(landmarks, template=template, **options)
        return mesh.with_vertices(mesh.vertices * np.array([5.0, 5.0, 0.05])) if broken(seeds[-1]) else mesh

    monkeypatch.setattr(sampling, "_draw", recording)
    monkeypatch.setattr(model, "mesh_from_landmarks", exploding, raising=False)


def test_sample_adds_only_passing_shapes_and_reports_the_failing_ones(extension, model_files, store, monkeypatch,
                                                                      capfd):
    """Sample 1 of 3 (seed 5, redraws 5 + 3r) explodes on every draw: it was added with
    its reasons in shapegen_quality; now it is not added and the report says why."""
    load_model("ppca", model_files)
    model = store.get_model(bpy.context.scene)
    _explode_draws(extension, model, monkeypatch, lambda seed: (seed - 5) % 3 == 0)
    capfd.readouterr()
    assert bpy.ops.shapegen.sample(count=3, seed=4) == {"FINISHED"}
    out = capfd.readouterr().out
    assert "Sampled 2 shape(s) from " in out
    assert "2 of 3 samples passed the quality gate within the budget of 63 draws; 1 still fail (commonest reasons " \
           "over their " in out and "extent " in out and "the failing ones were not added" in out
    samples = sorted(bpy.data.collections["ShapeGen Samples"].objects, key=lambda o: o["shapegen_seed"])
    assert [o["shapegen_seed"] for o in samples] == [4, 6]
    assert all("shapegen_quality" not in o for o in samples)
    largest = max(np.ptp(m.vertices, axis=0).max() for m in model.meshes)
    assert all(np.ptp(vertices(o), axis=0).max() < 1.5 * largest for o in samples)


def test_sample_adds_nothing_when_no_shape_passes(extension, model_files, store, monkeypatch):
    load_model("ppca", model_files)
    model = store.get_model(bpy.context.scene)
    before = set(bpy.data.objects)
    _explode_draws(extension, model, monkeypatch, lambda seed: True)
    with pytest.raises(RuntimeError, match=r"0 of 2 samples passed the quality gate within the budget of 42 draws; "
                       r"2 still fail \(commonest reasons over their \d+ refused meshes: .*extent .*\); none added"):
        bpy.ops.shapegen.sample(count=2, seed=0)
    assert set(bpy.data.objects) == before and "ShapeGen Samples" not in bpy.data.collections


def test_explore_keeps_the_gate_warning_on_the_live_object_and_the_panel_shows_it(extension, model_files, store,
                                                                                    monkeypatch, capfd):
    load_model("ppca", model_files)
    assert bpy.ops.shapegen.explore() == {"FINISHED"}
    scene = bpy.context.scene
    live = scene.shapegen.live_object
    assert live["shapegen_quality"] == ""
    assert not any(text.startswith("This shape fails") for kind, text in _draw_all(["SHAPEGEN_PT_explore"]))

    latent = addon_module(extension, "shapegen_addon.latent")
    quality = addon_module(extension, "core.generate.quality")
    model = store.get_model(scene)
    # a gate that finds every shape of the class five times too large: the live shape "exploded"
    shrunk = quality.QualityGate(model.meshes, quality.training_extents(model.meshes) / 5.0)
    monkeypatch.setattr(latent, "quality_gate", lambda model, settings: shrunk)
    scene.shapegen.latents[0].value = 1.0  # a slider drag: checked once the drag pauses (a timer)
    assert live["shapegen_quality"] == ""
    assert latent.live_quality(scene).reasons[0].startswith("extent: ")  # what the timer runs
    assert live["shapegen_quality"].startswith("extent: ")
    calls = _draw_all(["SHAPEGEN_PT_explore"])
    assert ("label", "This shape fails the quality gate:") in calls
    assert ("label", live["shapegen_quality"]) in calls
    capfd.readouterr()
    assert bpy.ops.shapegen.explore_snap() == {"FINISHED"}
    assert "This shape fails the quality gate: extent: " in capfd.readouterr().out

    monkeypatch.undo()
    assert bpy.ops.shapegen.explore_reset() == {"FINISHED"}
    assert live["shapegen_quality"] == ""
    assert latent.live_quality(scene).ok
