"""Orientation you can trust: consensus turns nobody when the inputs
agree, restores a perturbed subset where the evidence is clear and flags the rest without
moving anyone else, respects keep_pose, reports every change and flags a doubtful pose
with its reason and a turn Turn Flagged makes."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.demo_data import make_barrels, make_vases
from shapegen_core.preprocess import ShapeTransform, prepare_collection
from shapegen_core.preprocess.prepare import turn_as_flagged
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS, describe_rotation, rotation_angle, yaw_rotation

UPSIDE_DOWN = AXIS_ROTATIONS[4]  # 180° about x
ON_ITS_SIDE = AXIS_ROTATIONS[9]  # +x up, then a quarter turn
HALF_TURN = yaw_rotation(180.0)


def _upright(n: int, seed: int, kind: str) -> list:
    """Consistent input: upright, facing +x, random size and position."""
    rng = np.random.default_rng(seed)
    meshes = make_barrels(n, seed=seed, pose=False) if kind == "barrel" else \
        [v.mesh for v in make_vases(n, seed=seed, resolution=(12, 16), pose=False)]
    return [m.with_vertices(ShapeTransform(np.eye(3), rng.uniform(0.5, 2), rng.uniform(-1, 1, 3))
                            .to_normalised(m.vertices)) for m in meshes]


def _turned(meshes, turns: dict) -> list:
    return [m.with_vertices(m.vertices @ turns[i].T) if i in turns else m for i, m in enumerate(meshes)]



@pytest.mark.quality
@pytest.mark.parametrize("kind,seed", [("vase", 2), ("barrel", 3)])
def test_consistent_input_keeps_every_pose_exactly(kind, seed):
    prepared = prepare_collection(_upright(10, seed, kind))
    for shape in prepared:
        assert np.array_equal(shape.transform.rotation, np.eye(3))
        assert np.array_equal(shape.pose_rotation, np.eye(3))
        assert not shape.orientation_changed and shape.pose_change == "" and shape.pose_outlier == ""


@pytest.mark.quality
def test_perturbed_subset_is_restored_or_flagged_and_nobody_else_moves():
    """The orientation policy on barrels (nearly symmetric top to bottom: only the odd moments
    tell the ends apart): turns about up are undone, a shape on its side is stood on
    its axis (its end on weak evidence, flagged), a barrel upside down is flagged, not
    turned; Turn Flagged stands it up; nobody else moves."""
    meshes = _upright(10, 5, "barrel")
    turns = {1: UPSIDE_DOWN, 4: ON_ITS_SIDE, 6: yaw_rotation(37.0), 8: HALF_TURN}
    prepared = prepare_collection(_turned(meshes, turns))
    assert not prepared[1].orientation_changed and "may be upside down" in prepared[1].pose_outlier
    assert "file-convention turn" in prepared[4].pose_change
    # its end rests on weak evidence (the odd moments): right here, and flagged
    assert (prepared[4].pose_rotation @ turns[4])[2, 2] > np.cos(np.radians(3.0))
    assert prepared[4].pose_outlier.startswith("may be upside down: stood on another axis")
    assert "37° about -z" in prepared[6].pose_change and "facing" in prepared[6].pose_change
    assert rotation_angle(prepared[8].pose_rotation @ turns[8]) < 3.0
    for i, shape in enumerate(prepared):
        if i not in turns:
            assert np.array_equal(shape.pose_rotation, np.eye(3)) and not shape.orientation_changed
            assert shape.pose_outlier == ""
    turned, _ = turn_as_flagged(prepared[1])  # the user answers barrel 1's flag: stood up
    assert (turned.pose_rotation @ turns[1])[2, 2] > np.cos(np.radians(3.0)), turned.pose_change


@pytest.mark.quality
def test_keep_pose_is_respected_and_the_wrong_pose_flagged():
    meshes = _turned(_upright(10, 7, "barrel"), {2: UPSIDE_DOWN})
    keep = [i == 2 for i in range(10)]
    prepared = prepare_collection(meshes, keep_pose=keep)
    assert np.array_equal(prepared[2].pose_rotation, np.eye(3)) and not prepared[2].orientation_changed
    assert "upside down" in prepared[2].pose_outlier and "kept by request" in prepared[2].pose_outlier
    assert all(not s.orientation_changed and s.pose_outlier == "" for i, s in enumerate(prepared) if i != 2)
    with pytest.raises(ValueError, match="keep_pose has 2 entries for 10 shapes"):
        prepare_collection(meshes, keep_pose=[True, False])


@pytest.mark.parametrize("turn,words", [(UPSIDE_DOWN, "upside down"), (ON_ITS_SIDE, "on its side")])
def test_wrong_pose_is_flagged_without_consensus(turn, words):
    """align 'none' turns nobody, but a shape upside down or on its side inside an upright
    class is named with its reason."""
    prepared = prepare_collection(_turned(_upright(8, 11, "vase"), {3: turn}), align="none")
    assert words in prepared[3].pose_outlier
    assert [bool(s.pose_outlier) for s in prepared] == [i == 3 for i in range(8)]


def test_pca_reports_its_turn():
    prepared = prepare_collection(_upright(3, 1, "vase"), align="pca")
    for shape in prepared:
        assert shape.pose_change.endswith("(align pca)") == shape.orientation_changed


def test_describe_rotation():
    assert describe_rotation(np.eye(3)) == "unturned"
    assert describe_rotation(UPSIDE_DOWN) == "turned 180° about x"
    assert describe_rotation(yaw_rotation(-37.0)) == "turned 37° about -z"
    assert describe_rotation(AXIS_ROTATIONS[8]) == "turned 90° about -y"
