"""Damaged mesh files through Import Training Collection: a representative part
of the core tier's corpus (tests/core/corrupt_corpus.py; every case the core refuses, for
every format) in one folder beside good files. Each damaged file is reported by name in one
line and imported as nothing; the good files are imported; what was in the scene before
is untouched."""

from __future__ import annotations

import sys
from pathlib import Path

import bpy
import numpy as np
import pytest
from conftest import addon_module, vertices

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "core"))
from corrupt_corpus import FORMATS, corrupt_cases, file_bytes  # noqa: E402

#: a few cases per format keep the Blender tier fast (the core tier runs them all)
CASES = ("empty", "truncated_0.5", "truncated_0.9", "utf16", "vertex_nan", "vertex_huge_1e200", "all_scaled_1e200",
         "face_index_out_of_range", "vertex_count_plus_1", "face_count_minus_1", "triangle_count_minus_1",
         "vertex_line_dropped", "accessor_indices_count_minus_1")


@pytest.fixture
def damaged_folder(extension, tmp_path):
    """(folder, names of the damaged files, names of the good files)."""
    datasets = addon_module(extension, "core.demo_data")
    meshes = [s.mesh for s in datasets.make_vases(3, seed=1, resolution=(5, 7))]
    folder = tmp_path / "mixed"
    folder.mkdir()
    damaged, good = [], []
    for file_format, suffix in FORMATS.items():
        for index, mesh in enumerate(meshes[1:]):
            (folder / f"good_{file_format}_{index}{suffix}").write_bytes(
                file_bytes(file_format, mesh.vertices, mesh.faces))
            good.append(f"good_{file_format}_{index}")
        for name, data in corrupt_cases(file_format, meshes[0].vertices, meshes[0].faces):
            if name in CASES:
                (folder / f"{file_format}_{name}{suffix}").write_bytes(data)
                damaged.append(f"{file_format}_{name}")
    return folder, damaged, good


def test_damaged_files_are_reported_by_name_and_the_scene_is_intact(damaged_folder, capfd):
    folder, damaged, good = damaged_folder
    assert len(damaged) >= 6 * len(FORMATS)
    artist = bpy.data.objects.new("artist's cube", bpy.data.meshes.new("artist's cube"))
    artist.data.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    bpy.context.scene.collection.objects.link(artist)
    before = vertices(artist).copy()
    capfd.readouterr()
    assert bpy.ops.shapegen.import_collection(directory=str(folder)) == {"FINISHED"}
    output = capfd.readouterr()
    reports = [line for line in (output.out + output.err).splitlines() if str(folder) in line]
    collection = bpy.context.scene.shapegen.source_collection
    assert sorted(o.name for o in collection.objects) == sorted(good)  # every good file, no damaged one
    assert set(bpy.data.objects) == set(collection.objects) | {artist}  # nothing else left in the file
    np.testing.assert_array_equal(vertices(artist), before)
    for name in damaged:  # one line each, naming the file
        lines = [line for line in reports if f"{folder / name}." in line]
        assert len(lines) == 1, (name, lines)
    assert "Traceback" not in output.out + output.err
