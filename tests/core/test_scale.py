"""Dense meshes and large collections: the vertex-clustering proxy, exact
closest points on a full surface from an upper bound, dense and sparse copies of one
shape corresponding alike, and what a worker receives not growing with the collection.
Small meshes only: time and memory at scale are measured by bench/scale.py."""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from shapegen_core.preprocess.collection import PrepareSettings, PreparedCollection, prepare_meshes
from shapegen_core.correspond import CorrespondenceSettings, correspond
from shapegen_core.correspond.settings import IterationSettings
from shapegen_core.correspond import groupwise
from shapegen_core.correspond.proxy import PlacementTask, place_on_full_surface
from shapegen_core.correspond.registration import Registration
from shapegen_core.demo_data import make_vases
from shapegen_core.geometry import TargetSurface
from shapegen_core.geometry.nearby import closest_within
from shapegen_core.meshes.mesh import Mesh
from shapegen_core.meshes.simplify import proxy_mesh

from conftest import subdivided


_subdivided = subdivided


@pytest.fixture(scope="module")
def vases():
    return [s.mesh for s in make_vases(5, seed=3, resolution=(26, 32))]


def test_proxy_is_small_close_and_keeps_small_meshes(vases):
    mesh = _subdivided(vases[0], 2)
    proxy = proxy_mesh(mesh, 3000)
    assert proxy_mesh(vases[0], vases[0].n_faces).mesh is vases[0]  # not above the size: the mesh itself
    assert not proxy.is_full and 1000 < proxy.mesh.n_faces <= 3150
    # every proxy vertex has a representative vertex of the full mesh near it
    gap = np.linalg.norm(mesh.vertices[proxy.representatives] - proxy.mesh.vertices, axis=1)
    assert gap.max() < 0.05 * mesh.bbox_diagonal()
    # the proxy lies on the surface up to a small fraction of the diagonal, both ways
    samples = mesh.sample_surface(2000, np.random.default_rng(0)).points
    there = TargetSurface(proxy.mesh.vertices, proxy.mesh.faces).closest(samples).distance
    back = TargetSurface(mesh.vertices, mesh.faces).closest(proxy.mesh.vertices[np.unique(proxy.mesh.faces)]).distance
    assert there.mean() < 0.005 * mesh.bbox_diagonal() and back.max() < 0.03 * mesh.bbox_diagonal()
    # the proxy's faces face the same way as the surface they stand for
    normals = proxy.mesh.face_normals()
    found = TargetSurface(mesh.vertices, mesh.faces).closest(proxy.mesh.triangles.mean(axis=1))
    agree = np.einsum("nd,nd->n", normals, mesh.face_normals()[found.face_index])
    assert np.median(agree) > 0.9


def test_closest_within_is_exact(vases, rng):
    mesh = _subdivided(vases[1], 1)
    surface = TargetSurface(mesh.vertices, mesh.faces)
    points = mesh.vertices[rng.choice(mesh.n_vertices, 300)] + rng.normal(scale=0.02, size=(300, 3))
    # any surface point gives an upper bound: here a random vertex per query, far or near
    bound = np.linalg.norm(points - mesh.vertices[rng.choice(mesh.n_vertices, 300)], axis=1)
    found = closest_within(mesh.vertices, mesh.faces, points, bound)
    expected = surface.closest(points)
    np.testing.assert_allclose(found.distance, expected.distance, rtol=0, atol=1e-12)
    on_face = np.einsum("nk,nkd->nd", found.barycentric, mesh.triangles[found.face_index])
    np.testing.assert_allclose(found.points, on_face, atol=1e-12)
    # with normals: the closest compatible point, as TargetSurface finds it
    normals = mesh.face_normals()[expected.face_index]
    compatible = closest_within(mesh.vertices, mesh.faces, points, bound, normals, 0.5)
    np.testing.assert_allclose(compatible.distance, surface.closest(points, normals, 0.5).distance, atol=1e-12)


def _collection(meshes) -> PreparedCollection:
    """Prepared without turning (align none), 200 landmarks."""
    return prepare_meshes(meshes, PrepareSettings(n_landmarks=200, align="none"))


