"""Intake (core/meshes/intake.py): triangle soups welded into one connected surface with a map
back to the input's vertices; inside-out, mirrored and inconsistently wound meshes wound
outwards (closed and open), non-orientable parts wound face by face towards their outside;
fast winding numbers against the closed form; and an STL class whose smoothed samples have
no cracks and are written as connected meshes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from shapegen_core.preprocess.collection import PrepareSettings
from shapegen_core.demo_data import make_vases, write_collection
from shapegen_core.generate.deform import enclosed_volume
from shapegen_core.meshes.winding import OPEN_PART_MIN_OUTWARDNESS, outside_sides, outwardness, winding_numbers
from shapegen_core.meshes.intake import WELD_RTOL, clean_mesh, weld_vertices
from shapegen_core.meshes.reading import read_folder, read_mesh
from shapegen_core.meshes.writing import write_mesh
from shapegen_core.meshes.mesh import Mesh
from shapegen_core.meshes.meshset import load_mesh_set, save_mesh_set
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.pipeline import fit_meshes

from conftest import random_surface


@pytest.fixture(scope="module")
def vase():
    return make_vases(1, seed=4, resolution=(14, 18))[0]


def _open_vase(vase) -> Mesh:
    """The vase's base and outer wall only (profile s < 0.58): open at the top, it
    encloses no volume."""
    keep = (vase.vertex_st[vase.mesh.faces][..., 0] < 0.58).all(axis=1)
    return Mesh(vase.mesh.vertices, vase.mesh.faces[keep], name="open")


def _soup(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return vertices[faces].reshape(-1, 3), np.arange(3 * len(faces)).reshape(-1, 3)


# ---------------------------------------------------------------------------- welding
def test_a_clean_mesh_comes_out_unchanged(rng):
    vertices, faces = random_surface(rng)
    mesh = clean_mesh(vertices, faces, name="s")
    np.testing.assert_array_equal(mesh.vertices, vertices)
    np.testing.assert_array_equal(mesh.faces, faces)
    assert mesh.report.summary() == "clean"
    assert mesh.report.vertex_map is None and mesh.report.face_source is None and mesh.report.face_reversed is None


def test_a_soup_is_welded_with_a_map_back_to_its_vertices(vase):
    vertices, faces = _soup(vase.mesh.vertices, vase.mesh.faces)
    mesh = clean_mesh(vertices, faces, name="soup")
    assert mesh.n_vertices == vase.mesh.n_vertices and mesh.n_faces == vase.mesh.n_faces
    assert mesh.report.vertices_welded == len(vertices) - vase.mesh.n_vertices
    np.testing.assert_array_equal(mesh.vertices[mesh.report.vertex_map], vertices)  # each input vertex kept its place
    np.testing.assert_array_equal(mesh.faces, mesh.report.vertex_map[faces])
    # the same surface as the indexed original, one connected closed body
    np.testing.assert_allclose(mesh.face_areas(), vase.mesh.face_areas(), rtol=1e-12)
    assert mesh.is_closed() and trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).body_count == 1
    # welded vertices are numbered by first occurrence
    assert np.all(np.diff(np.maximum.accumulate(mesh.report.vertex_map)) <= 1)


def test_weld_tolerance_is_relative_to_the_diagonal():
    """1e-9 of the diagonal merges float64 rounding noise at any scale; a gap of 1e-6
    of the diagonal (far below a modelled feature, far above rounding) stays open."""
    for scale in (1e-3, 1.0, 1e4):
        base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1]], float) * scale
        diagonal = np.sqrt(3.0) * scale
        near = base[1] + [0.2 * WELD_RTOL * diagonal, 0, 0]
        far = base[2] + [1e-6 * diagonal, 0, 0]
        welded, vertex_map = weld_vertices(np.vstack([base, near, far]))
        np.testing.assert_array_equal(vertex_map, [0, 1, 2, 3, 1, 4])
        np.testing.assert_array_equal(welded[:4], base)


def test_faces_collapsed_by_welding_are_dropped_and_counted():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1e-12]], float)
    mesh = clean_mesh(vertices, [[0, 1, 2], [0, 3, 1], [0, 4, 1], [1, 3, 2], [0, 2, 3]], name="c")
    # face 2 (corner 4 = corner 0 within 1e-9 of the diagonal) collapses; the tetrahedron stays
    assert mesh.n_vertices == 4 and mesh.n_faces == 4
    assert mesh.report.degenerate_faces_dropped == 1
    np.testing.assert_array_equal(mesh.report.face_source, [0, 1, 3, 4])


# ---------------------------------------------------------------------------- winding
def _variants(mesh: Mesh, rng) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    shuffled = rng.random(mesh.n_faces) < 0.4
    return {
        "inside out": (mesh.vertices, mesh.faces[:, ::-1]),
        "shuffled winding": (mesh.vertices, np.where(shuffled[:, None], mesh.faces[:, ::-1], mesh.faces)),
        "shuffled soup": _soup(mesh.vertices, np.where(shuffled[:, None], mesh.faces[:, ::-1], mesh.faces)),
    }


def test_inside_out_and_inconsistent_closed_vases_come_out_like_the_original(vase, rng):
    original = vase.mesh
    assert enclosed_volume(original) > 0 and outwardness(original.vertices, original.faces)[0] > 0
    for kind, (vertices, faces) in _variants(original, rng).items():
        mesh = clean_mesh(vertices, faces, name=kind)
        np.testing.assert_allclose(mesh.face_normals(), original.face_normals(), atol=1e-12, err_msg=kind)
        assert enclosed_volume(mesh) == pytest.approx(enclosed_volume(original), rel=1e-12)
        assert trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).is_winding_consistent
        reversed_faces = mesh.report.face_reversed
        np.testing.assert_array_equal(reversed_faces, np.einsum("ij,ij->i", np.cross(
            vertices[faces][:, 1] - vertices[faces][:, 0], vertices[faces][:, 2] - vertices[faces][:, 0]),
            original.face_normals()) < 0, err_msg=kind)
    inside_out = clean_mesh(original.vertices, original.faces[:, ::-1], name="i")
    assert inside_out.report.parts_turned_outward == 1 and inside_out.report.faces_rewound == 0
    assert "1 inside-out part(s) turned outward" in inside_out.report.summary()
    shuffled = clean_mesh(*_variants(original, rng)["shuffled winding"], name="s")
    assert shuffled.report.faces_rewound == int(shuffled.report.face_reversed.sum()) > 0
    assert "re-wound to agree with their neighbours" in shuffled.report.summary()


def test_a_mirrored_vase_comes_out_outward(vase):
    """A mirror image (x -> -x) with the faces as they were is inside out."""
    mirrored = vase.mesh.vertices * [-1.0, 1.0, 1.0]
    assert enclosed_volume(Mesh(mirrored, vase.mesh.faces)) < 0
    mesh = clean_mesh(mirrored, vase.mesh.faces, name="m")
    assert enclosed_volume(mesh) == pytest.approx(enclosed_volume(vase.mesh), rel=1e-12)
    assert mesh.report.parts_turned_outward == 1
    # a reader that reverses the faces itself (Blender, negative scale) says so; nothing left to turn
    read = clean_mesh(mirrored, vase.mesh.faces[:, [0, 2, 1]], name="m", mirrored=True)
    assert enclosed_volume(read) > 0 and read.report.parts_turned_outward == 0
    assert "mirrored (negative scale): winding reversed" in read.report.summary()


def test_an_open_vase_is_turned_outward_though_it_encloses_nothing(vase, rng):
    """Open at the top there is no volume to take the sign of; the area-weighted test
    Σ A n·(c_f − c) decides, clearly (about 0.8, against 0 for a flat sheet)."""
    original = _open_vase(vase)
    assert not original.is_closed()
    score = outwardness(original.vertices, original.faces)[0]
    assert score > 10 * OPEN_PART_MIN_OUTWARDNESS
    for kind, (vertices, faces) in _variants(original, rng).items():
        mesh = clean_mesh(vertices, faces, name=kind)
        np.testing.assert_allclose(mesh.face_normals(), original.face_normals(), atol=1e-12, err_msg=kind)
        assert outwardness(mesh.vertices, mesh.faces)[0] == pytest.approx(score)
        assert trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).is_winding_consistent
    mirrored = clean_mesh(original.vertices * [1.0, -1.0, 1.0], original.faces, name="m")
    assert outwardness(mirrored.vertices, mirrored.faces)[0] == pytest.approx(score)


def test_each_part_is_turned_on_its_own():
    """Two closed boxes, one inside out: only that one is turned."""
    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(1, 2, 1))
    vertices = np.vstack([a.vertices, b.vertices + [3, 0, 0]])
    faces = np.vstack([a.faces, b.faces[:, ::-1] + len(a.vertices)])
    mesh = clean_mesh(vertices, faces, name="two")
    assert mesh.report.parts_turned_outward == 1
    np.testing.assert_array_equal(mesh.report.face_reversed, np.arange(len(faces)) >= len(a.faces))
    assert enclosed_volume(mesh) == pytest.approx(1.0 + 2.0)


def test_a_flat_sheet_keeps_its_winding_and_says_it_has_no_outside():
    grid = np.stack(np.meshgrid(np.arange(4.0), np.arange(4.0), indexing="ij"), -1).reshape(-1, 2)
    vertices = np.column_stack([grid, np.zeros(len(grid))])
    index = np.arange(16).reshape(4, 4)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    faces = np.vstack([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    for winding in (faces, faces[:, ::-1]):
        mesh = clean_mesh(vertices, winding, name="sheet")
        np.testing.assert_array_equal(mesh.faces, winding)
        assert mesh.report.parts_without_inside == 1
        assert "1 open flat part(s) with no outside: winding kept" in mesh.report.summary()


def _moebius_band(n: int = 12, radius: float = 1.0, width: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """A Möbius band of 2n triangles: no winding makes every pair of neighbours agree."""
    t = 2 * np.pi * np.arange(n) / n
    centre = np.stack([np.cos(t), np.sin(t), np.zeros(n)], 1) * radius
    across = np.stack([np.cos(t / 2) * np.cos(t), np.cos(t / 2) * np.sin(t), np.sin(t / 2)], 1) * width
    vertices = np.vstack([centre + across, centre - across])  # i: one edge, n + i: the other
    faces = []
    for i in range(n):
        j = (i + 1) % n
        top_j, bottom_j = (j, n + j) if j else (n, 0)  # the strip comes back half-twisted
        faces += [[i, n + i, bottom_j], [i, bottom_j, top_j]]
    return vertices, np.array(faces)


def test_a_moebius_band_inside_a_closed_body_reads_and_the_body_stays_outward(vase, rng):
    """The band is wound face by face (neither of its sides is outside: the body's
    inside is all around it) and named; the body around it keeps its outward winding."""
    band_vertices, band_faces = _moebius_band()
    lo, hi = vase.mesh.bounds()
    band_vertices = (lo + hi) / 2 + band_vertices * 0.1 * (hi - lo).min()
    vertices = np.concatenate([vase.mesh.vertices, band_vertices])
    shuffled = np.where((rng.random(len(band_faces)) < 0.5)[:, None], band_faces[:, ::-1], band_faces)
    for body in (vase.mesh.faces, vase.mesh.faces[:, ::-1]):  # as given, and inside out
        mesh = clean_mesh(vertices, np.concatenate([body, shuffled + vase.mesh.n_vertices]), name="banded")
        assert mesh.n_faces == vase.mesh.n_faces + len(band_faces)
        np.testing.assert_allclose(mesh.face_normals()[:vase.mesh.n_faces], vase.mesh.face_normals(), atol=1e-12)
        report = mesh.report
        assert report.unorientable_parts == 1 and report.unorientable_faces == len(band_faces)
        assert report.faces_rewound == 0 and report.parts_turned_outward == int(body is not vase.mesh.faces)
        assert "1 non-orientable part(s) (24 faces, like a Möbius strip) wound face by face, outward" in report.summary()


def test_outside_sides_of_closed_and_open_surfaces_wound_at_random(rng):
    """Ray parity tells each face's outside whatever the winding around it: a torus and a
    thick tube (closed, concave in places) and a deep bowl (open), every face's winding
    drawn at random."""
    sphere = trimesh.creation.icosphere(3)
    surfaces = {"torus": trimesh.creation.torus(1.0, 0.3), "tube": trimesh.creation.annulus(0.8, 1.0, 2.0),
                "bowl": trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 2] < 0.5], process=False)}
    for name, surface in surfaces.items():
        vertices, faces = np.asarray(surface.vertices, dtype=float), np.asarray(surface.faces)
        assert outwardness(vertices, faces)[0] > 0, name  # as made: outward
        flipped = rng.random(len(faces)) < 0.5
        inwards, decided = outside_sides(vertices, np.where(flipped[:, None], faces[:, [0, 2, 1]], faces),
                                         np.arange(len(faces)))
        assert decided.all(), name
        np.testing.assert_array_equal(inwards, flipped, err_msg=name)


def test_a_file_holding_a_moebius_band_reads_with_its_message(vase, tmp_path, rng):
    """A CAD-like OBJ (double-sided soup with UVs) of a vase whose label is a Möbius
    band reads through read_mesh; the vase stays outward and the message says what was done."""
    band_vertices, band_faces = _moebius_band(16)
    lo, hi = vase.mesh.bounds()
    band_vertices = (lo + hi) / 2 + band_vertices * 0.3 * (hi - lo).min()
    band_vertices[:, 0] += 0.8 * (hi - lo)[0]  # beside the vase, touching nothing
    body = Mesh(np.concatenate([vase.mesh.vertices, band_vertices]),
                np.concatenate([vase.mesh.faces, band_faces + vase.mesh.n_vertices]))
    _cad_obj(body, tmp_path / "banded.obj", rng)
    mesh = read_mesh(tmp_path / "banded.obj")
    assert mesh.report.unorientable_parts == 1 and mesh.report.unorientable_faces == 32
    summary = mesh.report.summary()
    assert "1 non-orientable part(s) (32 faces, like a Möbius strip) wound face by face, outward" in summary
    body = Mesh(mesh.vertices, mesh.faces[(mesh.faces < vase.mesh.n_vertices).all(axis=1)])  # welded in file order
    assert body.n_faces == vase.mesh.n_faces and body.is_closed()
    assert enclosed_volume(body) == pytest.approx(enclosed_volume(vase.mesh), rel=1e-9)


def test_the_blender_hand_off_is_cleaned_like_a_file(vase, tmp_path):
    """Fit's meshes from Blender (a "shapegen.meshes" file the worker reads) go through the
    same intake: a soup wound inside out comes out welded and outward."""
    vertices, faces = _soup(vase.mesh.vertices, vase.mesh.faces[:, ::-1])
    path = save_mesh_set(tmp_path / "meshes.npz", ["soup", "vase"], [vertices, vase.mesh.vertices],
                         [faces, vase.mesh.faces])
    soup, clean = load_mesh_set(path)
    assert soup.n_vertices == vase.mesh.n_vertices and soup.report.parts_turned_outward == 1
    np.testing.assert_allclose(soup.face_normals(), vase.mesh.face_normals(), atol=1e-12)
    assert clean.report.summary() == "clean"
    np.testing.assert_array_equal(clean.faces, vase.mesh.faces)


# ---------------------------------------------------------------------------- STL class
@pytest.fixture(scope="module")
def stl_model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("stl")
    shapes = make_vases(6, seed=2, resolution=(14, 18))
    write_collection(shapes, folder, "stl")
    meshes = read_folder(folder)
    return folder, shapes, meshes, fit_meshes(meshes, FitSettings(prepare=PrepareSettings(n_landmarks=80), model="ppca"), jobs=1)


def test_stl_files_are_read_as_connected_outward_surfaces(stl_model):
    _, shapes, meshes, _ = stl_model
    for shape, mesh in zip(shapes, meshes):
        assert mesh.n_vertices == shape.mesh.n_vertices
        assert mesh.report.vertices_welded == 3 * shape.mesh.n_faces - shape.mesh.n_vertices
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        assert mesh.is_closed() and tm.body_count == 1 and tm.is_winding_consistent and tm.volume > 0


def binary_stl_corners(path) -> np.ndarray:
    """Every triangle's three corners as a binary STL stores them (80-byte header, a count,
    then 50-byte records: normal, three corners, attribute), read without trimesh (whose
    loaders merge corners or not depending on the release)."""
    data = path.read_bytes()
    count = int(np.frombuffer(data, "<u4", 1, 80)[0])
    assert len(data) == 84 + 50 * count, "not a binary STL"
    record = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
    return np.frombuffer(data, record, count, 84)["corners"].reshape(-1, 3).astype(np.float64)


def test_smoothed_samples_of_an_stl_class_have_no_cracks_and_are_written_connected(stl_model, tmp_path):
    """Corners that coincide in the template's STL file stay together (to 1e-9 of the
    diagonal) through sampling and curvature-flow smoothing, and the written files are one
    body. (Unwelded, one smoothing step opened cracks of a median 9.6 % of the diagonal and
    three steps failed: each loose triangle shrank on its own to a singular system.)"""
    folder, _, _, model = stl_model
    samples, _ = model.sample(4, np.random.default_rng(0))
    for k, landmarks in enumerate(samples):
        index = model.choose_template(landmarks, "nearest-data")
        template = model.meshes[index]
        mesh = model.mesh_from_landmarks(landmarks, template=model.names[index], smooth=3)
        in_file = binary_stl_corners(folder / f"{model.names[index]}.stl")
        assert len(in_file) == len(template.report.vertex_map) == 3 * template.n_faces
        _, first, group = np.unique(in_file, axis=0, return_index=True, return_inverse=True)
        at_corners = mesh.vertices[template.report.vertex_map]  # the sample at each file corner
        crack = np.linalg.norm(at_corners - at_corners[first[group.ravel()]], axis=1).max()
        assert crack <= 1e-9 * mesh.bbox_diagonal()
        for suffix in ("obj", "ply"):
            written = trimesh.load(write_mesh(mesh, tmp_path / f"sample_{k}.{suffix}"), process=False)
            assert written.body_count == 1 and len(written.vertices) == template.n_vertices
        assert read_mesh(write_mesh(mesh, tmp_path / f"sample_{k}.stl")).is_closed()


# ---------------------------------------------------------------------------- CAD files
def _double_sided(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every face twice, the copy wound the other way (how CAD files store sheets)."""
    return vertices, np.concatenate([faces, faces[:, [0, 2, 1]]])


