"""Rotations of the preparation step (thesis §3.4): the up axis, the horizontal PCA with
its third-moment sign rule, and the 24 candidate poses the consensus chooses from.

A candidate pose is numbered 4·d + k: up direction d (+z, -z, +x, -x, +y, -y of the
up-rotated frame) and a quarter turn k·90° about z; candidate 0 is the shape's PCA pose.
"""

from __future__ import annotations

import numpy as np

from ..mesh import Mesh
from .moments import surface_moments, third_central_moment

__all__ = ["UP_AXES", "up_rotation", "horizontal_pca_rotation", "candidate_poses", "half_turn"]

UP_AXES = ("x", "y", "z", "-x", "-y", "-z")


def up_rotation(up_axis: str) -> np.ndarray:
    """Proper rotation taking the named input axis to +z."""
    if up_axis not in UP_AXES:
        raise ValueError(f"unknown up axis {up_axis!r}; choose from {UP_AXES}")
    sign = -1.0 if up_axis.startswith("-") else 1.0
    axis = "xyz".index(up_axis[-1])
    up = np.zeros(3)
    up[axis] = sign
    if axis == 2:
        return np.diag([1.0, sign, sign])  # z: identity; -z: 180° about x
    # new z = up; new x = the next input axis cyclically (x->y->z), y completes right-handed
    new_x = np.zeros(3)
    new_x[(axis + 1) % 3] = 1.0
    new_y = np.cross(up, new_x)
    return np.stack([new_x, new_y, up])  # rows: input -> output basis


def horizontal_pca_rotation(mesh: Mesh) -> np.ndarray:
    """Rotation about z putting the main axis of the x–y spread on x, with +x the side of
    the positive third moment (deterministic sign rule)."""
    _, mean, cov = surface_moments(mesh)
    evals, evecs = np.linalg.eigh(cov[:2, :2])
    main = np.array([evecs[0, 1], evecs[1, 1], 0.0])  # largest eigenvalue last
    if third_central_moment(mesh, main, mean) < 0:
        main = -main
    c, s = main[0], main[1]
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _quarter_turns() -> np.ndarray:
    """Rotations by k·90° about z, k = 0..3, with exact 0 / ±1 entries."""
    out = []
    for k in range(4):
        c, s = np.round(np.cos(k * np.pi / 2)), np.round(np.sin(k * np.pi / 2))
        out.append(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
    return np.stack(out)


def _tilts() -> np.ndarray:
    """Proper rotations taking +z, -z, +x, -x, +y, -y (in that order) to +z."""
    return np.stack([
        np.eye(3),
        np.diag([1.0, -1.0, -1.0]),
        np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
        np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
        np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
        np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    ])


_QUARTER_TURNS = _quarter_turns()
_TILTS = _tilts()


def candidate_poses(mesh: Mesh, up: np.ndarray) -> np.ndarray:
    """The 24 candidate orientations of one shape, (24, 3, 3), index 0 = its PCA pose.

    Candidate 4·d + k: the axis d of the up-rotated frame (+z, -z, +x, -x, +y, -y) is
    turned to +z, the horizontal PCA with its sign rule is redone in that upright frame
    (so a shape lying on its side still gets its own principal horizontal axis on x), then
    a turn of k·90° about z. Every candidate is built from the shape's own moments, so the
    choice between them is the only thing the collection decides.
    """
    _, mean, cov = surface_moments(mesh)
    poses = []
    for d in range(6):
        tilt = _TILTS[d] @ up
        c2 = (tilt @ cov @ tilt.T)[:2, :2]
        _, evecs = np.linalg.eigh(c2)
        main = np.array([evecs[0, 1], evecs[1, 1], 0.0])
        if third_central_moment(mesh, tilt.T @ main, mean) < 0:
            main = -main
        yaw = np.array([[main[0], main[1], 0.0], [-main[1], main[0], 0.0], [0.0, 0.0, 1.0]])
        for k in range(4):
            poses.append(_QUARTER_TURNS[k] @ yaw @ tilt)
    return np.stack(poses)


def half_turn(candidate: int) -> int:
    """The candidate with the same up direction turned a further 180° about z (k <-> k + 2)."""
    return 4 * (candidate // 4) + (candidate % 4 + 2) % 4