@pytest.mark.quality
def test_dense_and_sparse_copies_correspond_alike(vases):
    """A shape and its 16x denser copy (the same surface) land their landmarks at the same
    places, up to the spacing of the landmarks (each copy picks its own target landmarks);
    registering the dense copy against its proxy and placing the landmarks on its full
    surface moves them far less than that from registering against the full surface."""
    dense = _subdivided(vases[0], 2)
    settings = CorrespondenceSettings(proxy_faces=4000)
    assert dense.n_faces > 2.5 * settings.proxy_faces > settings.proxy_faces > vases[0].n_faces
    sparse_run = correspond(_collection(vases), settings, template=vases[1].name, jobs=1)
    dense_collection = _collection([dense] + vases[1:])
    messages = []
    dense_run = correspond(dense_collection, settings, template=vases[1].name, jobs=1,
                           progress=lambda fraction, message: messages.append((fraction, message)))
    fractions = [f for f, _ in messages]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert any("proxy of" in m for _, m in messages) and any("full surface" in m for _, m in messages)
    full_run = correspond(dense_collection, replace(settings, proxy_faces=10**6), template=vases[1].name, jobs=1)
    diagonal = vases[0].bbox_diagonal()
    spacing = dense_collection.landmarks[0].radius / diagonal  # landmarks are at least this far apart
    # compare in input coordinates (the collections were prepared separately)
    shift = np.linalg.norm(dense_run.points_input[0] - sparse_run.points_input[0], axis=1) / diagonal
    assert np.median(shift) < 0.5 * spacing
    proxy_effect = np.linalg.norm(dense_run.points[0] - full_run.points[0], axis=1) / diagonal
    assert np.median(proxy_effect) < 0.005 and np.median(proxy_effect) < 0.1 * spacing
    assert abs(dense_run.residuals[0] - full_run.residuals[0]) < 0.1 * full_run.residuals[0]
    # the dense shape's landmarks lie exactly on its full surface, at their face and barycentrics
    full = dense_collection.shapes[0].mesh
    on_face = np.einsum("nk,nkd->nd", dense_run.barycentric[0], full.triangles[dense_run.face_index[0]])
    np.testing.assert_allclose(on_face, dense_run.points[0], atol=1e-9)
    # the other shapes barely notice
    others = np.linalg.norm(dense_run.points_input[1:] - sparse_run.points_input[1:], axis=2) / diagonal
    assert np.median(others) < 0.5 * spacing


def test_placement_on_full_surface_matches_a_full_search(vases, rng):
    """`place_on_full_surface` (bound from the proxy's representatives) equals a search
    over every face: the closest compatible point, in the registration frame."""
    mesh = _subdivided(vases[2], 1)
    proxy = proxy_mesh(mesh, 2000)
    centre, scale = np.array([0.1, -0.2, 0.3]), 0.7
    points = mesh.sample_surface(200, rng).points + rng.normal(scale=0.01, size=(200, 3))
    normals = mesh.face_normals()[TargetSurface(mesh.vertices, mesh.faces).closest(points).face_index]
    deformed = (points - centre) / scale
    registration = Registration(None, None, deformed, 0.0, 1, np.zeros(1), normals)
    task = PlacementTask(mesh.vertices, mesh.faces, proxy.representatives, points[:50], registration,
                         float(np.cos(np.radians(60))), centre, scale)
    placed = place_on_full_surface(task)
    full = TargetSurface((mesh.vertices - centre) / scale, mesh.faces)
    expected = full.closest(deformed, normals, float(np.cos(np.radians(60))))
    np.testing.assert_allclose(placed.placed.distance, expected.distance, atol=1e-12)
    np.testing.assert_allclose(placed.normals, full.face_normals[placed.placed.face_index], atol=1e-12)
    assert np.isfinite(placed.residual) and placed.deformed is deformed


def test_what_a_worker_receives_does_not_grow_with_the_collection(vases, monkeypatch):
    """The pickled registration task of one shape has the same size in a collection of 3
    and of 9 shapes: a worker receives one shape at a time."""
    sizes = {}

    def recording_run(self, tasks, progress, label):
        sizes.setdefault(len(tasks), len(pickle.dumps(tasks[0])))
        return original(self, tasks, progress, label)

    original = groupwise.RegistrationRunner.run
    monkeypatch.setattr(groupwise.RegistrationRunner, "run", recording_run)
    settings = CorrespondenceSettings(groupwise_rounds=0, iterations=IterationSettings(max_iterations=2))
    base = _collection(vases[:3])
    for copies in (1, 3):
        shapes = [s for _ in range(copies) for s in base.shapes]
        shapes = [type(s)(s.mesh.with_vertices(s.mesh.vertices, name=f"{s.name}_{k}"), s.transform,
                          s.orientation_changed, s.pose_rotation, s.pose_change, s.pose_outlier)
                  for k, s in enumerate(shapes)]
        collection = PreparedCollection(shapes, base.landmarks * copies, base.settings)
        correspond(collection, settings, template=shapes[0].name, jobs=1)
    assert set(sizes) == {3, 9}
    assert sizes[3] == sizes[9]