def _label(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """A small closed box (a label) standing off the side of `mesh`."""
    lo, hi = mesh.bounds()
    box = trimesh.creation.box(extents=0.05 * (hi - lo))
    return box.vertices + [hi[0] + 0.05 * (hi[0] - lo[0]), 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])], box.faces


def _cad_obj(mesh: Mesh, path, rng) -> None:
    """`mesh` with a label, double-sided, as a soup with one UV per corner (an OBJ file)."""
    label_vertices, label_faces = _label(mesh)
    vertices = np.concatenate([mesh.vertices, label_vertices])
    vertices, faces = _double_sided(vertices, np.concatenate([mesh.faces, label_faces + mesh.n_vertices]))
    corners = vertices[faces.ravel()]
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in corners.tolist()]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in rng.random((len(corners), 2))]
    lines += [f"f {3 * i + 1}/{3 * i + 1} {3 * i + 2}/{3 * i + 2} {3 * i + 3}/{3 * i + 3}" for i in range(len(faces))]
    path.write_text("\n".join(lines) + "\n")


def test_a_double_sided_soup_is_one_outward_surface_with_a_map_back_to_the_file(vase, rng):
    vertices, faces = _soup(*_double_sided(vase.mesh.vertices, rng.permutation(vase.mesh.faces)))
    mesh = clean_mesh(vertices, faces, name="cad")
    assert mesh.n_faces == vase.mesh.n_faces and mesh.n_vertices == vase.mesh.n_vertices
    assert mesh.is_closed() and enclosed_volume(mesh) > 0
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert tm.is_winding_consistent and tm.body_count == 1
    report = mesh.report
    assert report.twin_faces_dropped == vase.mesh.n_faces
    # every file triangle maps to one mesh face: kept ones through face_source, the other
    # sides through twin_source/twin_of, onto the same three vertices
    source = np.arange(mesh.n_faces) if report.face_source is None else report.face_source
    assert sorted(np.concatenate([source, report.twin_source]).tolist()) == list(range(len(faces)))
    welded = report.vertex_map[faces]
    np.testing.assert_array_equal(np.sort(welded[report.twin_source], axis=1),
                                  np.sort(mesh.faces[report.twin_of], axis=1))
    # one sensible line: no per-triangle parts turned or left without an outside
    summary = report.summary()
    assert "inside-out" not in summary and "no outside" not in summary and "\n" not in summary
    assert f"{vase.mesh.n_faces} double-sided" in summary


