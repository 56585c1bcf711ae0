"""Radius-based landmarks (§4.2.1, Alg. 2): count within ±2 %, minimum spacing r,
seeded determinism, points on the surface."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shapegen_core.meshes.reading import read_mesh
from shapegen_core.preprocess.landmarks import radius_select, select_landmarks
from shapegen_core.preprocess import prepare_collection

from conftest import psb_class


@pytest.fixture(scope="module")
def vase(small_vases):
    return prepare_collection([s.mesh for s in small_vases[:2]], align="pca")[0].mesh


def _check(mesh, landmarks, requested):
    assert abs(len(landmarks) - requested) <= 0.02 * requested, len(landmarks)
    # no two landmarks closer than (or at) r
    assert cKDTree(landmarks.points).query_pairs(landmarks.radius) == set()
    # every landmark is a surface point given by its face and barycentrics
    on_surface = np.einsum("nk,nkd->nd", landmarks.barycentric, mesh.triangles[landmarks.face_index])
    np.testing.assert_allclose(landmarks.points, on_surface, atol=1e-12)
    np.testing.assert_allclose(landmarks.barycentric.sum(axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("requested", [200, 800])
def test_count_and_spacing(vase, requested):
    landmarks = select_landmarks(vase, requested, seed=0)
    _check(vase, landmarks, requested)
    # r is not needlessly small: the landmarks cover the surface (every dense sample lies
    # within r of a landmark, since Alg. 2 only drops points within r of a kept one)
    dense = vase.sample_surface(5000, np.random.default_rng(9)).points
    gap, _ = cKDTree(landmarks.points).query(dense)
    assert np.quantile(gap, 0.99) < 1.5 * landmarks.radius


def test_deterministic_for_a_seed_and_different_for_another(vase):
    a = select_landmarks(vase, 200, seed=1)
    b = select_landmarks(vase, 200, seed=1)
    c = select_landmarks(vase, 200, seed=2)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.face_index, b.face_index)
    assert a.radius == b.radius
    assert len(c) != len(a) or not np.allclose(c.points, a.points)


def test_radius_select_is_algorithm_2():
    """Fixed radius on a 1-D grid: visiting in order keeps every (k+1)-th point."""
    points = np.c_[np.arange(10.0), np.zeros(10), np.zeros(10)]
    kept = radius_select(points, 1.5, np.arange(10))
    np.testing.assert_array_equal(kept, [0, 2, 4, 6, 8])
    kept = radius_select(points, 1.0, np.arange(10))  # distance exactly r is dropped too
    np.testing.assert_array_equal(kept, [0, 2, 4, 6, 8])
    kept = radius_select(points, 0.5, np.arange(10)[::-1])
    np.testing.assert_array_equal(kept, np.arange(10)[::-1])


def test_rejects_tiny_requests(vase):
    with pytest.raises(ValueError, match="at least 4 landmarks"):
        select_landmarks(vase, 3)
    with pytest.raises(ValueError, match="at least twice"):
        select_landmarks(vase, 100, n_dense=150)


def test_real_mesh_800_landmarks():
    folder = psb_class("Vase")
    mesh = read_mesh(sorted(folder.glob("*.off"))[0])
    landmarks = select_landmarks(mesh, 800, seed=0)
    _check(mesh, landmarks, 800)
