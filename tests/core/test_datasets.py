"""Procedural classes: the ground-truth parametrisation must agree with the meshes."""

from __future__ import annotations

import numpy as np

from shapegen_core.demo_data import PROFILE_BREAKS, make_vases, vase_surface


def test_vertices_lie_at_their_surface_coordinates():
    for shape in make_vases(3, seed=5):
        np.testing.assert_allclose(shape.points_at(shape.vertex_st), shape.mesh.vertices, atol=1e-12)


def test_surface_coordinates_of_face_points_round_trip_within_discretisation():
    shape = make_vases(1, seed=2)[0]
    samples = shape.mesh.sample_surface(2000, np.random.default_rng(0))
    st = shape.surface_coordinates(samples.face_index, samples.barycentric)
    # the analytic surface at the interpolated (s, θ) is close to the flat-triangle point
    error = np.linalg.norm(shape.points_at(st) - samples.points, axis=1)
    assert np.median(error) < 0.2 * shape.mesh.mean_edge_length()


def test_meshes_are_closed_outward_and_triangulated_differently():
    shapes = make_vases(4, seed=1)
    counts = {s.mesh.n_vertices for s in shapes}
    assert len(counts) == 4  # different resolutions
    for shape in shapes:
        mesh = shape.mesh
        edges = np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]]), axis=1)
        _, multiplicity = np.unique(edges, axis=0, return_counts=True)
        assert np.all(multiplicity == 2)  # watertight, manifold
        tri = mesh.triangles
        signed_volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
        assert signed_volume > 0  # outward normals
        assert mesh.report.degenerate_faces_dropped == 0


def test_profile_parts_meet_at_the_breakpoints():
    shape = make_vases(1, seed=0, pose=False)[0]
    eps = 1e-9
    for s in PROFILE_BREAKS[1:-1]:
        before = vase_surface(shape.params, np.array([s - eps]), np.array([0.3]))
        after = vase_surface(shape.params, np.array([s + eps]), np.array([0.3]))
        np.testing.assert_allclose(before, after, atol=1e-6)


def test_generation_is_deterministic_for_a_seed():
    a, b = make_vases(2, seed=9), make_vases(2, seed=9)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.mesh.vertices, y.mesh.vertices)
        np.testing.assert_array_equal(x.mesh.faces, y.mesh.faces)
    assert not np.array_equal(make_vases(1, seed=10)[0].mesh.vertices[:10], a[0].mesh.vertices[:10])


def _parted_classes():
    from shapegen_core.demo_data import make_handled_mugs, make_quadrupeds

    return [make_handled_mugs(3, seed=4, resolution=(12, 16)), make_quadrupeds(3, seed=4, resolution=(12, 16))]


def test_parted_shapes_are_closed_outward_parts_at_their_coordinates():
    for shapes in _parted_classes():
        assert len({s.mesh.n_vertices for s in shapes}) > 1  # triangulated differently
        for shape in shapes:
            mesh = shape.mesh
            np.testing.assert_allclose(shape.points_at(shape.vertex_coordinates), mesh.vertices, atol=1e-12)
            part_of_face = shape.vertex_coordinates[mesh.faces, 0]
            assert np.all(part_of_face == part_of_face[:, :1])  # a face never spans two parts
            edges = np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]]), axis=1)
            assert np.all(np.unique(edges, axis=0, return_counts=True)[1] == 2)  # every part closed and manifold
            tri = mesh.triangles
            volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6
            for k in range(len(shape.parts)):
                assert volume[part_of_face[:, 0] == k].sum() > 0  # every part faces outward


def test_parted_surface_coordinates_round_trip_within_discretisation():
    for shapes in _parted_classes():
        shape = shapes[0]
        samples = shape.mesh.sample_surface(2000, np.random.default_rng(0))
        coordinates = shape.surface_coordinates(samples.face_index, samples.barycentric)
        error = np.linalg.norm(shape.points_at(coordinates) - samples.points, axis=1)
        assert np.median(error) < 0.2 * shape.mesh.mean_edge_length()


def test_quadruped_bodies_correspond_by_an_affine_map():
    """Equal body coordinates are an affine map between two quadrupeds' bodies (what the
    ground truth claims geometry can recover): a least-squares affine fits them exactly."""
    from shapegen_core.demo_data import make_quadrupeds

    a, b = make_quadrupeds(2, seed=9, resolution=(12, 16), pose=False)
    rng = np.random.default_rng(1)
    coordinates = np.column_stack([np.zeros(200), rng.uniform(0, 1, 200), rng.uniform(-np.pi, np.pi, 200)])
    pa, pb = a.points_at(coordinates), b.points_at(coordinates)
    affine, *_ = np.linalg.lstsq(np.c_[pa, np.ones(200)], pb, rcond=None)
    np.testing.assert_allclose(np.c_[pa, np.ones(200)] @ affine, pb, atol=1e-9)
