"""Positions between turning lines (core/correspond/turning.py; issue 13, beyond the thesis)."""

from __future__ import annotations

import numpy as np
from scipy.stats import spearmanr

from shapegen_core.correspond.turning import NO_LINE, position_between_turning_lines
from shapegen_core.datasets import PROFILE_BREAKS, make_vases
from shapegen_core.landmarks import select_landmarks


def _sphere(count: int) -> np.ndarray:
    """Fibonacci points on the unit sphere (their own normals)."""
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    angle = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(angle), r * np.sin(angle), z], axis=1)


def test_on_a_sphere_it_is_the_latitude_over_a_right_angle():
    # the equator is the one turning line of each hemisphere; geodesic distance from it is
    # the latitude, largest (π/2) at the pole: g = |latitude| / (π/2)
    points = _sphere(6000)
    g = position_between_turning_lines(points, points)
    expected = np.abs(np.arcsin(points[:, 2])) / (np.pi / 2)
    error = np.abs(g - expected)
    # measured 0.020 / 0.049: the line's points lie up to one spacing off the equator
    assert error.mean() < 0.03 and error.max() < 0.06, (error.mean(), error.max())


def test_a_turning_line_in_pieces_is_one_line():
    # the equator broken into two arcs by gaps in the samples (on prepared vases a wide,
    # nearly vertical belly broke into four arcs): both arcs are the hemisphere's line, so g
    # is still the latitude. Measured mean 0.023; with only the lowest piece as the line
    # (before) 0.272, g measured around the sphere from one arc.
    points = _sphere(6000)
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    gaps = (np.abs(points[:, 2]) < 0.15) & ((np.abs(azimuth) < 0.4) | (np.abs(np.abs(azimuth) - np.pi) < 0.4))
    points = points[~gaps]
    g = position_between_turning_lines(points, points)
    error = np.abs(g - np.abs(np.arcsin(points[:, 2])) / (np.pi / 2))
    # measured 0.023 / 0.126 (the largest errors beside the gaps, where the line is missing)
    assert error.mean() < 0.04 and np.percentile(error, 99) < 0.2, (error.mean(), np.percentile(error, 99))


def test_it_does_not_depend_on_scale_or_position():
    points = _sphere(800)
    g = position_between_turning_lines(points, points)
    np.testing.assert_allclose(position_between_turning_lines(3.0 * points + [1.0, -2.0, 0.5], points), g, atol=1e-12)


def test_a_vase_wall_between_belly_and_neck_runs_from_zero_to_one():
    vase = make_vases(1, seed=11, resolution=(65, 130), pose=False)[0]
    # landmarks, and dense surface samples (rank correlations measured 0.985 / -0.940 and 0.999 / -0.996)
    for count, seed, rank in ((800, 0, 0.9), (16000, 1, 0.98)):
        if count == 800:
            landmarks = select_landmarks(vase.mesh, count, seed=seed)
            points, faces, bary = landmarks.points, landmarks.face_index, landmarks.barycentric
        else:
            samples = vase.mesh.sample_surface(count, np.random.default_rng(seed))
            points, faces, bary = samples.points, samples.face_index, samples.barycentric
        g = position_between_turning_lines(points, vase.mesh.face_normals()[faces])
        u = (vase.surface_coordinates(faces, bary)[:, 0] - PROFILE_BREAKS[1]) / (PROFILE_BREAKS[2] - PROFILE_BREAKS[1])
        between = (u > 1 / 3 + 0.03) & (u < 2 / 3 - 0.03)  # outer wall, belly to neck (away from the lines)
        assert spearmanr(u[between], g[between])[0] > rank
        assert g[between].min() < 0.15 and g[between].max() > 0.85
        below = (u > 0.03) & (u < 1 / 3 - 0.03)  # base to belly: one line (the belly) above, g falls towards it
        assert spearmanr(u[below], g[below])[0] < -rank
        assert ((g >= 0) & (g <= 1)).all()


def test_a_surface_facing_one_way_has_no_turning_line():
    rng = np.random.default_rng(0)
    plate = np.c_[rng.uniform(size=(500, 2)), np.zeros(500)]
    up = np.tile([0.0, 0.0, 1.0], (500, 1))
    assert (position_between_turning_lines(plate, up) == NO_LINE).all()
    assert (position_between_turning_lines(plate[:1], up[:1]) == NO_LINE).all()
