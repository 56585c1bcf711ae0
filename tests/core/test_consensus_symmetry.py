"""Up by the collection's evidence and symmetries (core/preprocess/symmetry.py and
step 1 of the consensus): a group of shapes lying on their side together among an upright
majority is stood up or flagged, a flat shape among tall ones is not laid on its side
because they fit it better that way (its own up has the collection's symmetry)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import placed
from shapegen_core.demo_data import make_barrels, make_vases
from shapegen_core.preprocess import ConsensusSettings, prepare_collection
from shapegen_core.preprocess.consensus import CostSettings, PoseDecision
from shapegen_core.preprocess.consensus.state import combined
from shapegen_core.preprocess.posesearch import PoseSearch
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS, yaw_rotation
from shapegen_core.preprocess.symmetry import AxisSymmetry, tilt_to_z

ON_ITS_SIDE = AXIS_ROTATIONS[9]  # +x up, then a quarter turn


def _vases(n: int, seed: int) -> list:
    return [v.mesh for v in make_vases(n, seed=seed, resolution=(12, 16), pose=False)]


def _up_error(shape, turn: np.ndarray) -> float:
    """Degrees between the prepared shape's up and its canonical up (+z before `turn`)."""
    return float(np.degrees(np.arccos(np.clip((shape.transform.rotation @ turn)[2, 2], -1.0, 1.0))))


@pytest.mark.quality
def test_group_lying_together_is_stood_up_or_flagged():
    """Three barrels on their side among upright vases and one upright barrel: the upright
    majority fits each of them better standing on another axis of its file; each is
    stood up (its up within 3° of its own) or, where the evidence is not clear, flagged
    with a suggested turn; nobody else moves."""
    meshes = placed(_vases(8, 4) + make_barrels(4, seed=4, pose=False), 1)
    turns = {9: ON_ITS_SIDE, 10: ON_ITS_SIDE, 11: AXIS_ROTATIONS[17]}
    meshes = [m.with_vertices(m.vertices @ turns[i].T) if i in turns else m for i, m in enumerate(meshes)]
    prepared = prepare_collection(meshes)
    for i, shape in enumerate(prepared):
        if i in turns:
            if shape.orientation_changed:
                # its axis line is up; which end, among vases, nothing in the collection tells
                assert min(_up_error(shape, turns[i]), 180.0 - _up_error(shape, turns[i])) < 3.0, shape.pose_change
                assert "file-convention turn" in shape.pose_change
            else:
                assert "on its side" in shape.pose_outlier and shape.flag_turn is not None
        else:
            assert np.array_equal(shape.pose_rotation, np.eye(3)) and not shape.orientation_changed
            assert shape.pose_outlier == ""


@pytest.mark.quality
def test_flat_shapes_are_not_laid_on_their_side_by_tall_neighbours():
    """Bowls (vases flattened) among tall vases fit them better on their side; the
    symmetry about their up vetoes that change of up, even with no margin."""
    vases = _vases(11, 9)
    bowls = [m.with_vertices(m.vertices * [1.8, 1.8, 0.3]) for m in vases[8:]]
    meshes = placed(vases[:8] + bowls, 3)
    settings = ConsensusSettings(costs=CostSettings(margin=1.0))
    prepared = prepare_collection(meshes, consensus=settings)
    for shape in prepared[8:]:
        assert _up_error(shape, np.eye(3)) < 1.0, shape.pose_change


def test_axis_scores_and_the_tilt_search():
    meshes = make_barrels(6, seed=2, pose=False)
    search = PoseSearch.of(meshes, [np.eye(3)] * 6, 400, 0)
    symmetry = AxisSymmetry.of(search, meshes, [np.eye(3)] * 6, 0, 0.3)
    assert not symmetry.fitted
    symmetry.fit_profile([np.eye(3)] * 6, range(6))
    assert symmetry.fitted
    for j in range(6):
        scores = symmetry.axis_scores(j, np.eye(3))
        assert scores[0] < 1.5 and scores[0] < min(scores[1:]) - 1.0  # up looks like up, x and y do not
        # a barrel turned about up is the same barrel: same descriptor
        np.testing.assert_allclose(symmetry.descriptor(j, yaw_rotation(90.0)), symmetry.descriptor(j, np.eye(3)))
    # a tilted pose scores worse, and the search finds the way back
    tilt = Rotation.from_euler("y", 30, degrees=True).as_matrix()
    assert symmetry.score(0, tilt) > symmetry.score(0, np.eye(3)) + 1.0
    back, score = symmetry.best_up(0, tilt, 40)
    assert np.degrees(np.arccos(np.clip((back @ tilt)[2, 2], -1, 1))) < 5.0
    assert score < symmetry.score(0, tilt)
    # a change of up is allowed only towards an up scoring no worse
    assert not symmetry.allows_tilt(0, ON_ITS_SIDE, np.eye(3))
    assert symmetry.allows_tilt(0, np.eye(3), ON_ITS_SIDE) and symmetry.allows_tilt(0, yaw_rotation(40.0), np.eye(3))


@pytest.mark.parametrize("direction", [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0.3, -0.5, 0.8]])
def test_tilt_to_z(direction):
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    turn = tilt_to_z(direction)
    np.testing.assert_allclose(turn @ direction, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(turn @ turn.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(turn), 1.0)


def test_turned_there_and_back_is_no_change():
    half = yaw_rotation(180.0)
    back = yaw_rotation(180.4) @ half
    merged = combined(PoseDecision(np.eye(3)), PoseDecision(half, "a"), PoseDecision(back, "b"))
    assert not merged.changed and np.array_equal(merged.rotation, np.eye(3))
    merged = combined(PoseDecision(np.eye(3)), PoseDecision(half, "a"), PoseDecision(half))
    assert merged.reason == "a" and np.array_equal(merged.rotation, half)