def test_a_small_separate_part_is_kept_and_named(vase):
    label_vertices, label_faces = _label(vase.mesh)
    vertices = np.concatenate([vase.mesh.vertices, label_vertices])
    faces = np.concatenate([vase.mesh.faces, label_faces + vase.mesh.n_vertices])
    mesh = clean_mesh(vertices, faces, name="labelled")
    assert mesh.n_faces == len(faces) and mesh.report.separate_parts == 2
    assert "2 separate parts" in mesh.report.summary()


@pytest.fixture(scope="module")
def cad_model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cad")
    rng = np.random.default_rng(3)
    for shape in make_vases(4, seed=2, resolution=(12, 16)):
        _cad_obj(shape.mesh, folder / f"{shape.name}.obj", rng)
    meshes = read_folder(folder)
    return meshes, fit_meshes(meshes, FitSettings(prepare=PrepareSettings(n_landmarks=40), model="ppca"), jobs=1)


def test_samples_of_a_double_sided_class_are_written_one_sided_outward_with_their_label(cad_model, tmp_path):
    """Written as the CLI writes them (the template's file layout: its soup and UVs), a
    sample has no coincident faces, its body is consistently wound and encloses a positive
    volume, and the label is a second body of the file."""
    from shapegen_core.meshes.writing import MeshWriters
    from shapegen_core.generate.quality import coincident_faces

    meshes, model = cad_model
    assert all(m.report.layout is not None and m.report.separate_parts == 2 for m in meshes)
    writers = MeshWriters(model.meshes)
    samples, _ = model.sample(2, np.random.default_rng(0))
    for k, landmarks in enumerate(samples):
        index = model.choose_template(landmarks, "nearest-data")
        mesh = model.mesh_from_landmarks(landmarks, template=model.names[index])
        written = trimesh.load(writers.write(mesh, index, tmp_path / f"sample_{k}.obj"), process=False, force="mesh")
        assert len(written.faces) == model.meshes[index].n_faces  # one side: half the file's faces
        assert coincident_faces(np.asarray(written.vertices), np.asarray(written.faces)) == 0
        welded = trimesh.Trimesh(written.vertices, written.faces)  # merged vertices: the connected surface
        assert welded.body_count == 2 and welded.is_winding_consistent
        assert all(body.volume > 0 for body in welded.split(only_watertight=False))


