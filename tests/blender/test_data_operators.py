"""Data section operators, driven through the installed extension on bpy 5.0.1:
Import Training Collection (Blender's own importers) and Prepare."""

from __future__ import annotations

import importlib
import json
import time

import bpy
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from conftest import addon_module


@pytest.fixture
def datasets(extension):
    return importlib.import_module(f"{extension}.core.demo_data")


@pytest.fixture
def vase_folder(tmp_path, datasets):
    """Four procedural vases, one per file format Blender (or the core reader) imports."""
    shapes = datasets.make_vases(4, seed=3, resolution=(16, 24))
    folder = tmp_path / "vases"
    folder.mkdir()
    for shape, fmt in zip(shapes, ("obj", "ply", "off", "obj")):
        trimesh.Trimesh(shape.mesh.vertices, shape.mesh.faces, process=False).export(folder / f"{shape.name}.{fmt}")
    return folder, shapes


def _vertices(obj) -> np.ndarray:
    co = np.empty(len(obj.data.vertices) * 3)
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def test_import_makes_one_object_per_file_with_vertex_order_kept(vase_folder):
    folder, shapes = vase_folder
    assert bpy.ops.shapegen.import_collection(directory=str(folder)) == {"FINISHED"}
    collection = bpy.context.scene.shapegen.source_collection
    assert collection is not None and collection.name == "vases"
    assert sorted(o.name for o in collection.objects) == sorted(s.name for s in shapes)
    for shape in shapes:
        obj = collection.objects[shape.name]
        assert obj.type == "MESH"
        np.testing.assert_allclose(_vertices(obj), shape.mesh.vertices, atol=1e-5)  # float32 in Blender
        assert len(obj.data.polygons) == shape.mesh.n_faces


def test_import_of_an_off_file_with_text_after_its_data(vase_folder):
    """Text after an OFF file's declared lines (PSB Vase 361 ends with its exporter's
    settings) is ignored, on the numpy Blender 4.2-5.0 ship (1.26) as on numpy 2.5, where
    the core once crashed in the operator on `np.fromstring`."""
    folder, shapes = vase_folder
    (off,) = folder.glob("*.off")
    off.write_text(off.read_text() + "\nexported by SomeTool 2.1\nunits mm scale 1.0\n")
    assert bpy.ops.shapegen.import_collection(directory=str(folder)) == {"FINISHED"}
    obj = bpy.context.scene.shapegen.source_collection.objects[off.stem]
    shape = next(s for s in shapes if s.name == off.stem)
    np.testing.assert_allclose(_vertices(obj), shape.mesh.vertices, atol=1e-5)


def test_import_of_folder_without_meshes_is_a_clear_error(tmp_path):
    (tmp_path / "notes.txt").write_text("not a mesh")
    with pytest.raises(RuntimeError, match="no mesh files"):
        bpy.ops.shapegen.import_collection(directory=str(tmp_path))
    assert len(bpy.data.collections) == 0


def test_import_reports_a_broken_file_by_name_and_keeps_the_rest(vase_folder):
    folder, shapes = vase_folder
    (folder / "broken.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\nnan 1 0\n3 0 1 2\n")
    assert bpy.ops.shapegen.import_collection(directory=str(folder)) == {"FINISHED"}
    collection = bpy.context.scene.shapegen.source_collection
    assert "broken" not in collection.objects
    assert len(collection.objects) == len(shapes)


def test_import_parses_each_file_once_in_the_core_and_leaves_cleaning_to_prepare(extension, vase_folder, monkeypatch):
    """Blender's importer reads the OBJ and PLY files (keeping what they hold); the core only
    checks each for damage, parsing it once and never running intake's costly cleaning,
    which Prepare runs on the object. OFF, which Blender cannot read, is the core's one read."""
    folder, shapes = vase_folder
    io = addon_module(extension, "core.meshes.reading")
    parsed, cleaned = [], []
    parse, clean = io._parsed, io.clean_mesh
    monkeypatch.setattr(io, "_parsed", lambda path, name=None: parsed.append(path.name) or parse(path, name))
    monkeypatch.setattr(io, "clean_mesh", lambda *args, **kwargs: cleaned.append(kwargs["name"]) or clean(*args, **kwargs))
    assert bpy.ops.shapegen.import_collection(directory=str(folder)) == {"FINISHED"}
    assert sorted(parsed) == sorted(p.name for p in folder.iterdir())
    assert cleaned == [p.stem for p in folder.iterdir() if p.suffix == ".off"] == [shapes[2].name]
    assert len(bpy.context.scene.shapegen.source_collection.objects) == len(shapes)


