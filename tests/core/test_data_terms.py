"""The data term's pieces (core/correspond/data_terms.py, thesis §4.2.2 eq. 4.11) on a flat
square, where every match has a closed form."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.correspond.data_terms import (AnchorTerm, Anchors, BidirectionalTerm, ClosestMatches, ForwardTerm,
                                                 Pulls)
from shapegen_core.correspond.settings import DataTermSettings
from shapegen_core.geometry import TargetSurface

#: the unit square at z = 0, its normal up
SQUARE = TargetSurface(np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]), np.array([[0, 1, 2], [0, 2, 3]]))
POINTS = np.array([[0.2, 0.3, 0.1], [0.7, 0.6, 0.4], [0.5, 0.9, -0.2]])  # template points above and below it
UP = np.tile([0.0, 0.0, 1.0], (3, 1))
LANDMARKS = np.array([[0.25, 0.25, 0.0], [0.5, 0.8, 0.0]])  # target landmarks on it


def _matches(settings=DataTermSettings(), landmark_normals=None):
    return ClosestMatches(SQUARE, SQUARE, LANDMARKS, landmark_normals, settings)


def test_the_forward_term_pulls_every_point_to_its_closest_compatible_point():
    pulls = ForwardTerm(_matches()).pulls(POINTS, UP, None)
    np.testing.assert_array_equal(pulls.rows, [0, 1, 2])
    np.testing.assert_allclose(pulls.goals, POINTS * [1, 1, 0], atol=1e-15)  # straight down (or up) onto the square
    np.testing.assert_array_equal(pulls.weights, [1.0, 1.0, 1.0])
    facing_away = UP * [[1], [-1], [1]]  # 180° from the square's normal: no compatible match within 60°
    pulls = ForwardTerm(_matches()).pulls(POINTS, facing_away, None)
    np.testing.assert_array_equal(pulls.weights, [1.0, 0.0, 1.0])
    np.testing.assert_array_equal(pulls.goals[1], POINTS[1])  # any finite goal: its weight is 0
    plain = ForwardTerm(_matches(DataTermSettings(normal_max_angle=None))).pulls(POINTS, facing_away, None)
    np.testing.assert_array_equal(plain.weights, [1.0, 1.0, 1.0])  # the thesis's plain closest points


def test_distance_weights_are_one_over_one_plus_d_normalised():
    pulls = ForwardTerm(_matches(DataTermSettings(distance_weights=True))).pulls(POINTS, UP, None)
    s = 1.0 / (1.0 + np.abs(POINTS[:, 2]))  # (4.12-4.13)
    np.testing.assert_allclose(pulls.weights, s / s.max(), rtol=1e-14)


def test_the_bidirectional_term_lets_each_landmark_pull_its_closest_template_point_by_lambda():
    pulls = BidirectionalTerm(_matches(), LANDMARKS, 0.5).pulls(POINTS, UP, None)
    nearest = [int(np.argmin(np.linalg.norm(POINTS - u, axis=1))) for u in LANDMARKS]
    np.testing.assert_array_equal(pulls.rows, nearest)
    np.testing.assert_array_equal(pulls.goals, LANDMARKS)
    np.testing.assert_array_equal(pulls.weights, [0.5, 0.5])
    # with normals on both sides, a landmark pulls only a template point facing alike
    landmark_normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    turned = UP * [[1], [1], [-1]]
    pulls = BidirectionalTerm(_matches(landmark_normals=landmark_normals), LANDMARKS, 1.0).pulls(POINTS, turned, None)
    assert 2 not in pulls.rows.tolist()


def test_known_pairs_and_the_stacked_system():
    anchors = Anchors(np.array([2, 0]), np.array([[0.5, 0.5, 0.0], [0.1, 0.1, 0.0]]), weight=7.0)
    terms = [ForwardTerm(_matches()), BidirectionalTerm(_matches(), LANDMARKS, 1.0), AnchorTerm(anchors)]
    stacked = Pulls.stacked([term.pulls(POINTS, UP, None) for term in terms])
    assert stacked.rows.tolist()[3:] == [int(i) for i in terms[1].pulls(POINTS, UP, None).rows] + [2, 0]
    assert stacked.goals.shape == (3 + 2 + 2, 3) and stacked.weights.tolist()[-2:] == [7.0, 7.0]
    with pytest.raises(ValueError, match="anchor weight must be > 0"):
        Anchors(np.array([0]), np.zeros((1, 3)), weight=0.0)
