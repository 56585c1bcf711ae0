"""The consensus's last step (issue 12, `consensus.restore_flagged`): the pose check of the
settled poses, against every shape's nearest shapes in their final poses, turns a shape
the stages left in a wrong pose (PSB cup 31 faced away but agreed with two neighbours one
by one, so it kept its pose and misled cup 26) and says why; a kept pose is only flagged."""

from __future__ import annotations

import numpy as np

from shapegen_core.datasets import make_vases
from shapegen_core.preprocess import ConsensusSettings
from shapegen_core.preprocess.consensus import PoseDecision, pose_checks, restore_flagged
from shapegen_core.preprocess.posesearch import PoseSearch
from shapegen_core.preprocess.rotations import yaw_rotation
from shapegen_core.preprocess.signature import Signatures

SETTINGS = ConsensusSettings()
FACING_AWAY = 3


def _collection(turn: np.ndarray):
    """Eight upright vases facing +x, vase 3 turned by `turn` in its input; the search and
    signatures of their base poses (as prepare_collection builds them)."""
    meshes = [v.mesh for v in make_vases(8, seed=2, resolution=(12, 16), pose=False)]
    meshes[FACING_AWAY] = meshes[FACING_AWAY].with_vertices(meshes[FACING_AWAY].vertices @ turn.T)
    base = [np.eye(3)] * len(meshes)
    return ([m.name for m in meshes], PoseSearch.of(meshes, base, SETTINGS.points, 0),
            Signatures(meshes, base, SETTINGS.facing_order))


def test_a_pose_the_stages_left_wrong_is_turned_with_its_reason():
    turn = yaw_rotation(150.0)
    names, search, signatures = _collection(turn)
    settled = [PoseDecision(np.eye(3))] * len(names)  # as if every stage had kept every pose
    restored = restore_flagged(search, signatures, names, [False] * len(names), SETTINGS, settled)
    for j, decision in enumerate(restored):
        if j == FACING_AWAY:
            relative = decision.rotation @ turn  # canonical frame -> its prepared pose
            assert np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1))) < 10.0, decision.reason
            assert "nearest shapes in their final poses" in decision.reason
        else:
            assert not decision.changed and np.array_equal(decision.rotation, np.eye(3))
    rechecked = pose_checks(search, signatures, [d.rotation for d in restored], [False] * len(names), SETTINGS)
    assert all(check.reason == "" for check in rechecked)


def test_a_kept_pose_is_flagged_and_not_turned():
    names, search, signatures = _collection(yaw_rotation(150.0))
    keep = [j == FACING_AWAY for j in range(len(names))]
    settled = [PoseDecision(np.eye(3))] * len(names)
    restored = restore_flagged(search, signatures, names, keep, SETTINGS, settled)
    assert all(not d.changed for d in restored)
    check = pose_checks(search, signatures, [d.rotation for d in restored], keep, SETTINGS)[FACING_AWAY]
    assert check.reason and "kept by request" in check.reason and check.rotation is not None


def test_consistent_poses_are_left_alone():
    names, search, signatures = _collection(np.eye(3))
    settled = [PoseDecision(np.eye(3))] * len(names)
    restored = restore_flagged(search, signatures, names, [False] * len(names), SETTINGS, settled)
    assert all(not d.changed and np.array_equal(d.rotation, np.eye(3)) for d in restored)


def test_a_decision_combined_again_lists_its_turns_once():
    """The final pose check combines a shape's stage decision (itself combined from the
    stages that turned it) with its own turn: the reason lists every turn once, under one
    "in all", instead of nesting "in all (... in all (...))"."""
    from shapegen_core.preprocess.consensus import _combined

    first = PoseDecision(yaw_rotation(30.0), "turned 30° about z: stage A")
    second = PoseDecision(yaw_rotation(70.0), "turned 40° about z: stage B")
    stages = _combined(first, second)
    check = PoseDecision(yaw_rotation(160.0), "turned 90° about z: the pose check")
    final = _combined(stages, check)
    assert final.reason.count("in all") == 1
    assert final.steps == ("turned 30° about z: stage A", "turned 40° about z: stage B",
                           "turned 90° about z: the pose check")
    assert final.reason.endswith("(turned 30° about z: stage A; then turned 40° about z: stage B; "
                                 "then turned 90° about z: the pose check)")
    assert np.allclose(final.rotation, yaw_rotation(160.0))
    # a single turn keeps its own reason, no "in all"
    assert _combined(PoseDecision(np.eye(3)), first).reason == first.reason
