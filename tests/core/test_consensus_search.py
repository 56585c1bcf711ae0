"""The measurements behind consensus: remembered pair costs equal the Chamfer
distance they stand for, the up signature from exact moment tensors equals its quadrature
sum, and a search from a start rotation searches around that pose."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from shapegen_core.demo_data import make_vases
from shapegen_core.geometry.chamfer import chamfer_distance
from shapegen_core.preprocess.posesearch import PoseSearch
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS
from shapegen_core.preprocess.signature import Signatures


def _vases(n=4, seed=1):
    return [v.mesh for v in make_vases(n, seed=seed, resolution=(12, 16), pose=False)]


def test_pair_costs_are_the_chamfer_distance_and_remembered():
    meshes = _vases()
    search = PoseSearch.of(meshes, [np.eye(3)] * len(meshes), 200, 0)
    turn = Rotation.random(random_state=3).as_matrix()
    expected = chamfer_distance(search.samples[1], search.samples[2], turn, search.trees[1], search.trees[2])
    assert search.pair_cost(1, 2, turn) == expected
    assert search.cost(1, turn, [(2, np.eye(3))]) == expected
    remembered = len(search._pair_costs)
    assert search.cost(1, turn, [(2, np.eye(3))]) == expected and len(search._pair_costs) == remembered
    # the cost of j against i turned by R_i is that of R_iᵀ R against i in its base pose
    other = Rotation.random(random_state=4).as_matrix()
    assert np.isclose(search.cost(1, turn, [(2, other)]), search.pair_cost(1, 2, other.T @ turn))


def test_up_signature_from_moment_tensors_equals_the_quadrature_sum():
    meshes = _vases(3, seed=2)
    signatures = Signatures(meshes, [np.eye(3)] * 3, 5)
    for j in range(3):
        rotation = Rotation.random(random_state=j).as_matrix()
        points, weights, _ = signatures.quadrature(j)
        points = points @ rotation.T
        z = points[:, 2]
        expected = [weights @ z**3, weights @ (z * (points[:, 0] ** 2 + points[:, 1] ** 2))]
        np.testing.assert_allclose(signatures.up(j, rotation), expected, rtol=1e-10, atol=1e-14)
        # remembered facing is the one computed
        np.testing.assert_array_equal(signatures.facing(j, rotation), signatures._facing_of(j, rotation))


def test_search_from_a_start_rotation():
    """best_rotation(start=S) searches rotations that follow S: a shape whose start is
    its turn back fits best without a further turn, 'upright' keeps S's up."""
    meshes = _vases(4, seed=5)
    turn = AXIS_ROTATIONS[9]  # on its side
    meshes[0] = meshes[0].with_vertices(meshes[0].vertices @ turn.T)
    search = PoseSearch.of(meshes, [np.eye(3)] * 4, 300, 0)
    references = [(i, np.eye(3)) for i in (1, 2, 3)]
    upright, best = search.best_rotation(0, references, 30.0, 2, False, 0.03, start=turn.T)
    # standing again (a vase's facing is left to the signatures), with start's up kept
    assert np.isclose((best.rotation @ turn)[2, 2], 1.0) and np.allclose(upright.rotation[2], turn.T[2])
    assert best.cost == search.cost(0, best.rotation, references)
    _, from_base = search.best_rotation(0, references, 30.0, 2, False, 0.03)
    assert np.isclose((from_base.rotation @ turn)[2, 2], 1.0)
