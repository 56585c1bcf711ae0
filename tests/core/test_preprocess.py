"""Alignment and scaling (§3.4): exact round trips, scaling invariants, exact surface
moments, floor / centre, the PCA sign rule and the consensus orientation."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
from shapegen_core.demo_data import make_vases
from shapegen_core.base.errors import CollectionError
from shapegen_core.meshes.mesh import Mesh
from shapegen_core.preprocess import (
    ShapeTransform,
    prepare_collection,
    scale_measure,
    surface_moments,
    third_central_moment,
)

from conftest import unit_cube

Z_TO_MINUS_Z = np.diag([1.0, -1.0, -1.0])  # upside down (half turn about x)
Z_TO_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # file written y-up (z -> +y)


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------------------- transforms
CASES = [(a, s, c) for a in ("pca", "none") for s in ("variance", "bbox", "none")
         for c in ("centroid", "highest", "none")]
CASES += [("consensus", "variance", "centroid"), ("consensus", "bbox", "highest")]


@pytest.mark.parametrize("align,scale,centre", CASES)
def test_round_trip_input_normalised_input(small_vases, align, scale, centre):
    meshes = [s.mesh for s in small_vases[:3]]  # a property of each shape's transform: three show it
    prepared = prepare_collection(meshes, up_axis="y", align=align, scale=scale, centre=centre)
    for mesh, shape in zip(meshes, prepared):
        t = shape.transform
        size = np.abs(mesh.vertices).max()
        np.testing.assert_allclose(t.to_input(shape.mesh.vertices), mesh.vertices, rtol=0, atol=1e-9 * size)
        np.testing.assert_allclose(shape.mesh.vertices, t.to_normalised(mesh.vertices), rtol=0, atol=1e-12 * size)
        # the 4x4 matrix is the same map and survives from_matrix
        homogeneous = np.c_[mesh.vertices, np.ones(mesh.n_vertices)] @ t.matrix.T
        np.testing.assert_allclose(homogeneous[:, :3], shape.mesh.vertices, atol=1e-12 * size)
        again = ShapeTransform.from_matrix(t.matrix)
        np.testing.assert_allclose(again.to_input(shape.mesh.vertices), mesh.vertices, atol=1e-9 * size)
        # a proper similarity: R orthonormal with det +1, s > 0
        np.testing.assert_allclose(t.rotation @ t.rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(t.rotation) == pytest.approx(1.0) and t.scale > 0
        assert np.array_equal(shape.mesh.faces, mesh.faces)


def test_landmarks_map_back_to_the_input_surface(small_vases):
    meshes = [s.mesh for s in small_vases[:3]]
    for align, scale in (("pca", "variance"), ("none", "bbox"), ("consensus", "variance")):
        prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=60, align=align, scale=scale, seed=3))
        for i, mesh in enumerate(meshes):
            lm = prepared.landmarks[i]
            on_input = np.einsum("nk,nkd->nd", lm.barycentric, mesh.triangles[lm.face_index])
            size = np.abs(mesh.vertices).max()
            np.testing.assert_allclose(prepared.landmarks_input(i), on_input, atol=1e-9 * size)
            np.testing.assert_allclose(prepared.shapes[i].transform.to_normalised(on_input), lm.points,
                                       atol=1e-9 * size)


def test_transform_composition_and_rejection():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    t = ShapeTransform(q, 2.5, np.array([1.0, -2.0, 3.0])).then(_rz(0.3), 0.4, np.array([0.5, 0, 0]))
    x = rng.normal(size=(10, 3))
    expected = 0.4 * (2.5 * x @ q.T + [1.0, -2.0, 3.0]) @ _rz(0.3).T + [0.5, 0, 0]
    np.testing.assert_allclose(t.to_normalised(x), expected, atol=1e-12)
    np.testing.assert_allclose(t.to_input(expected), x, atol=1e-12)
    with pytest.raises(ValueError, match="det <= 0"):
        ShapeTransform.from_matrix(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="not a similarity"):
        ShapeTransform.from_matrix(np.diag([1.0, 2.0, 0.5, 1.0]))


# ---------------------------------------------------------------------------- scaling
@pytest.mark.parametrize("align", ["pca", "none"])
def test_scaling_invariants(small_vases, align):
    meshes = [s.mesh for s in small_vases[:3]]
    variance = prepare_collection(meshes, align=align, scale="variance")
    values = np.array([np.trace(surface_moments(s.mesh)[2]) for s in variance])
    np.testing.assert_allclose(values, values[0], rtol=1e-9)
    # the common value is the geometric mean of the inputs' (rotation invariant) variances
    inputs = np.array([scale_measure(m, "variance") for m in meshes])
    assert values[0] == pytest.approx(np.exp(np.log(inputs).mean()), rel=1e-9)

    bbox = prepare_collection(meshes, align=align, scale="bbox")
    volumes = np.array([np.prod(np.diff(s.mesh.bounds(), axis=0)) for s in bbox])
    np.testing.assert_allclose(volumes, volumes[0], rtol=1e-9)

    unscaled = prepare_collection(meshes, align=align, scale="none")
    assert all(s.transform.scale == 1.0 for s in unscaled)


# ---------------------------------------------------------------------------- moments
def test_surface_moments_closed_form_unit_cube():
    area, mean, cov = surface_moments(unit_cube())
    assert area == pytest.approx(6.0, rel=1e-12)
    np.testing.assert_allclose(mean, 0.5, atol=1e-12)
    # per axis: two faces at distance 1/2 (variance 1/4), four faces uniform (1/12)
    var = (2 * 0.25 + 4 / 12) / 6
    np.testing.assert_allclose(cov, var * np.eye(3), atol=1e-12)


def test_surface_moments_against_dense_trimesh_samples(small_vases):
    mesh = small_vases[0].mesh
    area, mean, cov = surface_moments(mesh)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert area == pytest.approx(tm.area, rel=1e-12)
    points, _ = trimesh.sample.sample_surface(tm, 400_000, seed=11)
    scale = np.sqrt(np.trace(cov))
    # Monte-Carlo standard error ~ scale / sqrt(n) ~ 1.6e-3 scale; allow 5 sigma
    np.testing.assert_allclose(mean, points.mean(axis=0), atol=8e-3 * scale)
    np.testing.assert_allclose(cov, np.cov(points.T), atol=1e-2 * scale**2)
    axis = np.array([0.6, -0.8, 0.0])
    exact = third_central_moment(mesh, axis, mean)
    mc = float(np.mean(((points - mean) @ axis) ** 3))
    assert exact == pytest.approx(mc, abs=2e-2 * scale**3)


def test_surface_moments_ignore_resolution():
    """A coarse and a fine triangulation of the same box have identical moments; vertex
    moments would differ (the refined mesh has interior vertices on the faces)."""
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    fine = box.subdivide().subdivide()
    a = surface_moments(Mesh(box.vertices, box.faces))
    b = surface_moments(Mesh(fine.vertices, fine.faces))
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, atol=1e-12)
    assert not np.allclose(np.cov(box.vertices.T), np.cov(fine.vertices.T))


# ---------------------------------------------------------------------------- floor, centre
def test_floor_and_centre(small_vases):
    meshes = [s.mesh for s in small_vases]
    for shape in prepare_collection(meshes, align="pca", centre="centroid"):
        assert shape.mesh.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-12)
        np.testing.assert_allclose(surface_moments(shape.mesh)[1][:2], 0.0, atol=1e-12)
    for shape in prepare_collection(meshes, align="pca", centre="highest"):
        top = shape.mesh.vertices[np.argmax(shape.mesh.vertices[:, 2])]
        np.testing.assert_allclose(top[:2], 0.0, atol=1e-12)
        assert shape.mesh.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-12)


def test_stray_vertex_does_not_move_the_floor():
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    vertices = np.vstack([box.vertices, [[0.0, 0.0, -50.0]]])  # unused, far below
    meshes = [Mesh(vertices, box.faces, name="a"), Mesh(box.vertices * 2, box.faces, name="b")]
    for shape in prepare_collection(meshes, align="none", scale="none"):
        used = shape.mesh.vertices[np.unique(shape.mesh.faces)]
        assert used[:, 2].min() == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("up,rotation", [("z", np.eye(3)), ("-z", Z_TO_MINUS_Z), ("y", Z_TO_Y)])
def test_up_axis(small_vases, up, rotation):
    """Vases written with their up along +z, -z or +y come out upright with the named axis."""
    meshes = [s.mesh.with_vertices(s.mesh.vertices @ rotation.T) for s in small_vases[:3]]
    for shape, vase in zip(prepare_collection(meshes, up_axis=up, align="pca"), small_vases):
        total = shape.transform.rotation @ rotation @ vase.pose.rotation  # canonical -> normalised
        assert total[2, 2] == pytest.approx(1.0, abs=1e-9)


# ---------------------------------------------------------------------------- PCA sign rule
def test_pca_sign_rule_is_deterministic_under_yaw():
    vase = make_vases(1, seed=4, resolution=(14, 18), pose=False)[0].mesh
    rng = np.random.default_rng(2)
    copies = [vase]
    for k in range(5):
        pose = ShapeTransform(_rz(rng.uniform(-np.pi, np.pi)), rng.uniform(0.5, 2), rng.uniform(-3, 3, 3))
        copies.append(vase.with_vertices(pose.to_normalised(vase.vertices), name=f"copy{k}"))
    prepared = prepare_collection(copies, align="pca", scale="variance")
    for shape in prepared[1:]:
        np.testing.assert_allclose(shape.mesh.vertices, prepared[0].mesh.vertices, atol=1e-6)
    # the rule itself: the main horizontal axis is x and the third moment along +x is positive
    _, mean, cov = surface_moments(prepared[0].mesh)
    assert cov[0, 0] > cov[1, 1] and abs(cov[0, 1]) < 1e-9
    assert third_central_moment(prepared[0].mesh, np.array([1.0, 0, 0]), mean) > 0


# ---------------------------------------------------------------------------- consensus
def test_consensus_restores_one_orientation():
    """Vases in random yaw; some written upside down, some y-up. With up_axis 'z', PCA
    alone leaves those wrong; consensus brings every one upright and facing the same way
    (the spout, at +x in each vase's canonical frame, points the same way for all, to
    within the vases' own variation of about 10°). The inputs disagree in facing, so the
    facing is the one of a shape whose pose is kept, not the PCA axis."""
    vases = make_vases(9, seed=3, resolution=(12, 16))
    extra = [np.eye(3), Z_TO_MINUS_Z, Z_TO_Y] * 3
    meshes = [v.mesh.with_vertices(v.mesh.vertices @ r.T) for v, r in zip(vases, extra)]

    def canonical_to_normalised(prepared):
        return [s.transform.rotation @ r @ v.pose.rotation for s, r, v in zip(prepared, extra, vases)]

    pca = canonical_to_normalised(prepare_collection(meshes, align="pca"))
    assert sum(abs(r[2, 2] - 1) < 1e-6 for r in pca) == 3  # only the upright files

    prepared = prepare_collection(meshes, align="consensus")
    rotations = canonical_to_normalised(prepared)
    for r in rotations:
        assert r[2, 2] == pytest.approx(1.0, abs=1e-6)  # upright
        relative = r @ rotations[0].T
        assert np.degrees(abs(np.arctan2(relative[1, 0], relative[0, 0]))) < 12.0  # one facing
    # every shape written on another axis was turned, each flag matches its rotation
    for s, r in zip(prepared, extra):
        assert s.orientation_changed == (not np.array_equal(s.pose_rotation, np.eye(3))) == bool(s.pose_change)
        if not np.allclose(r, np.eye(3)):
            assert s.orientation_changed


def test_consensus_keeps_the_majority_orientation():
    """When the reference would be one of the odd shapes, the majority's pose still wins,
    and its members are not turned at all."""
    vases = make_vases(5, seed=8, resolution=(12, 16), pose=False)
    extra = [Z_TO_Y, np.eye(3), np.eye(3), Z_TO_MINUS_Z, np.eye(3)]
    meshes = [v.mesh.with_vertices(v.mesh.vertices @ r.T) for v, r in zip(vases, extra)]
    prepared = prepare_collection(meshes, align="consensus")
    for s, r, v in zip(prepared, extra, vases):
        assert (s.transform.rotation @ r @ v.pose.rotation)[2, 2] == pytest.approx(1.0, abs=1e-6)
    assert [s.orientation_changed for s in prepared] == [True, False, False, True, False]
    for s in (prepared[1], prepared[2], prepared[4]):
        assert np.array_equal(s.transform.rotation, np.eye(3))


def test_consensus_is_deterministic(small_vases):
    meshes = [s.mesh for s in small_vases[:4]]
    a = prepare_collection(meshes, align="consensus", seed=5)
    b = prepare_collection(meshes, align="consensus", seed=5)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.mesh.vertices, y.mesh.vertices)


# ---------------------------------------------------------------------------- errors
def test_bad_arguments(small_vases):
    meshes = [s.mesh for s in small_vases[:2]]
    with pytest.raises(ValueError, match="unknown align mode"):
        prepare_collection(meshes, align="best")
    with pytest.raises(ValueError, match="unknown scale mode"):
        prepare_collection(meshes, scale="area")
    with pytest.raises(ValueError, match="unknown centre mode"):
        prepare_collection(meshes, centre="middle")
    with pytest.raises(ValueError, match="unknown up axis"):
        prepare_collection(meshes, up_axis="w")
    with pytest.raises(CollectionError, match="empty"):
        prepare_collection([])


def test_flat_shape_cannot_be_scaled_by_bbox():
    flat = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), [[0, 1, 2]], name="flat")
    other = Mesh(np.eye(3) + 0.1, [[0, 1, 2]], name="tri")
    from shapegen_core.base.errors import MeshError

    with pytest.raises(MeshError, match="flat: cannot scale by bbox"):
        prepare_collection([flat, other], align="none", scale="bbox")