# ------------------------------------------------- quads, walls between cells, slivers
_CUBE = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
_CUBE_QUADS = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]


def test_a_double_sided_quad_soup_file_is_one_surface_however_its_back_was_cut(tmp_path):
    """An OBJ soup of quads and a hexagon, each written twice with opposite windings (the
    back starts at another corner, so trimesh cuts it along the other diagonal): one
    closed outward surface, every back named as a twin, written back one-sided."""
    hexagon = [[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 7)[:-1]]
    polygons = [[tuple(_CUBE[v]) for v in q] for q in _CUBE_QUADS]
    polygons += [[tuple(p) for p in np.asarray(hexagon) * 0.3 + [0.5, 0.5, 1.5]]]  # a sheet floating above
    polygons += [p[::-1][1:] + p[::-1][:1] for p in polygons]  # the backs, from another corner
    lines, face_lines = [], []
    for polygon in polygons:
        face_lines.append("f " + " ".join(str(len(lines) + k + 1) for k in range(len(polygon))))
        lines += ["v %r %r %r" % tuple(map(float, p)) for p in polygon]
    (tmp_path / "box.obj").write_text("\n".join(lines + face_lines) + "\n")
    mesh = read_mesh(tmp_path / "box.obj")
    assert mesh.n_faces == 12 + 4 and mesh.report.twin_faces_dropped == 16
    box = Mesh(mesh.vertices, mesh.faces[:12])
    assert box.is_closed() and enclosed_volume(box) == pytest.approx(1.0)
    assert "16 double-sided" in mesh.report.summary() and "no outside" in mesh.report.summary()
    written = write_mesh(mesh, tmp_path / "out.obj").read_text()
    assert sum(line.startswith("f ") for line in written.splitlines()) == 7  # one side of each polygon


