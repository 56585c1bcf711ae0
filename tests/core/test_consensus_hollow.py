"""Top and bottom by which way a shape's hollow opens (core/preprocess/hollow.py):
a cup turned upside down inside an upright class whose walls taper either way is put
right (the Chamfer cost and the odd moments see an upright cup of the opposite taper),
or flagged with that reason when its pose is kept; consistent cups, which are surfaces of
revolution with no facing at all, are left alone."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.demo_data.revolved import _revolved_mesh
from shapegen_core.demo_data import make_barrels
from shapegen_core.meshes.mesh import Mesh
from shapegen_core.preprocess import ConsensusSettings, ShapeTransform, prepare_collection
from shapegen_core.preprocess.consensus import HollowSettings
from shapegen_core.preprocess.hollow import Hollows, opening_vector
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS, yaw_rotation

UPSIDE_DOWN = AXIS_ROTATIONS[4]  # half turn about x
ON_ITS_SIDE = AXIS_ROTATIONS[9]
NO_HOLLOWS = ConsensusSettings(hollows=HollowSettings(opening=np.inf))


def _cups(n: int, seed: int) -> list[tuple[Mesh, float]]:
    """(cup, taper): closed cups of revolution open at the top (outer wall, rim, inner
    wall, inner floor), walls tapering either way, random size and position."""
    rng = np.random.default_rng(seed)
    cups = []
    for i in range(n):
        radius, height = rng.uniform(0.8, 1.2), rng.uniform(1.4, 2.4)
        taper, wall, bottom = rng.uniform(-0.25, 0.25), rng.uniform(0.1, 0.14), rng.uniform(0.12, 0.2)
        outer_z, inner_z = np.linspace(0.0, height, 8), np.linspace(height, bottom, 8)
        outer = radius * (1.0 + taper * (outer_z / height - 0.5))
        inner = radius * (1.0 + taper * (inner_z / height - 0.5)) - wall
        profile = np.concatenate([[[0.0, 0.0]], np.stack([outer, outer_z], axis=1),
                                  np.stack([inner, inner_z], axis=1), [[0.0, bottom]]])
        vertices, faces = _revolved_mesh(profile, lambda theta, z: np.ones_like(theta), rng, int(rng.integers(24, 36)))
        place = ShapeTransform(np.eye(3), rng.uniform(0.5, 2.0), rng.uniform(-1.0, 1.0, 3))
        cups.append((Mesh(place.to_normalised(vertices), faces, name=f"cup_{i:02d}"), float(taper)))
    return cups


def _flipped_widest_topped(seed: int) -> tuple[list[Mesh], int]:
    """Ten cups, the one widest at the top turned upside down (it then looks like an
    upright cup narrowing upwards)."""
    cups = _cups(10, seed)
    flipped = int(np.argmax([taper for _, taper in cups]))
    return [m.with_vertices(m.vertices @ UPSIDE_DOWN.T) if i == flipped else m
            for i, (m, _) in enumerate(cups)], flipped


def _up_error(shape, turn: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((shape.transform.rotation @ turn)[2, 2], -1.0, 1.0))))


def test_opening_vector_points_out_of_the_open_end():
    cup = _cups(1, 0)[0][0]
    upright = opening_vector(cup, np.eye(3), 40, 0)
    assert upright[2] > 0.3 and np.hypot(*upright[:2]) < 0.05
    assert opening_vector(cup, UPSIDE_DOWN, 40, 0)[2] < -0.3
    assert abs(opening_vector(cup, ON_ITS_SIDE, 40, 0)[2]) < 0.05
    # a turn of the shape turns the vector (computed once in the base pose)
    turned = opening_vector(cup, ON_ITS_SIDE, 40, 0)
    assert np.linalg.norm(turned - ON_ITS_SIDE @ upright) < 0.05
    barrel = make_barrels(1, seed=0, pose=False)[0]
    assert np.linalg.norm(opening_vector(barrel, np.eye(3), 40, 0)) < 0.02


def test_upside_down_needs_every_reference_and_the_floor():
    hollows = Hollows([np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 0.45]), np.array([0.0, 0.0, 0.05])])
    up = [(1, np.eye(3))]
    assert hollows.upside_down(0, np.eye(3), up, 0.1) is None
    own, theirs = hollows.upside_down(0, UPSIDE_DOWN, up, 0.1)
    assert own == pytest.approx(-0.5) and theirs == pytest.approx(0.45)
    # a reference whose hollow hardly opens up or down cannot tell
    assert hollows.upside_down(0, UPSIDE_DOWN, [(1, np.eye(3)), (2, np.eye(3))], 0.1) is None
    # turned about up: still upright
    assert hollows.upside_down(0, yaw_rotation(70.0), up, 0.1) is None


@pytest.mark.quality
def test_cup_upside_down_that_the_cost_misses_is_turned_by_its_hollow():
    """Seed 5: without the hollows the upside-down cup is left upside down (only flagged as
    an unusual shape); with them it is turned back and the reason says why."""
    meshes, flipped = _flipped_widest_topped(5)
    without = prepare_collection(meshes, consensus=NO_HOLLOWS)  # a taper alone turns nobody over
    assert _up_error(without[flipped], UPSIDE_DOWN) > 170.0
    assert not any(shape.orientation_changed for shape in without)
    prepared = prepare_collection(meshes)
    assert _up_error(prepared[flipped], UPSIDE_DOWN) < 1.0, prepared[flipped].pose_change
    assert "its hollow opens downwards" in prepared[flipped].pose_change
    for i, shape in enumerate(prepared):
        assert shape.pose_outlier == ""
        if i != flipped:
            assert not shape.orientation_changed and np.array_equal(shape.pose_rotation, np.eye(3))


@pytest.mark.quality
def test_kept_upside_down_cup_is_flagged_with_its_hollow():
    meshes, flipped = _flipped_widest_topped(5)
    kept = prepare_collection(meshes, keep_pose=[i == flipped for i in range(len(meshes))])
    assert not kept[flipped].orientation_changed
    reason = kept[flipped].pose_outlier
    assert "upside down" in reason and "hollow opens downwards" in reason and "kept by request" in reason
    assert all(s.pose_outlier == "" for i, s in enumerate(kept) if i != flipped)


@pytest.mark.quality
def test_flip_the_cost_objects_to_is_flagged_not_made():
    """When the cost objects to the flip more than hollows.cost allows (0: always), the
    hollow does not turn the cup; the pose check still flags it by its hollow."""
    meshes, flipped = _flipped_widest_topped(5)
    prepared = prepare_collection(meshes, consensus=ConsensusSettings(hollows=HollowSettings(cost=0.0)))
    assert _up_error(prepared[flipped], UPSIDE_DOWN) > 170.0
    assert "hollow opens downwards" in prepared[flipped].pose_outlier


@pytest.mark.quality
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_consistent_cups_keep_their_poses(seed):
    """Upright cups of revolution: no turn (their facing is triangulation noise, no
    facing), no flag."""
    prepared = prepare_collection([m for m, _ in _cups(10, seed)])
    assert all(not s.orientation_changed and s.pose_outlier == "" for s in prepared)
