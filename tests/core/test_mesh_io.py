"""Mesh type and file reading: vertex order, triangulation, degenerate faces, normals,
areas, area-weighted sampling, and a corpus of bad inputs with their own messages.
(Welding and winding on intake: test_intake.py.)"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from shapegen_core.base.errors import CollectionError, MeshError, MeshFileError
from shapegen_core.meshes.reading import read_folder, read_mesh
from shapegen_core.meshes.writing import write_mesh
from shapegen_core.meshes.mesh import Mesh

from conftest import random_mesh, random_surface


# ---------------------------------------------------------------------------- vertex order
@pytest.mark.parametrize("suffix", ["obj", "ply", "off", "glb"])
def test_vertex_and_face_order_kept(tmp_path, rng, suffix):
    vertices, faces = random_surface(rng)
    # written by trimesh itself (an independent writer), read back through read_mesh
    path = tmp_path / f"shape.{suffix}"
    trimesh.Trimesh(vertices, faces, process=False).export(str(path))
    mesh = read_mesh(path)
    assert mesh.name == "shape"
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int32  # int32: half the memory of dense meshes
    assert mesh.vertices.shape == vertices.shape  # nothing merged, nothing dropped
    # PLY/GLB store float32, OBJ/OFF print ~8-10 significant digits
    np.testing.assert_allclose(mesh.vertices, vertices, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, faces)


def test_stl_corners_are_welded_and_map_back_to_the_file(tmp_path, rng):
    """STL has no shared vertices (corner j of triangle k is the file's vertex 3k + j):
    read_mesh welds them into one connected surface and report.vertex_map says which mesh
    vertex each file corner became."""
    vertices, faces = random_surface(rng)
    path = tmp_path / "shape.stl"
    trimesh.Trimesh(vertices, faces, process=False).export(str(path))
    mesh = read_mesh(path)
    assert mesh.n_vertices == len(vertices) and mesh.n_faces == len(faces)
    assert mesh.report.vertices_welded == 3 * len(faces) - len(vertices)
    corners = vertices[faces].reshape(-1, 3)  # the file's vertex list
    vertex_map = mesh.report.vertex_map
    assert vertex_map.shape == (3 * len(faces),)
    np.testing.assert_allclose(mesh.vertices[vertex_map], corners, atol=1e-6)  # STL stores float32
    np.testing.assert_array_equal(mesh.faces, vertex_map.reshape(-1, 3))  # face k = triangle k, winding kept
    assert mesh.is_closed() and trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).body_count == 1
    assert "duplicate vertices welded" in mesh.report.summary()


def test_obj_with_uv_normals_materials_and_groups_keeps_vertex_list(tmp_path, rng):
    """Ordinary exports: per-corner vt/vn indices that differ from v, two materials, two
    objects. trimesh alone would split / repeat vertices; read_mesh must not."""
    vertices, faces = random_surface(rng, subdivisions=0)
    lines = ["mtllib missing.mtl", "o first"]
    lines += [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in vertices]
    lines += [f"vt {u} {v}" for u, v in rng.random((7, 2))]
    lines += ["vn 0 0 1", "vn 0 1 0", "vn 1 0 0"]
    for k, face in enumerate(faces):
        if k == 8:
            lines += ["o second", "usemtl red", "s 1"]
        corners = [f"{v + 1}/{(v * 5 + k) % 7 + 1}/{(v + k) % 3 + 1}" for v in face]
        lines.append("f " + " ".join(corners))
    path = tmp_path / "export.obj"
    path.write_text("\n".join(lines) + "\n")
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, vertices)
    np.testing.assert_array_equal(mesh.faces, faces)


def test_unused_vertices_are_kept_in_place(tmp_path):
    path = tmp_path / "stray.obj"
    path.write_text("v 9 9 9\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 2 3 4\n")
    mesh = read_mesh(path)
    assert mesh.n_vertices == 4
    np.testing.assert_array_equal(mesh.faces, [[1, 2, 3]])


# ---------------------------------------------------------------------------- polygons
def test_from_polygons_fan_triangulates_and_counts():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0.5, 1.5, 0], [0, 1, 0], [0, 0, 1]], float)
    mesh = Mesh.from_polygons(vertices, [[0, 1, 2, 3, 4], [0, 1, 5], [1, 2, 5, 0]])
    np.testing.assert_array_equal(
        mesh.faces, [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 1, 5], [1, 2, 5], [1, 5, 0]]
    )
    assert mesh.report.polygons_triangulated == 2
    assert mesh.report.triangles_from_polygons == 5
    assert "2 polygon(s) triangulated into 5 triangles" in mesh.report.summary()
    # area is preserved by the fan: the pentagon's shoelace area
    pentagon = 0.5 * abs(np.cross(vertices[[1, 2, 3, 4]] - vertices[0], vertices[[2, 3, 4, 0]] - vertices[0])[:, 2]).sum()
    assert mesh.face_areas()[:3].sum() == pytest.approx(pentagon, rel=1e-12)


POLYGON_FILES = {
    "obj": "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0.5 1.5 0\nv 0 1 0\nv 0 0 1\n"
           "f 1 2 3 4 5\nf 1 2 6\nf 2 3 6 1\n",
    "off": "OFF\n6 3 0\n0 0 0\n1 0 0\n1 1 0\n0.5 1.5 0\n0 1 0\n0 0 1\n"
           "5 0 1 2 3 4\n3 0 1 5\n4 1 2 5 0\n",
    "ply": "ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\n"
           "property float z\nelement face 3\nproperty list uchar int vertex_indices\nend_header\n"
           "0 0 0\n1 0 0\n1 1 0\n0.5 1.5 0\n0 1 0\n0 0 1\n5 0 1 2 3 4\n3 0 1 5\n4 1 2 5 0\n",
}


@pytest.mark.parametrize("suffix", sorted(POLYGON_FILES))
def test_polygon_faces_are_triangulated_not_an_error(tmp_path, suffix):
    path = tmp_path / f"poly.{suffix}"
    path.write_text(POLYGON_FILES[suffix])
    mesh = read_mesh(path)
    assert mesh.n_vertices == 6
    # pentagon -> 3, triangle -> 1, quad -> 2, of which the quad's second (2 6 1) lies on the
    # triangle's corners (1 2 6): one surface, kept once
    assert mesh.n_faces == 3 + 1 + 2 - 1
    assert mesh.report.twin_faces_dropped == 1
    # the triangulation covers the polygons: pentagon (shoelace 1.25) + quad (holding the triangle)
    quad = Mesh.from_polygons(mesh.vertices, [[1, 2, 5, 0]]).area()
    assert mesh.area() == pytest.approx(1.25 + quad, rel=1e-6)


# ---------------------------------------------------------------------------- degenerate
def test_degenerate_faces_dropped_and_counted():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [0.5, 0, 1e-17]], float)
    faces = [[0, 1, 2], [0, 1, 3], [1, 1, 2], [0, 3, 4], [2, 1, 0]]
    mesh = Mesh.from_polygons(vertices, faces, name="d")
    # collinear (0,1,3), repeated index (1,1,2), flat up to rounding (0,3,4)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [2, 1, 0]])
    assert mesh.report.degenerate_faces_dropped == 3
    assert "3 degenerate face(s) dropped" in mesh.report.summary()


def test_degenerate_faces_in_a_file_are_counted(tmp_path):
    path = tmp_path / "degenerate.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nf 1 2 3\nf 1 2 4\nf 1 1 2\n")
    mesh = read_mesh(path)
    assert mesh.n_faces == 1 and mesh.report.degenerate_faces_dropped == 2


def test_all_faces_degenerate_is_an_error():
    with pytest.raises(MeshError, match="every face is degenerate"):
        Mesh.from_polygons(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float), [[0, 1, 2]], name="line")


# ---------------------------------------------------------------------------- geometry
def test_normals_and_areas_match_trimesh(rng):
    vertices, faces = random_mesh(rng, 60, 120)
    mesh = Mesh(vertices, faces)
    tm = trimesh.Trimesh(vertices, faces, process=False)
    np.testing.assert_allclose(mesh.face_areas(), tm.area_faces, rtol=1e-12)
    assert mesh.area() == pytest.approx(tm.area, rel=1e-12)
    np.testing.assert_allclose(mesh.face_normals(), tm.face_normals, atol=1e-12)
    # area-weighted vertex normals: sum of adjacent (normal * area), normalised
    weighted = tm.faces_sparse @ (tm.face_normals * tm.area_faces[:, None])
    used = np.linalg.norm(weighted, axis=1) > 0
    expected = weighted[used] / np.linalg.norm(weighted[used], axis=1, keepdims=True)
    np.testing.assert_allclose(mesh.vertex_normals()[used], expected, atol=1e-10)
    np.testing.assert_array_equal(mesh.vertex_normals()[~used], 0.0)


def test_closed_forms_on_a_box():
    import trimesh.creation

    box = trimesh.creation.box(extents=(2.0, 3.0, 5.0))
    mesh = Mesh(box.vertices, box.faces)
    assert mesh.area() == pytest.approx(2 * (6 + 10 + 15), rel=1e-12)
    np.testing.assert_allclose(mesh.bounds(), [[-1, -1.5, -2.5], [1, 1.5, 2.5]])
    assert mesh.bbox_diagonal() == pytest.approx(np.sqrt(4 + 9 + 25))
    # outward normals: the face centre lies on the side its normal points to
    centres = mesh.triangles.mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals(), centres) > 0)


def test_area_weighted_sampling_is_uniform(rng):
    """Fraction of samples per face ≈ area fraction (chi-square bound), and points lie
    inside their faces with barycentrics uniform on the triangle (mean 1/3 each)."""
    vertices, faces = random_mesh(rng, 40, 60)
    mesh = Mesh(vertices, faces)
    n = 200_000
    samples = mesh.sample_surface(n, np.random.default_rng(7))
    expected = n * mesh.face_areas() / mesh.area()
    observed = np.bincount(samples.face_index, minlength=mesh.n_faces)
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    dof = mesh.n_faces - 1
    assert chi2 < dof + 5 * np.sqrt(2 * dof), chi2  # ~5 sigma of the chi-square law
    np.testing.assert_allclose(samples.barycentric.sum(axis=1), 1.0, atol=1e-12)
    assert samples.barycentric.min() >= 0.0
    np.testing.assert_allclose(
        samples.points, np.einsum("nk,nkd->nd", samples.barycentric, mesh.triangles[samples.face_index]), atol=1e-12
    )
    np.testing.assert_allclose(samples.barycentric.mean(axis=0), 1 / 3, atol=3e-3)
    # a skewed sampler (plain uniform barycentrics, no sqrt) would put E[b0^2] at 1/3 not 1/6
    np.testing.assert_allclose((samples.barycentric**2).mean(axis=0), 1 / 6, atol=3e-3)


def test_sampling_is_seeded(rng):
    mesh = Mesh(*random_mesh(rng))
    a = mesh.sample_surface(500, np.random.default_rng(3)).points
    b = mesh.sample_surface(500, np.random.default_rng(3)).points
    c = mesh.sample_surface(500, np.random.default_rng(4)).points
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_write_then_read_round_trip(tmp_path, rng):
    mesh = Mesh(*random_surface(rng), name="w")
    path = write_mesh(mesh, tmp_path / "w.obj")
    back = read_mesh(path)
    np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-6)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    assert [p.name for p in tmp_path.iterdir()] == ["w.obj"]  # no temporary left behind


# ---------------------------------------------------------------------------- bad inputs
def test_mesh_validation_messages():
    with pytest.raises(MeshError, match="m: mesh is empty"):
        Mesh(np.empty((0, 3)), np.empty((0, 3), int), name="m")
    with pytest.raises(MeshError, match="m: 1 vertex coordinate row"):
        Mesh(np.array([[0, 0, 0], [np.nan, 0, 0], [0, 1, 0]]), [[0, 1, 2]], name="m")
    with pytest.raises(MeshError, match=r"m: face 1 has vertex index \[0, 1, 3\] out of range"):
        Mesh(np.eye(3), [[0, 1, 2], [0, 1, 3]], name="m")
    with pytest.raises(MeshError, match="m: mesh has no faces"):
        Mesh(np.eye(3), np.empty((0, 3), int), name="m")
    with pytest.raises(MeshError, match="face 0 has 2 vertices"):
        Mesh.from_polygons(np.eye(3), [[0, 1]], name="m")
    assert not Mesh(np.eye(3), [[0, 1, 2]]).vertices.flags.writeable


BAD_FILES = {
    # name: (content, expected message fragment)
    "empty.obj": ("", "file is empty"),
    "nan.obj": ("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "vertex 0 has a NaN or infinite coordinate"),
    "nan.off": ("OFF\n3 1 0\n0 0 0\n1 inf 0\n0 1 0\n3 0 1 2\n", "vertex 1 has a NaN or infinite coordinate"),
    "range.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "a face refers to a vertex that does not exist"),
    "range.off": ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "face 0 has vertex index [0, 1, 7] out of range [0, 3)"),
    "notamesh.obj": ("hello, this is a text file\n", "contains no mesh geometry"),
    "image.ply": (b"\x89PNG\r\n\x1a\n" + bytes(range(256)), "not a readable PLY mesh"),
    "random.glb": (bytes(range(256)) * 2, "not a readable GLB mesh"),
    "points.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "has vertices but no faces"),
    "notes.txt": ("a mesh? no\n", "unsupported file type '.txt'"),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_bad_file_gives_its_own_message_naming_the_file(tmp_path, name):
    content, fragment = BAD_FILES[name]
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(MeshFileError) as info:
        read_mesh(path)
    message = str(info.value)
    assert message.startswith(f"{path}: "), message
    assert fragment in message, message
    assert "\n" not in message


def test_off_with_text_after_its_data_reads(tmp_path, rng):
    """Text after the declared vertex and face lines is not the mesh's (PSB Vase 361 ends
    with the settings of the tool that wrote it): the file reads, on every numpy (numpy 2.3
    and later refuse the half-read `np.fromstring` this check once used)."""
    vertices, faces = random_surface(rng, subdivisions=0)
    path = tmp_path / "tail.off"
    trimesh.Trimesh(vertices, faces, process=False).export(str(path))
    path.write_text(path.read_text() + "\nexported by SomeTool 2.1 (c) 1999\nunits mm scale 1.0\n")
    mesh = read_mesh(path)
    assert mesh.vertices.shape == vertices.shape and len(mesh.faces) == len(faces)


@pytest.mark.parametrize("tail, fragment", [("0.5 0.5 0.5\n", "holds 33 lines of data"),
                                            ("3 0 1 2\nnot 1 2\n", "holds 33 lines of data")])
def test_off_with_more_numbers_than_declared_is_refused(tmp_path, rng, tail, fragment):
    """Numbers after the declared lines are data the header does not count: refused, named."""
    vertices, faces = random_surface(rng, subdivisions=0)
    path = tmp_path / "extra.off"
    trimesh.Trimesh(vertices, faces, process=False).export(str(path))
    path.write_text(path.read_text().rstrip("\n") + "\n" + tail)
    with pytest.raises(MeshFileError, match=fragment):
        read_mesh(path)


def test_ascii_ply_with_a_word_among_its_numbers_is_refused(tmp_path, rng):
    vertices, faces = random_surface(rng, subdivisions=0)
    path = tmp_path / "word.ply"
    trimesh.Trimesh(vertices, faces, process=False).export(str(path), encoding="ascii")
    header, body = path.read_text().split("end_header\n")
    lines = body.splitlines()
    lines[3] = lines[3].split(" ", 1)[0] + " oops " + lines[3].split(" ", 2)[2]
    path.write_text(header + "end_header\n" + "\n".join(lines) + "\n")
    with pytest.raises(MeshFileError, match="holds a value that is not a number"):
        read_mesh(path)


def test_missing_file(tmp_path):
    with pytest.raises(MeshFileError, match="no such file"):
        read_mesh(tmp_path / "gone.obj")


def test_bad_messages_are_distinct(tmp_path):
    messages = set()
    for name, (content, _) in BAD_FILES.items():
        path = tmp_path / name
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
        with pytest.raises(MeshFileError) as info:
            read_mesh(path)
        messages.add(str(info.value).split(": ", 1)[1].split(" (")[0])
    assert len(messages) >= 8  # each class of problem has its own wording


def _write_good(folder, names, rng):
    for name in names:
        write_mesh(Mesh(*random_surface(rng, subdivisions=0)), folder / name)


def test_folder_reads_all_sorted_and_ignores_other_files(tmp_path, rng):
    _write_good(tmp_path, ["b.obj", "a.ply", "c.off"], rng)
    (tmp_path / "readme.txt").write_text("not a mesh")
    (tmp_path / "sub").mkdir()
    meshes = read_folder(tmp_path)
    assert [m.name for m in meshes] == ["a", "b", "c"]


def test_folder_with_one_mesh(tmp_path, rng):
    _write_good(tmp_path, ["only.obj"], rng)
    with pytest.raises(CollectionError) as info:
        read_folder(tmp_path)
    message = str(info.value)
    assert str(tmp_path) in message and "at least 2 meshes" in message and "only.obj" in message


def test_folder_with_none(tmp_path):
    (tmp_path / "readme.txt").write_text("nothing here")
    with pytest.raises(CollectionError, match="no mesh files found"):
        read_folder(tmp_path)


def test_not_a_folder(tmp_path):
    with pytest.raises(CollectionError, match="not a folder"):
        read_folder(tmp_path / "missing")


def test_folder_with_one_bad_file_names_it_in_one_line(tmp_path, rng):
    _write_good(tmp_path, ["a.obj", "b.obj"], rng)
    (tmp_path / "c.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(MeshFileError) as info:
        read_folder(tmp_path)
    message = str(info.value)
    assert message.startswith(f"{tmp_path / 'c.obj'}: a face refers to a vertex that does not exist")
    assert "(1 of 3 files" in message and "\n" not in message


def test_folder_with_several_bad_files_names_each(tmp_path, rng):
    _write_good(tmp_path, ["a.obj", "b.obj"], rng)
    (tmp_path / "c.obj").write_text("")
    (tmp_path / "d.off").write_text("OFF\n3 1 0\nnan 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    with pytest.raises(MeshFileError) as info:
        read_folder(tmp_path)
    message = str(info.value)
    assert "2 of 4 files could not be read" in message and "\n" not in message
    assert f"{tmp_path / 'c.obj'}: file is empty" in message
    assert f"{tmp_path / 'd.off'}: vertex 0 has a NaN" in message


def test_folder_with_clashing_names(tmp_path, rng):
    _write_good(tmp_path, ["a.obj", "a.ply"], rng)
    with pytest.raises(CollectionError, match="share the name"):
        read_folder(tmp_path)


def test_fast_obj_writer_round_trips_through_trimesh_with_vertex_order(tmp_path):
    """writing.ObjWriter / obj_bytes (used for mass generation) read back identically."""
    import trimesh as _trimesh

    from shapegen_core.demo_data import make_vases
    from shapegen_core.meshes.writing import ObjWriter, write_mesh
    from shapegen_core.meshes.reading import read_mesh

    mesh = make_vases(1, seed=3, resolution=(12, 14))[0].mesh
    write_mesh(mesh, tmp_path / "a.obj")
    writer = ObjWriter(mesh.faces)
    moved = mesh.vertices * 1.5 + 0.25
    writer.write(moved, tmp_path / "b.obj")
    a, b = read_mesh(tmp_path / "a.obj"), read_mesh(tmp_path / "b.obj")
    np.testing.assert_allclose(a.vertices, mesh.vertices, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(b.vertices, moved, rtol=1e-7, atol=1e-9)
    np.testing.assert_array_equal(a.faces, mesh.faces)
    np.testing.assert_array_equal(b.faces, mesh.faces)
    other = _trimesh.load(tmp_path / "b.obj", process=False, maintain_order=True)
    assert len(other.vertices) == mesh.n_vertices and len(other.faces) == mesh.n_faces
    assert not list(tmp_path.glob(".*tmp*"))


def test_is_closed_agrees_with_trimesh_watertight():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    closed = Mesh(sphere.vertices, sphere.faces, name="sphere")
    opened = Mesh(sphere.vertices, sphere.faces[1:], name="sphere minus a face")
    assert closed.is_closed() and sphere.is_watertight
    assert not opened.is_closed()
    assert not trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False).is_watertight