def _two_cells():
    """A 2 × 1 × 1 box of two unit cells and the wall between them (quads as triangles)."""
    vertices = np.array([[x, y, z] for x in (0, 1, 2) for y in (0, 1) for z in (0, 1)], dtype=float)
    at = lambda x, y, z: 4 * x + 2 * y + z  # noqa: E731
    quads = [[at(0, 0, 0), at(0, 0, 1), at(0, 1, 1), at(0, 1, 0)], [at(2, 0, 0), at(2, 1, 0), at(2, 1, 1), at(2, 0, 1)]]
    for x in (0, 1):
        quads += [[at(x, 0, 0), at(x + 1, 0, 0), at(x + 1, 0, 1), at(x, 0, 1)],
                  [at(x, 1, 0), at(x, 1, 1), at(x + 1, 1, 1), at(x + 1, 1, 0)],
                  [at(x, 0, 0), at(x, 1, 0), at(x + 1, 1, 0), at(x + 1, 0, 0)],
                  [at(x, 0, 1), at(x + 1, 0, 1), at(x + 1, 1, 1), at(x, 1, 1)]]
    wall = [at(1, 0, 0), at(1, 1, 0), at(1, 1, 1), at(1, 0, 1)]
    triangles = lambda q: [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]  # noqa: E731
    return vertices, np.array([t for q in quads for t in triangles(q)]), np.array(triangles(wall))


