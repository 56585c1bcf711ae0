"""Prepare's orientation decisions on whole collections: the PSB Airplane and Cup
classes as filed (every shape's decision pinned; no airplane laid on its side), the
airplanes turned at random about up (they end in one pose again), a class
whose files mix the two common up conventions (it ends as the single-convention class
does, PSB cups among them), and upright shapes on one floor (never turned).

A change to a pinned decision updates PINNED in the same commit, with the part-label
transfer before and after (bench/label_transfer_regression.py) in its message."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import Y_UP_FILE, on_a_floor, placed, psb_class, tosca_class, turned
from shapegen_core.demo_data import make_mugs, make_vases
from shapegen_core.geometry import TargetSurface
from shapegen_core.meshes.reading import read_folder
from shapegen_core.preprocess import prepare_collection
from shapegen_core.preprocess.rotations import describe_rotation, rotation_angle, up_rotation, yaw_rotation

#: Prepare's decision for each shape as filed (up y): "kept", or the turn made; "flagged"
#: when its pose is flagged as doubtful
#: (Airplane 62, 63, 64 and 77 and Cup 26, 27, 29, 34 and 37 lie on their sides in their files;
#: four of those cups along the file's z, as files saved z-up would: Cup 34 stands on the
#: end that convention puts up, unflagged)
PINNED = {
    "Airplane": {
        "61": "kept", "62": "turned 125° about (0.52, -0.60, -0.60), flagged",
        "63": "turned 124° about (0.53, -0.60, -0.60), flagged", "64": "turned 90° about x, flagged", "65": "kept",
        "66": "kept", "67": "kept, flagged", "68": "kept", "69": "kept", "70": "kept", "71": "kept", "72": "kept",
        "73": "kept", "74": "kept", "75": "kept", "76": "kept",
        "77": "turned 120° about (0.58, 0.58, 0.58), flagged", "78": "kept", "79": "kept", "80": "kept, flagged",
    },
    "Cup": {
        "21": "turned 180° about z", "22": "kept", "23": "turned 179° about z", "24": "kept", "25": "kept",
        "26": "turned 90° about -y", "27": "turned 90° about -y", "28": "turned 180° about z",
        "29": "turned 90° about -y", "30": "turned 141° about z, flagged", "31": "kept", "32": "kept",
        "33": "kept", "34": "turned 120° about (0.58, -0.57, 0.58)", "35": "kept", "36": "kept",
        "37": "turned 121° about (-0.57, -0.58, 0.58)", "38": "turned 180° about -z", "39": "kept",
        "40": "kept",
    },
}


def _decision(shape) -> str:
    words = describe_rotation(shape.pose_rotation) if shape.pose_change else "kept"
    return words + (", flagged" if shape.pose_outlier else "")



@pytest.fixture(scope="module")
def psb_prepared():
    cache = {}

    def prepared(name: str):
        if name not in cache:
            cache[name] = prepare_collection(read_folder(psb_class(name)), up_axis="y")
        return cache[name]

    return prepared


@pytest.mark.quality
@pytest.mark.parametrize("name", sorted(PINNED))
def test_psb_decisions_as_filed_are_pinned(psb_prepared, name):
    decisions = {shape.name: _decision(shape) for shape in psb_prepared(name)}
    assert decisions == PINNED[name]


#: the PSB airplanes lying on their sides in their files (y up): every other one stands upright
#: as filed, as the part-label transfer of the version before the floor rule showed (94 %)
AIRPLANES_LYING = {"62", "63", "64", "77"}


@pytest.mark.quality
def test_no_psb_airplane_is_laid_on_its_side(psb_prepared):
    """Every airplane upright in its file keeps its file's up (none laid on its side or
    turned over by the floor the centred files seem to share); those lying in their files
    are stood up."""
    for shape in psb_prepared("Airplane"):
        up = shape.pose_rotation[2, 2]  # the file's up (z after the up rotation) against the prepared up
        if shape.name in AIRPLANES_LYING:
            assert abs(up) < np.cos(np.radians(45.0)), (shape.name, shape.pose_change)
        else:
            assert up > np.cos(np.radians(1.0)), (shape.name, shape.pose_change)


def _mixed_against_single(meshes):
    """Prepared as filed and with every third file re-saved y-up (a quarter turn about x
    about its origin): per shape (mixed run, single run, degrees between where the two
    put the same surface)."""
    single = prepare_collection(meshes)
    turns = {i: Y_UP_FILE for i in range(1, len(meshes), 3)}
    mixed = prepare_collection(turned(meshes, turns))
    return [(a, b, rotation_angle(a.transform.rotation @ turns.get(i, np.eye(3)) @ b.transform.rotation.T))
            for i, (a, b) in enumerate(zip(mixed, single))]


MIXED_CLASSES = {
    # solid mugs: no hollow tells top from bottom, and a re-saved file's odd moments lean to
    # the wrong end; the files clearly saved in the other convention tell it instead
    "closed mugs": lambda: placed(make_mugs(10, 0, closed=True, handle_height=(0.3, 0.7), pose=False), 7000),
    "vases": lambda: placed([v.mesh for v in make_vases(12, seed=3, resolution=(12, 16), pose=False)], 1),
    "open mugs on a floor": lambda: on_a_floor(make_mugs(12, 2, closed=False, handle_height=(0.3, 0.7), pose=False), 2),
}


@pytest.mark.quality
def test_airplanes_turned_at_random_about_up_end_in_one_pose(psb_prepared):
    # the real class where the chance majority went wrong: 5 of 20 airplanes ended half
    # a turn from the others, none flagged (random turns of seed 8)
    meshes = read_folder(psb_class("Airplane"))
    up = up_rotation("y")
    as_filed = psb_prepared("Airplane")
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


@pytest.mark.quality
@pytest.mark.parametrize("name", sorted(MIXED_CLASSES))
def test_mixed_file_conventions_end_as_one_convention_does(name):
    """Every third file re-saved y-up (a quarter turn about x about its origin): every
    shape ends within 5° of where the single-convention collection puts it, without Turn
    Flagged, and is flagged only where the single-convention run flags it too (an unusual
    shape)."""
    for a, b, apart in _mixed_against_single(MIXED_CLASSES[name]()):
        assert apart <= 5.0, (a.name, apart, a.pose_change, a.pose_outlier)
        assert bool(a.pose_outlier) == bool(b.pose_outlier), (a.name, a.pose_outlier, b.pose_outlier)


@pytest.mark.quality
def test_mixed_file_conventions_of_a_tosca_class_end_as_one_convention_does():
    """TOSCA's centaurs stand on z = 0 in one pose each; two of six files re-saved y-up (a
    quarter turn about their origin): no majority rests on one floor any more, the costs
    hardly tell a centaur lying from one standing, and every shape still ends within 5° of
    where the single-convention collection puts it (the files' floor, met to a hair by the
    others, and the convention's turn that lands them on it tell)."""
    for a, _, apart in _mixed_against_single(read_folder(tosca_class("centaur"))):
        assert apart <= 5.0, (a.name, apart, a.pose_change, a.pose_outlier)


#: a PSB file (y up) re-saved z-up: a quarter turn about x about its origin
Z_UP_FILE = Y_UP_FILE.T


def _same_surface(prepared, relative: np.ndarray) -> bool:
    """Whether the turn `relative` (prepared frame) leaves the prepared shape where it was:
    within 5°, or a turn about up after which its surface samples lie on its surface (RMS
    distance below 1 % of its RMS radius: a round cup at any turn about its axis)."""
    if rotation_angle(relative) <= 5.0:
        return True
    if relative[2, 2] < np.cos(np.radians(5.0)):
        return False
    mesh = prepared.mesh
    points = mesh.sample_surface(800, np.random.default_rng(0)).points
    centre = mesh.vertices.mean(axis=0)
    radius = np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1)))
    moved = (points - centre) @ relative.T + centre
    distance = np.linalg.norm(TargetSurface(mesh.vertices, mesh.faces).closest(moved).points - moved, axis=1)
    return bool(np.sqrt(np.mean(distance ** 2)) < 0.01 * radius)


