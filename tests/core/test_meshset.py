"""Many meshes in a few arrays (core/meshes/meshset.py): round trip, offset checks, hand-off file."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.demo_data import make_vases
from shapegen_core.base.errors import ModelFileError
from shapegen_core.meshes.meshset import load_mesh_set, pack, save_mesh_set, unpack


def test_pack_unpack_round_trip_keeps_every_mesh():
    meshes = [s.mesh for s in make_vases(3, seed=0, resolution=(8, 10))]
    arrays = pack([m.vertices for m in meshes], [m.faces for m in meshes], prefix="mesh_")
    back = unpack(arrays, [m.name for m in meshes], "test", prefix="mesh_")
    for a, b in zip(meshes, back):
        assert a.name == b.name
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)


def test_offsets_that_do_not_match_the_data_are_refused():
    meshes = [s.mesh for s in make_vases(2, seed=0, resolution=(8, 10))]
    arrays = pack([m.vertices for m in meshes], [m.faces for m in meshes])
    with pytest.raises(ModelFileError, match="src: vertex offsets do not match the 3 shapes"):
        unpack(arrays, ["a", "b", "c"], "src")
    arrays["face_offsets"] = arrays["face_offsets"][::-1].copy()
    with pytest.raises(ModelFileError, match="src: face offsets"):
        unpack(arrays, ["a", "b"], "src")


def test_hand_off_file_drops_degenerate_triangles_and_names_a_bad_mesh(tmp_path):
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    good = np.array([[0, 1, 2], [0, 2, 3], [0, 0, 1]])  # the last triangle is degenerate
    save_mesh_set(tmp_path / "m.npz", ["good", "broken"], [v, v], [good, good + 7], compress=False)
    with pytest.raises(ModelFileError, match="m.npz: mesh 'broken' is invalid.*out of range"):
        load_mesh_set(tmp_path / "m.npz")
    save_mesh_set(tmp_path / "ok.npz", ["good", "again"], [v, v], [good, good])
    meshes = load_mesh_set(tmp_path / "ok.npz")
    assert [m.n_faces for m in meshes] == [2, 2]
    assert meshes[0].report.degenerate_faces_dropped == 1
