"""Prepare on a collection whose inputs share no pose: every file turned about
its up at random. Stage A's Chamfer votes then agree only by chance; the collection
follows one shape from nearest shape to nearest shape, the nearest shapes found at any
turn about up (`PoseSearch.compare_turned`), instead of keeping a chance majority's poses."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import psb_class
from shapegen_core.meshes.reading import read_folder
from shapegen_core.preprocess import prepare_collection
from shapegen_core.preprocess.posesearch import PoseSearch
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS, rotation_angle, turn_rotations, up_rotation, yaw_rotation



def test_turn_rotations_are_the_axis_rotations_and_the_turns_between_them():
    rotations = turn_rotations(15.0)
    assert len(rotations) == 24 + 4 * 5
    assert np.array_equal(rotations[:24], AXIS_ROTATIONS)
    assert np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    yaws = sorted(round(float(np.degrees(np.arctan2(r[1, 0], r[0, 0]))) % 360) for r in rotations[24:])
    assert yaws == [a for a in range(0, 360, 15) if a % 90]


@pytest.mark.parametrize("exact_shapes", [64, 2])  # 2: the candidate pairs of a large collection
def test_a_copy_turned_between_axis_rotations_is_nearest_once_turns_are_compared(exact_shapes):
    rng = np.random.default_rng(0)
    wing = rng.normal(size=(300, 3)) * [1.0, 0.2, 0.05]  # flat and long: no turn looks alike
    blob = rng.normal(size=(300, 3)) * [0.6, 0.5, 0.4]
    search = PoseSearch([wing, wing @ yaw_rotation(45.0).T, blob], exact_shapes=exact_shapes)
    assert search.distance[0, 1] > search.distance[0, 2]  # at axis rotations the blob is nearer
    search.compare_turned(15.0)
    assert search.distance[0, 1] < 1e-12
    assert search.nearest(0, [1, 2], 1) == [1]


@pytest.mark.quality
def test_airplanes_turned_at_random_about_up_end_in_one_pose():
    # the real class where the chance majority went wrong: 5 of 20 airplanes ended half
    # a turn from the others, none flagged (random turns of seed 8)
    meshes = read_folder(psb_class("Airplane"))[:20]
    up = up_rotation("y")
    as_filed = prepare_collection(meshes, up_axis="y")
    assert not any("no input pose is shared" in p.pose_change for p in as_filed)
    poses = [p.pose_rotation @ up for p in as_filed]  # file -> prepared frame
    angles = np.random.default_rng(8).uniform(0.0, 360.0, len(meshes))
    turns = [pose.T @ yaw_rotation(a) @ pose for pose, a in zip(poses, angles)]  # about each shape's own up
    prepared = prepare_collection([m.with_vertices(m.vertices @ t.T) for m, t in zip(meshes, turns)], up_axis="y")
    # each shape's pose relative to its as-filed result: one common turn for all
    relative = [p.pose_rotation @ up @ t @ pose.T for p, t, pose in zip(prepared, turns, poses)]
    within = [[rotation_angle(a @ b.T) <= 20.0 for b in relative] for a in relative]
    common = relative[int(np.argmax(np.sum(within, axis=1)))]
    # shapes lying on their side in their files (62, 63, 77) are turned about a horizontal
    # axis by a turn about their own up: no file-convention turn undoes that (the
    # orientation policy: flagged or left), so only the shapes upright in their files, and not flagged
    # as maybe upside down there, are counted
    upright = {p.name for p in as_filed if not p.orientation_changed and not p.pose_outlier}
    apart = {p.name: round(rotation_angle(r @ common.T)) for p, r in zip(prepared, relative)
             if rotation_angle(r @ common.T) > 20.0 and p.name in upright}
    # main before the unshared rule: 65, 68, 73, 74 and 75 half a turn apart
    assert len(apart) <= 1, apart
    assert sum("no input pose is shared" in p.pose_change for p in prepared) >= len(meshes) // 2