def test_a_wall_between_two_cells_is_left_out_of_the_surface_and_named():
    vertices, outside, wall = _two_cells()
    faces = np.concatenate([wall, outside, wall[:, [0, 2, 1]]])  # the wall double-sided too
    mesh = clean_mesh(vertices, faces, name="cells")
    assert mesh.n_faces == len(outside) and mesh.is_closed() and enclosed_volume(mesh) == pytest.approx(2.0)
    assert mesh.report.internal_faces_dropped == 4 and mesh.report.twin_faces_dropped == 0
    np.testing.assert_array_equal(mesh.report.face_source, np.arange(2, 2 + len(outside)))
    assert "4 internal face(s)" in mesh.report.summary()


def test_a_fin_on_a_closed_box_is_not_internal():
    """A sheet standing on an edge of the box (three faces on that edge, but a border of
    its own) is part of the outside."""
    vertices, outside, _ = _two_cells()
    vertices = np.concatenate([vertices, [[0, 0, 2], [1, 0, 2]]])
    fin = np.array([[1, 5, 13], [1, 13, 12]])  # on the edge (0,0,1)-(1,0,1)
    mesh = clean_mesh(vertices, np.concatenate([outside, fin]), name="fin")
    assert mesh.n_faces == len(outside) + 2 and mesh.report.internal_faces_dropped == 0


