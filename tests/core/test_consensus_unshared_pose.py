"""Prepare on a collection whose inputs share no pose: every file turned about
its up at random. Stage A's Chamfer votes then agree only by chance; the collection
follows one shape from nearest shape to nearest shape, the nearest shapes found at any
turn about up (`PoseSearch.compare_turned`), instead of keeping a chance majority's poses.
The PSB airplanes turned so are in test_orientation_collections, beside their decisions as
filed (one Prepare of the class serves both)."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.preprocess.posesearch import PoseSearch
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS, turn_rotations, yaw_rotation


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
