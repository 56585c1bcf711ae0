"""Dense meshes kept on disk for a run (core/meshes/spill.py): the main process keeps
handles, not the meshes; the results equal the in-memory path's; the store's folder is
removed after success, error and cancel. Small meshes stand in for dense ones (the
store's size limit and the proxy size are lowered); bench/scale.py measures the real
memory at a million vertices."""

from __future__ import annotations

import pickle
import tempfile
import threading
import tracemalloc

import numpy as np
import pytest
import trimesh

from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
from shapegen_core.correspond import CorrespondenceSettings, correspond
from shapegen_core.demo_data import make_vases
from shapegen_core.base.errors import Cancelled
from shapegen_core.meshes.reading import read_folder
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.app.pipeline import fit_meshes, fit_shape_model
from shapegen_core.meshes.spill import SpillStore, StoredMesh

from conftest import subdivided

#: meshes above this many faces are kept on disk in these tests (the vases below have ~26k)
ABOVE = 5000
SETTINGS = PrepareSettings(n_landmarks=100, align="none")
CORRESPONDENCE = CorrespondenceSettings(proxy_faces=2000)  # shapes above 5000 faces: dense


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """4 vases subdivided to ~26k faces each, as binary PLY files."""
    path = tmp_path_factory.mktemp("dense")
    for mesh in make_vases(4, seed=5, resolution=(26, 32)):
        dense = subdivided(mesh.mesh, 2)
        assert dense.n_faces > ABOVE
        trimesh.Trimesh(dense.vertices, dense.faces, process=False).export(path / f"{mesh.name}.ply",
                                                                            encoding="binary")
    return path


def _mesh_bytes(meshes) -> int:
    return sum(m.vertices.nbytes + m.faces.nbytes for m in meshes)


def _fit(meshes, progress=None):
    prepared = prepare_meshes(meshes, SETTINGS)
    corr = correspond(prepared, CORRESPONDENCE, jobs=1, progress=progress)
    model = fit_shape_model([s.mesh for s in prepared.shapes], corr, FitSettings(prepare=SETTINGS, model="ppca"))
    return prepared, corr, model


@pytest.fixture(scope="module")
def in_memory(folder):
    """The folder read and fitted in memory: (meshes, prepared, correspondence, model, the
    correspondence's progress messages)."""
    memory = read_folder(folder, jobs=1)
    messages = []
    return (memory, *_fit(memory, lambda fraction, message: messages.append(message)), messages)


def test_a_spilled_fit_equals_the_in_memory_fit(folder, in_memory, tmp_path):
    """Read, Prepare, correspondence and the model file of meshes kept on disk give the
    same arrays as the same meshes held in memory; a worker that reads a file keeps it
    in the store itself."""
    memory, prepared, corr, model, _ = in_memory
    with SpillStore(above=ABOVE) as store:
        meshes = read_folder(folder, jobs=2, spill=store)
        assert all(isinstance(m, StoredMesh) for m in meshes)
        for stored, mesh in zip(meshes, memory):
            loaded = stored.load()
            np.testing.assert_array_equal(loaded.vertices, mesh.vertices)
            np.testing.assert_array_equal(loaded.faces, mesh.faces)
            assert loaded.faces.dtype == np.int32 and not loaded.vertices.flags.writeable
        prepared_s, corr_s, model_s = _fit(meshes)
        assert all(isinstance(s.mesh, StoredMesh) for s in prepared_s.shapes)
        for key, value in prepared.to_arrays().items():
            np.testing.assert_array_equal(prepared_s.to_arrays()[key], value, err_msg=key)
        for key, value in corr.to_arrays().items():
            np.testing.assert_array_equal(corr_s.to_arrays()[key], value, err_msg=key)
        model_s.save(tmp_path / "spilled.npz")
        prepared_s.save(tmp_path / "spilled-prepared.npz")
    model.save(tmp_path / "memory.npz")
    back = GenerativeShapeModel.load(tmp_path / "memory.npz")
    back_s = GenerativeShapeModel.load(tmp_path / "spilled.npz")
    for a, b in zip(back.meshes, back_s.meshes):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(back.correspondence.points, back_s.correspondence.points)
    assert not store.folder.exists()