def test_loose_slivers_are_dropped_and_slivers_inside_the_surface_kept():
    """A needle on the border of a sheet comes off (no new hole); a sliver between two
    faces of a closed surface stays (a hole otherwise), and both are counted."""
    sheet = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, -1e-6, 0]], dtype=float)
    mesh = clean_mesh(sheet, [[0, 1, 2], [0, 2, 3], [0, 4, 1]], name="sheet")
    assert mesh.n_faces == 2 and mesh.report.sliver_faces_dropped == 1
    assert "1 loose sliver face(s) dropped" in mesh.report.summary()
    # a tetrahedron-like closed surface with one corner nearly on the opposite edge
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1e-6, 0], [0.5, 0.3, 1]], dtype=float)
    closed = clean_mesh(vertices, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]], name="closed")
    assert closed.n_faces == 4 and closed.is_closed()
    assert closed.report.sliver_faces_kept == 1 and closed.report.sliver_faces_dropped == 0
    assert "1 sliver face(s) inside the surface kept" in closed.report.summary()


def _solid_angle_winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The reference: every face's signed solid angle at every point (Van Oosterom &
    Strackee's closed form per triangle) summed, over 4π."""
    corners = vertices[faces]  # (F, 3, 3)
    a, b, c = (corners[None, :, k, :] - points[:, None, :] for k in range(3))  # (Q, F, 3)
    la, lb, lc = (np.linalg.norm(d, axis=2) for d in (a, b, c))
    numerator = np.einsum("qfi,qfi->qf", a, np.cross(b, c))
    denominator = (la * lb * lc + np.einsum("qfi,qfi->qf", a, b) * lc
                   + np.einsum("qfi,qfi->qf", a, c) * lb + np.einsum("qfi,qfi->qf", b, c) * la)
    return 2 * np.arctan2(numerator, denominator).sum(axis=1) / (4 * np.pi)