@pytest.mark.quality
def test_mixed_file_conventions_of_psb_cups_end_as_filed(psb_prepared):
    """PSB's cups with every third file re-saved z-up: with a third of the files lying
    when read y-up, and five cups lying on their sides in their own files, no upright
    majority remains; the upright cups and those lying on the other convention's up line
    together are most of the collection, so every cup still ends where the files as filed
    put it (within 5°, or turned about its axis where that leaves its surface in place)."""
    meshes = read_folder(psb_class("Cup"))
    turns = {i: Z_UP_FILE for i in range(1, len(meshes), 3)}
    mixed = prepare_collection(turned(meshes, turns), up_axis="y")
    for i, (a, b) in enumerate(zip(mixed, psb_prepared("Cup"))):
        relative = a.transform.rotation @ turns.get(i, np.eye(3)) @ b.transform.rotation.T
        assert _same_surface(b, relative), (a.name, rotation_angle(relative), a.pose_change, a.pose_outlier)


@pytest.mark.quality
def test_upright_shapes_on_a_floor_are_never_turned():
    """Mugs and vases standing on one ground plane as their author put them (origins under
    their bases): nobody is turned over or onto a side."""
    for meshes in (on_a_floor(make_mugs(10, 4, closed=True, handle_height=(0.3, 0.7), pose=False), 5),
                   on_a_floor([v.mesh for v in make_vases(10, seed=6, resolution=(12, 16), pose=False)], 6)):
        for shape in prepare_collection(meshes):
            up = shape.pose_rotation[2, 2]
            assert up > np.cos(np.radians(1.0)), (shape.name, shape.pose_change)