def test_cubic_model_fits_of_many_shapes_say_so(vases, monkeypatch):
    """GP-LVM (O(N³) per iteration) notes its cost above CUBIC_NOTE_SHAPES shapes, as a
    ScaleWarning and a progress message; PPCA and the Bayesian GP-LVM never do."""
    from shapegen_core.models import scaling
    from shapegen_core.app.fit_settings import FitSettings
    from shapegen_core.app.pipeline import fit_shape_model

    assert scaling.size_note("gplvm", scaling.CUBIC_NOTE_SHAPES) is None
    assert "N³" in scaling.size_note("gplvm", 1000) and "bgplvm" in scaling.size_note("gplvm", 1000)
    assert scaling.size_note("bgplvm", 10**5) is None and scaling.size_note("ppca", 10**5) is None
    collection = _collection(vases)
    corr = correspond(collection, CorrespondenceSettings(groupwise_rounds=0, iterations=IterationSettings(max_iterations=3)),
                      jobs=1)
    monkeypatch.setattr(scaling, "CUBIC_NOTE_SHAPES", 3)
    messages = []
    with pytest.warns(scaling.ScaleWarning, match="N³"):
        fit_shape_model([s.mesh for s in collection.shapes], corr, FitSettings(model="gplvm", latent_dim=1),
                        progress=lambda fraction, message: messages.append(message))
    assert any("N³" in m for m in messages)


def test_files_read_in_workers_equal_those_read_here(vases, tmp_path):
    """read_folder(jobs=2) (shapegen fit reads so) gives the meshes read in this process:
    same names, order, vertices and int32 faces, read-only either way."""
    from shapegen_core.meshes.reading import read_folder

    for index, mesh in enumerate(vases[:3]):
        dense = _subdivided(mesh, 1)
        trimesh.Trimesh(dense.vertices, dense.faces, process=False).export(tmp_path / f"v{index}.ply",
                                                                            encoding="binary")
    here, workers = read_folder(tmp_path, jobs=1), read_folder(tmp_path, jobs=2)
    assert [m.name for m in here] == [m.name for m in workers] == ["v0", "v1", "v2"]
    for a, b in zip(here, workers):
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.faces, b.faces)
        assert a.faces.dtype == b.faces.dtype == np.int32
        assert not (b.vertices.flags.writeable or b.faces.flags.writeable)


def test_meshes_share_read_only_arrays_instead_of_copying(vases):
    """A mesh keeps read-only arrays of its dtypes as they are (with_vertices shares the
    faces); an unpickled mesh is read-only again."""
    mesh = vases[0]
    moved = mesh.with_vertices(mesh.vertices + 1.0)
    assert moved.faces is mesh.faces and mesh.faces.dtype == np.int32
    writable = mesh.faces.copy()
    assert not np.shares_memory(Mesh(mesh.vertices, writable).faces, writable)  # a writable array is copied
    back = pickle.loads(pickle.dumps(mesh))
    assert not (back.vertices.flags.writeable or back.faces.flags.writeable)
    assert back.bbox_diagonal() == mesh.bbox_diagonal()


def test_meshes_streamed_into_files_uncompressed(vases, tmp_path):
    """npzfile.Concatenation writes the concatenated array without building it, `stored`
    keys are written without compression, and the file reads back as before."""
    import zipfile

    from shapegen_core.base.npzfile import Concatenation, save_npz

    parts = [m.vertices for m in vases[:3]]
    path = save_npz(tmp_path / "x.npz", "shapegen.test", 1,
                    {"vertices": Concatenation(parts), "faces": Concatenation([m.faces for m in vases[:3]]),
                     "small": np.arange(5.0)}, stored=("vertices", "faces"))
    with np.load(path, allow_pickle=False) as data:
        np.testing.assert_array_equal(data["vertices"], np.concatenate(parts))
        assert data["faces"].dtype == np.int32 and len(data["faces"]) == sum(m.n_faces for m in vases[:3])
        np.testing.assert_array_equal(data["small"], np.arange(5.0))
    with zipfile.ZipFile(path) as archive:
        kinds = {info.filename: info.compress_type for info in archive.infolist()}
    assert kinds["vertices.npy"] == kinds["faces.npy"] == zipfile.ZIP_STORED
    assert kinds["small.npy"] == zipfile.ZIP_DEFLATED
    with pytest.raises(ValueError):
        Concatenation([np.zeros((2, 3)), np.zeros((2, 2))])