#: How far the fast winding number (libigl, Barill et al. 2018: far clusters of faces by a
#: second-order expansion) may stray from the exact sum; about 3× the worst seen on random meshes.
FAST_WINDING_TOLERANCE = 0.01


def test_fast_and_brute_force_winding_numbers_agree_on_random_meshes():
    """Closed and open jittered spheres at several sizes and scales; points anywhere
    around them, and just off both sides of the surface (1e-2 to 1e-6 of the diagonal)."""
    rng = np.random.default_rng(41)
    for subdivisions in (1, 2, 3):
        sphere = trimesh.creation.icosphere(subdivisions)
        vertices = np.asarray(sphere.vertices) * rng.uniform(0.7, 1.3, (len(sphere.vertices), 1)) * rng.uniform(0.01, 100)
        closed = np.asarray(sphere.faces)
        for faces in (closed, closed[vertices[closed].mean(axis=1)[:, 2] < 0.5 * vertices[:, 2].max()]):
            diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
            corners = vertices[faces]
            normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            normal /= np.linalg.norm(normal, axis=1)[:, None]
            at = rng.choice(len(faces), min(len(faces), 60), replace=False)
            on = np.einsum("fk,fki->fi", rng.dirichlet(np.ones(3), len(at)), corners[at])
            points = [rng.uniform(vertices.min(axis=0) - 0.2 * diagonal, vertices.max(axis=0) + 0.2 * diagonal, (200, 3))]
            points += [on + sign * offset * diagonal * normal[at] for offset in (1e-2, 1e-4, 1e-6) for sign in (1, -1)]
            points = np.concatenate(points)
            exact = _solid_angle_winding_numbers(vertices, faces, points)
            assert np.abs(exact).max() > 0.9  # the points do see the surface wind around them
            np.testing.assert_allclose(winding_numbers(vertices, faces, points), exact, atol=FAST_WINDING_TOLERANCE, rtol=0)


def test_winding_numbers_of_a_closed_box():
    """1 inside a closed outward surface, 0 outside; no faces wind around nothing."""
    vertices, outside, _ = _two_cells()
    mesh = clean_mesh(vertices, outside)
    points = np.array([[0.5, 0.5, 0.5], [1.5, 0.2, 0.9], [3, 0, 0], [-1, 2, 2]])
    np.testing.assert_allclose(winding_numbers(mesh.vertices, mesh.faces, points), [1, 1, 0, 0], atol=FAST_WINDING_TOLERANCE)
    np.testing.assert_array_equal(winding_numbers(mesh.vertices, mesh.faces[:0], points), np.zeros(4))