def test_the_main_process_keeps_handles_not_meshes(folder, in_memory):
    """With a store, what this process keeps from reading to the fitted model is names,
    sizes, summaries, proxies and landmarks: less than one mesh of the 4 (without it:
    every mesh, twice from Prepare on)."""
    memory, prepared, _, _, _ = in_memory  # the in-memory fit also imported whatever the stages import on first use
    one_mesh = _mesh_bytes(memory) / len(memory)
    assert len(pickle.dumps(prepared)) > 0.9 * _mesh_bytes(memory)
    with SpillStore(above=ABOVE) as store:
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            meshes = read_folder(folder, jobs=1, spill=store)
            after_read = tracemalloc.get_traced_memory()[0] - before
            prepared = prepare_meshes(meshes, SETTINGS)
            after_prepare = tracemalloc.get_traced_memory()[0] - before
            corr = correspond(prepared, CORRESPONDENCE, jobs=1)
            model = fit_shape_model([s.mesh for s in prepared.shapes], corr,
                                    FitSettings(prepare=SETTINGS, model="ppca"))
            after_fit = tracemalloc.get_traced_memory()[0] - before
        finally:
            tracemalloc.stop()
        assert after_read < 0.3 * one_mesh, (after_read, one_mesh)
        assert after_prepare < 0.5 * one_mesh, (after_prepare, one_mesh)
        assert after_fit < one_mesh, (after_fit, one_mesh)  # the proxies (2000 faces each), landmarks, model
        assert len(pickle.dumps((meshes, prepared, model.meshes))) < 0.5 * one_mesh
        # the registration proxy was built once and kept with its shape
        assert all(len(s.mesh.proxies) >= 1 for s in prepared.shapes)


def test_the_store_is_removed_after_success_error_and_cancel(folder):
    with SpillStore(above=ABOVE) as store:
        meshes = read_folder(folder, jobs=1, spill=store)
        assert len(list(store.folder.iterdir())) == 2 * len(meshes)
    assert not store.folder.exists()

    with pytest.raises(RuntimeError):
        with SpillStore(above=ABOVE) as store:
            read_folder(folder, jobs=1, spill=store)
            raise RuntimeError("a failing step")
    assert not store.folder.exists()

    asked = threading.Event()
    with pytest.raises(Cancelled):
        with SpillStore(above=ABOVE) as store:
            meshes = read_folder(folder, jobs=1, spill=store)

            def progress(fraction, message):
                if "correspondence" in message:
                    asked.set()  # cancel once correspondence has started
            fit_meshes(meshes, FitSettings(prepare=SETTINGS, model="ppca", correspondence=CORRESPONDENCE),
                       progress=progress, should_cancel=asked, jobs=1)
    assert asked.is_set() and not store.folder.exists()
    with pytest.raises(Exception, match="spill store was closed"):
        meshes[0].load()


def test_commands_remove_their_store(folder, tmp_path, monkeypatch):
    """`shapegen prepare` leaves no store behind, whether it succeeds or fails."""
    from shapegen_core.app.cli import main

    spill_parent = tmp_path / "tmp"
    spill_parent.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spill_parent))
    assert main(["prepare", str(folder), "-o", str(tmp_path / "p.npz"), "--landmarks", "100", "--align", "none",
                 "--up", "y"]) == 0
    assert main(["prepare", str(tmp_path / "nothing"), "-o", str(tmp_path / "q.npz")]) == 2
    assert list(spill_parent.iterdir()) == []


def test_correspondence_reuses_the_proxy_prepare_built(folder, in_memory, monkeypatch):
    """A stored shape's registration proxy is built once, by Prepare while the shape is at
    full density; correspondence registers against it without building another, with
    the same landmarks as when it builds the proxy itself (the in-memory fit's
    correspondence: the spilled fit's equals it)."""
    import shapegen_core.preprocess.collection as collection
    from shapegen_core.correspond.proxy import dense_limit

    _, _, built_later, _, built_later_messages = in_memory
    assert sum("proxy of" in m for m in built_later_messages) == len(built_later)
    key = (CORRESPONDENCE.proxy_faces, dense_limit(CORRESPONDENCE))
    with SpillStore(above=ABOVE) as store:
        meshes = read_folder(folder, jobs=1, spill=store)
        monkeypatch.setattr(collection, "REGISTRATION_PROXY", key)  # Prepare builds the proxy these settings use
        prepared = prepare_meshes(meshes, SETTINGS)
        assert all(key in s.mesh.proxies for s in prepared.shapes)
        messages = []
        reused = correspond(prepared, CORRESPONDENCE, jobs=1,
                            progress=lambda fraction, message: messages.append(message))
    assert not any("proxy of" in m for m in messages)
    np.testing.assert_array_equal(reused.points, built_later.points)