def test_prepare_aligns_scales_and_landmarks_without_touching_originals(vase_folder):
    folder, shapes = vase_folder
    bpy.ops.shapegen.import_collection(directory=str(folder))
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = 150
    source = settings.source_collection
    before = {o.name: _vertices(o).copy() for o in source.objects}
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}

    for obj in source.objects:  # originals untouched
        np.testing.assert_array_equal(_vertices(obj), before[obj.name])
    prepared = bpy.data.collections["vases Prepared"]
    assert prepared["shapegen_prepared"]
    shape_objects = [o for o in prepared.objects if "shapegen_landmarks" in o]
    assert len(shape_objects) == len(shapes)
    variances = []
    for obj in shape_objects:
        landmarks = np.asarray(obj["shapegen_landmarks"]).reshape(-1, 3)
        assert abs(len(landmarks) - 150) <= 0.02 * 150
        local = _vertices(obj)
        assert local[:, 2].min() == pytest.approx(0.0, abs=1e-5)  # floor at z = 0
        # landmarks lie on the prepared surface
        surface = trimesh.Trimesh(local, np.array([p.vertices[:] for p in obj.data.polygons]), process=False)
        _, distance, _ = trimesh.proximity.closest_point(surface, landmarks)
        assert distance.max() < 1e-4
        # the stored transform maps them back onto the user's original object
        transform = np.asarray(obj["shapegen_transform"]).reshape(4, 4)
        back = (landmarks - transform[:3, 3]) @ np.linalg.inv(transform[:3, :3]).T
        original = source.objects[obj["shapegen_source"]]
        tree = cKDTree(_vertices(original))
        assert tree.query(back)[0].max() < 0.2 * np.ptp(_vertices(original), axis=0).max()
        markers = [c for c in obj.children if c.name.endswith("landmarks")]
        assert len(markers) == 1 and len(markers[0].data.vertices) == 6 * len(landmarks)
        variances.append(np.trace(np.cov(landmarks.T)))
    # equal-variance scaling: landmark spreads agree closely (landmarks are surface samples)
    assert np.ptp(variances) / np.mean(variances) < 0.1


def test_prepare_skips_non_mesh_objects_and_refuses_empty_or_single(vase_folder):
    folder, _ = vase_folder
    bpy.ops.shapegen.import_collection(directory=str(folder))
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = 60
    source = settings.source_collection
    empty = bpy.data.objects.new("an empty", None)
    source.objects.link(empty)
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}  # skipped with a warning

    lonely = bpy.data.collections.new("lonely")
    bpy.context.scene.collection.children.link(lonely)
    lonely.objects.link(bpy.data.objects.new("only an empty", None))
    settings.source_collection = lonely
    with pytest.raises(RuntimeError, match="no mesh objects"):
        bpy.ops.shapegen.prepare(wait=True)
    lonely.objects.link(source.objects[0])
    with pytest.raises(RuntimeError, match="only one mesh object"):
        bpy.ops.shapegen.prepare(wait=True)


def test_prepare_extra_settings_override_the_panel_and_unknown_ones_are_refused(vase_folder):
    folder, _ = vase_folder
    bpy.ops.shapegen.import_collection(directory=str(folder))
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = 120
    with pytest.raises(RuntimeError, match="Invalid prepare settings: unknown option.*landmarks"):
        bpy.ops.shapegen.prepare(wait=True, extra_settings='{"landmarks": 40}')
    assert settings.job_state == "IDLE"  # refused before any worker started
    assert bpy.ops.shapegen.prepare(wait=True, extra_settings='{"n_landmarks": 40}') == {"FINISHED"}
    prepared = bpy.data.collections["vases Prepared"]
    assert int(json.loads(prepared["shapegen_prepare_settings"])["n_landmarks"]) == 40
    assert all(len(o["shapegen_landmarks"]) <= 3 * 40 for o in prepared.objects if "shapegen_landmarks" in o)


def test_prepare_names_the_object_with_bad_geometry(vase_folder):
    folder, _ = vase_folder
    bpy.ops.shapegen.import_collection(directory=str(folder))
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = 60
    bad = bpy.data.objects.new("no faces", bpy.data.meshes.new("no faces"))
    bad.data.vertices.add(3)
    settings.source_collection.objects.link(bad)
    n_collections = len(bpy.data.collections)
    with pytest.raises(RuntimeError, match="no faces: mesh has no faces"):
        bpy.ops.shapegen.prepare(wait=True)
    assert len(bpy.data.collections) == n_collections  # nothing half-created


