"""The one Chamfer distance (core/geometry/chamfer.py): against brute force, in rotation,
and as a pairwise matrix."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from shapegen_core.geometry.chamfer import chamfer_distance, chamfer_matrix


def brute_force(a, b):
    d2 = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)
    return d2.min(axis=1).mean() + d2.min(axis=0).mean()


def test_matches_brute_force_and_is_symmetric():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(40, 3)), rng.normal(size=(25, 3)) + 0.3
    assert chamfer_distance(a, b) == pytest.approx(brute_force(a, b), rel=1e-12)
    assert chamfer_distance(a, b) == pytest.approx(chamfer_distance(b, a), rel=1e-12)
    assert chamfer_distance(a, a) == 0.0


def test_rotation_turns_the_first_set_and_reuses_the_trees():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(30, 3)), rng.normal(size=(35, 3))
    R = Rotation.random(random_state=2).as_matrix()
    expected = brute_force(a @ R.T, b)
    assert chamfer_distance(a, b, R) == pytest.approx(expected, rel=1e-12)
    assert chamfer_distance(a, b, R, cKDTree(a), cKDTree(b)) == chamfer_distance(a, b, R)
    assert chamfer_distance(a, a @ R.T, R) == pytest.approx(0.0, abs=1e-24)


def test_matrix_is_symmetric_with_zero_diagonal():
    rng = np.random.default_rng(3)
    sets = [rng.normal(size=(20 + 5 * k, 3)) * (1 + k) for k in range(4)]
    M = chamfer_matrix(sets)
    assert np.array_equal(M, M.T) and np.all(np.diag(M) == 0.0)
    for i in range(4):
        for j in range(4):
            if i != j:
                assert M[i, j] == pytest.approx(brute_force(sets[i], sets[j]), rel=1e-12)
