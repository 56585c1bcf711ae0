"""Embedded deformation (thesis §6): closed-form cases, fast path, smoothing."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.spatial import cKDTree

from shapegen_core.demo_data import make_vases
from shapegen_core.generate.deform import (DeformInputError, DeformSettings, EmbeddedDeformer, LinearMeshMap,
                                           blend_matrix, cotangent_laplacian, enclosed_volume, smooth_curvature_flow)
from shapegen_core.geometry import stiffness_matrix
from shapegen_core.preprocess.landmarks import select_landmarks


def knn_edges(points: np.ndarray, k: int = 6) -> np.ndarray:
    _, index = cKDTree(points).query(points, k + 1)
    edges = np.sort(np.stack([np.repeat(np.arange(len(points)), k), index[:, 1:].ravel()], axis=1), axis=1)
    return np.unique(edges, axis=0)


@pytest.fixture(scope="module")
def setup():
    shapes = make_vases(2, seed=0, resolution=(20, 28), pose=False)
    template = shapes[0].mesh
    landmarks = select_landmarks(template, 200, seed=0)
    deformer = EmbeddedDeformer(template, landmarks.points, knn_edges(landmarks.points))
    return shapes, template, landmarks, deformer


@pytest.mark.parametrize("schedule", ["relax", "single"])
def test_own_landmarks_return_the_template(setup, schedule):
    _, template, landmarks, deformer = setup
    out = deformer.deform(landmarks.points, schedule)
    assert np.abs(out.vertices - template.vertices).max() <= 1e-9


@pytest.mark.parametrize("schedule", ["relax", "single"])
def test_global_affine_of_landmarks_is_that_affine_of_the_mesh(setup, schedule):
    _, template, landmarks, deformer = setup
    rng = np.random.default_rng(1)
    matrix = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
    shift = rng.standard_normal(3)
    out = deformer.deform(landmarks.points @ matrix.T + shift, schedule)
    np.testing.assert_allclose(out.vertices, template.vertices @ matrix.T + shift, atol=1e-9)


def test_fast_path_equals_the_single_alpha_solve(setup):
    shapes, _, landmarks, deformer = setup
    st = shapes[0].surface_coordinates(landmarks.face_index, landmarks.barycentric)
    targets = shapes[1].points_at(st)
    fast = LinearMeshMap(deformer)
    np.testing.assert_allclose(fast.vertices(targets), deformer.deform(targets, "single").vertices, atol=1e-10)
    # affine map: vertices(U + c B) = vertices(U) + c linear_part(B)
    direction = targets - landmarks.points
    moved = fast.vertices(landmarks.points) + 0.7 * fast.linear_part(direction[None])[0]
    np.testing.assert_allclose(fast.vertices(landmarks.points + 0.7 * direction), moved, atol=1e-10)


def test_normal_equations_match_dense_least_squares():
    rng = np.random.default_rng(3)
    nodes = rng.standard_normal((7, 3))
    edges = knn_edges(nodes, 3)
    targets = nodes + 0.1 * rng.standard_normal(nodes.shape)
    alpha, gamma = 0.7, 2.0
    x = np.zeros((len(nodes), 4 * len(nodes)))  # row j holds [x_j, 1] in columns 4j..4j+3
    for j, node in enumerate(nodes):
        x[j, 4 * j:4 * j + 4] = np.r_[node, 1.0]
    incidence = np.zeros((len(edges), len(nodes)))
    incidence[np.arange(len(edges)), edges[:, 0]] = 1
    incidence[np.arange(len(edges)), edges[:, 1]] = -1
    b = np.vstack([alpha * np.kron(incidence, np.diag([1, 1, 1, gamma])), x])
    c = np.vstack([np.zeros((4 * len(edges), 3)), targets])
    dense, *_ = np.linalg.lstsq(b, c, rcond=None)
    np.testing.assert_allclose(stiffness_matrix(edges, len(nodes), gamma).toarray(),
                               (np.kron(incidence, np.diag([1, 1, 1, gamma])).T
                                @ np.kron(incidence, np.diag([1, 1, 1, gamma]))))
    mesh = make_vases(1, seed=0, resolution=(8, 8))[0].mesh
    deformer = EmbeddedDeformer(mesh, nodes, edges, DeformSettings(final_alpha=alpha, gamma=gamma))
    np.testing.assert_allclose(deformer.solve_affines(nodes, targets, alpha), dense, atol=1e-10)


def test_blend_weights_are_a_partition_of_unity_over_k_nearest_nodes():
    rng = np.random.default_rng(0)
    nodes = rng.standard_normal((30, 3))
    vertices = rng.standard_normal((100, 3))
    w = blend_matrix(vertices, nodes, 4)
    per_node = np.asarray(w[:, 3::4].todense())  # the weight column of each node (times 1)
    np.testing.assert_allclose(per_node.sum(axis=1), 1.0)
    assert np.all((per_node > 0).sum(axis=1) <= 4)
    _, nearest = cKDTree(nodes).query(vertices, 1)
    assert np.all(per_node[np.arange(100), nearest] == per_node.max(axis=1))


def test_deforming_to_another_vase_follows_its_ground_truth(setup):
    shapes, template, landmarks, deformer = setup
    st = shapes[0].surface_coordinates(landmarks.face_index, landmarks.barycentric)
    targets = shapes[1].points_at(st)
    truth = shapes[1].points_at(shapes[0].vertex_st)
    diagonal = shapes[1].mesh.bbox_diagonal()
    low = EmbeddedDeformer(template, landmarks.points, deformer.edges, DeformSettings(final_alpha=0.1))
    error_low = np.linalg.norm(low.deform(targets).vertices - truth, axis=1).mean() / diagonal
    error_high = np.linalg.norm(deformer.deform(targets).vertices - truth, axis=1).mean() / diagonal
    before = np.linalg.norm(template.vertices - truth, axis=1).mean() / diagonal
    assert error_low < 0.02 < before
    assert error_low < error_high  # low stiffness follows landmarks more closely


def test_cotangent_laplacian_matches_trimesh_area_and_is_symmetric():
    mesh = make_vases(1, seed=2, resolution=(12, 14))[0].mesh
    laplacian = cotangent_laplacian(mesh)
    assert abs(laplacian - laplacian.T).max() < 1e-12
    np.testing.assert_allclose(np.asarray(laplacian.sum(axis=1)).ravel(), 0, atol=1e-9)
    # Σ_i v_i · (L v)_i = −2 · (Dirichlet energy); for the coordinate functions it is −2 · area
    energy = -0.5 * np.einsum("ij,ij->", mesh.vertices, laplacian @ mesh.vertices)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert energy == pytest.approx(tm.area, rel=1e-9)


def test_smoothing_reduces_noise_and_keeps_volume():
    shape = make_vases(1, seed=4, resolution=(30, 34))[0]
    mesh = shape.mesh
    rng = np.random.default_rng(0)
    noisy = mesh.with_vertices(mesh.vertices + 0.2 * mesh.mean_edge_length()
                               * rng.standard_normal(mesh.vertices.shape))
    smoothed = smooth_curvature_flow(noisy, 3)

    def roughness(m):  # mean |Δ_cot x| / mean edge length
        return np.linalg.norm(cotangent_laplacian(m) @ m.vertices, axis=1).mean() / m.mean_edge_length()

    assert roughness(smoothed) < 0.5 * roughness(noisy)
    # stated bound: volume of a closed mesh preserved to 1e-9 relative
    assert enclosed_volume(smoothed) == pytest.approx(enclosed_volume(noisy), rel=1e-9)
    # and one gentle step brings the noisy surface closer to the clean one
    clean = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    gentle = smooth_curvature_flow(noisy, 1, step=0.1)
    _, d_noisy, _ = trimesh.proximity.closest_point(clean, noisy.vertices)
    _, d_gentle, _ = trimesh.proximity.closest_point(clean, gentle.vertices)
    assert d_gentle.mean() < 0.8 * d_noisy.mean()


def test_bad_targets_are_refused_with_a_clear_error(setup):
    _, _, landmarks, deformer = setup
    with pytest.raises(DeformInputError, match="template has"):
        deformer.deform(landmarks.points[:-1])
    bad = landmarks.points.copy()
    bad[5, 1] = np.nan
    with pytest.raises(DeformInputError, match="landmark 5 is NaN"):
        deformer.deform(bad)
    with pytest.raises(DeformInputError, match="template has"):
        LinearMeshMap(deformer).vertices(np.zeros((3, 3)))


def test_stiffness_gram_is_sparse_and_has_rigid_null_space():
    nodes = np.random.default_rng(0).standard_normal((50, 3))
    gram = stiffness_matrix(knn_edges(nodes), 50, 2.0)
    assert sp.issparse(gram) and gram.nnz < 0.2 * gram.shape[0] ** 2
    identity = np.tile(np.vstack([np.eye(3), np.zeros((1, 3))]), (50, 1))
    assert np.abs(gram @ identity).max() < 1e-12  # equal affines cost nothing