@pytest.fixture
def jobs(extension):
    module = addon_module(extension, "shapegen_addon.jobs")
    yield module
    module.MANAGER.kill()  # never leave a worker behind


def _pump(jobs, timeout=120.0):
    """Poll like the UI timer (timers never fire in the bpy module) until the job ends."""
    deadline = time.monotonic() + timeout
    statuses = []
    while time.monotonic() < deadline:
        statuses.append(jobs.poll_job())
        if statuses[-1] is not None and statuses[-1].finished and not jobs.MANAGER.running:
            return statuses
        time.sleep(0.02)
    raise AssertionError(f"timed out; last status {statuses[-1] if statuses else None}")


def test_prepare_runs_in_a_worker_and_the_scene_changes_only_when_it_ends(vase_folder, jobs):
    folder, shapes = vase_folder
    bpy.ops.shapegen.import_collection(directory=str(folder))
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = 120
    n_collections = len(bpy.data.collections)
    assert bpy.ops.shapegen.prepare() == {"FINISHED"}  # returns at once: the worker runs
    assert jobs.MANAGER.running and settings.job_state == "RUNNING"
    assert len(bpy.data.collections) == n_collections
    assert not bpy.ops.shapegen.prepare.poll() and not bpy.ops.shapegen.fit.poll()  # one job at a time
    statuses = _pump(jobs)
    assert statuses[-1].state == "done" and settings.job_state == "DONE"
    assert any(0 < s.fraction < 1 for s in statuses if s is not None)  # progress came through
    assert f"Prepared {len(shapes)} shapes into 'vases Prepared'" in settings.job_message
    prepared = bpy.data.collections["vases Prepared"]
    assert len([o for o in prepared.objects if "shapegen_landmarks" in o]) == len(shapes)


def test_cancelling_or_deleting_a_source_while_preparing_creates_nothing(vase_folder, jobs):
    folder, _ = vase_folder
    bpy.ops.shapegen.import_collection(directory=str(folder))
    settings = bpy.context.scene.shapegen
    settings.prepare.n_landmarks = 120
    n_collections = len(bpy.data.collections)

    assert bpy.ops.shapegen.prepare() == {"FINISHED"}
    assert bpy.ops.shapegen.fit_cancel() == {"FINISHED"}
    assert _pump(jobs)[-1].state == "cancelled"
    assert settings.job_state == "CANCELLED" and "nothing was created" in settings.job_message
    assert len(bpy.data.collections) == n_collections

    assert bpy.ops.shapegen.prepare() == {"FINISHED"}
    victim = sorted(o.name for o in settings.source_collection.objects)[1]
    bpy.data.objects.remove(bpy.data.objects[victim])
    assert _pump(jobs)[-1].state == "done"  # the worker finished; the result is refused
    assert settings.job_state == "FAILED" and victim in settings.job_message
    assert "nothing was created" in settings.job_message
    assert len(bpy.data.collections) == n_collections


def test_operators_push_undo_steps():
    # headless bpy has no window, so ed.undo cannot run here (its poll fails); the
    # operators declare UNDO so Blender records a step for each in the UI.
    for name in ("import_collection", "prepare"):
        op = getattr(bpy.types, f"SHAPEGEN_OT_{name}")
        assert "UNDO" in op.bl_options


def test_prepare_says_triangulated_once_for_the_whole_collection(jobs):
    collection = bpy.data.collections.new("boxes")
    bpy.context.scene.collection.children.link(collection)
    for i, size in enumerate((1.0, 1.3, 0.8)):
        bpy.ops.mesh.primitive_cube_add(size=size)
        cube = bpy.context.active_object
        cube.scale.z = 1.0 + 0.3 * i
        for owner in list(cube.users_collection):
            owner.objects.unlink(cube)
        collection.objects.link(cube)
    settings = bpy.context.scene.shapegen
    settings.source_collection, settings.prepare.n_landmarks = collection, 60
    assert bpy.ops.shapegen.prepare(wait=True) == {"FINISHED"}
    assert settings.job_message.lower().count("triangulated") == 1
    assert "Triangulated 18 polygon(s) of 3 object(s) into 36 triangles" in settings.job_message
