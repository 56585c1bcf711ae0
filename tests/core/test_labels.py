"""Part labels (core/meshes/labels.py): the PSB form read and written, mapped from a file's
polygons onto the mesh the core reads and back onto the faces of a written copy."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.meshes.reading import read_mesh
from shapegen_core.meshes.labels import (LabelFileError, PartLabels, labels_beside, read_label_file, write_label_file,
                                         written_face_labels)

CUBE = """v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
f 1 4 3 2
f 5 6 7 8
f 1 2 6 5
f 2 3 7 6
f 3 4 8 7
f 4 1 5 8
"""


def test_quads_labels_reach_every_triangle_and_come_back_per_quad(tmp_path):
    (tmp_path / "cube.obj").write_text(CUBE)
    (tmp_path / "cube_labels.txt").write_text("bottom\n1\nlid\n2\n\nsides\n3 4 5 6\n")
    mesh = read_mesh(tmp_path / "cube.obj")
    names, part = labels_beside(tmp_path / "cube.obj", mesh)
    assert names == ["bottom", "lid", "sides"] and len(part) == len(mesh.faces) == 12
    z = mesh.vertices[mesh.faces][:, :, 2]
    np.testing.assert_array_equal(part[(z == 0).all(1)], 0)
    np.testing.assert_array_equal(part[(z == 1).all(1)], 1)
    assert np.all(part[~(z == 0).all(1) & ~(z == 1).all(1)] == 2)
    assert mesh.report.layout is not None
    np.testing.assert_array_equal(written_face_labels(mesh, part, "obj"), [0, 1, 2, 2, 2, 2])   # the file's quads
    np.testing.assert_array_equal(written_face_labels(mesh, part, "stl"), [0, 0, 1, 1] + [2] * 8)  # their fans


def test_label_files_round_trip_and_cover_every_face(tmp_path):
    write_label_file(tmp_path / "a_labels.txt", ["x", "y"], np.array([1, 0, -1, 1]))
    assert (tmp_path / "a_labels.txt").read_text() == "x\n2\ny\n1 4\nunlabelled\n3\n"
    names, part = read_label_file(tmp_path / "a_labels.txt", 4)
    assert names == ["x", "y", "unlabelled"] and part.tolist() == [1, 0, 2, 1]


@pytest.mark.parametrize("text, message", [("body\n1 2\nhandle\n", "no face ids"), ("body\n1 x\n", "whole numbers"),
                                           ("body\n1 9\n", "face 9 does not exist"),
                                           ("body\n1 2\nlid\n2\n", "face 2 is in two parts")])
def test_bad_label_files_name_the_file_and_the_problem(tmp_path, text, message):
    (tmp_path / "m_labels.txt").write_text(text)
    with pytest.raises(LabelFileError, match=message) as error:
        read_label_file(tmp_path / "m_labels.txt", 4)
    assert "m_labels.txt" in str(error.value)


def test_merged_labels_share_one_name_list():
    merged = PartLabels.merge([(["body", "lid"], np.array([0, 1, -1])), None, (["lid"], np.array([0, 0]))], [3, 2, 2])
    assert merged.names == ("body", "lid")
    assert [p.tolist() for p in merged.parts] == [[0, 1, -1], [-1, -1], [1, 1]]
    assert PartLabels.merge([None, None], [3, 2]) is None
