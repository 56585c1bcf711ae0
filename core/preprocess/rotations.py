"""Rotations of the preparation step (thesis §3.4): the up axis, the horizontal PCA with
its third-moment sign rule, the 24 axis rotations and the turns about z the consensus
searches, and the words that report a rotation ("turned 180° about x").

Axis rotation 4·d + k: up direction d (+z, -z, +x, -x, +y, -y of the up-rotated frame)
turned to +z, then a quarter turn k·90° about z; axis rotation 0 is the identity.
"""

from __future__ import annotations

import numpy as np

from ..meshes.mesh import Mesh
from scipy.spatial.transform import Rotation

from .moments import surface_moments, third_central_moment

__all__ = ["UP_AXES", "up_rotation", "horizontal_pca_rotation", "AXIS_ROTATIONS", "TILTS", "yaw_rotation",
           "turn_rotations", "describe_rotation", "rotation_angle"]

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


def yaw_rotation(degrees: float) -> np.ndarray:
    """Rotation by an angle (degrees) about z; exact 0 / ±1 entries at quarter turns."""
    if float(degrees) % 90.0 == 0.0:
        k = int(round(float(degrees) / 90.0)) % 4
        c, s = (1.0, 0.0, -1.0, 0.0)[k], (0.0, 1.0, 0.0, -1.0)[k]
    else:
        c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


#: proper rotations taking +z, -z, +x, -x, +y, -y (in that order) to +z
TILTS = np.stack([
    np.eye(3),
    np.diag([1.0, -1.0, -1.0]),
    np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
    np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
])

#: the 24 rotations of the cube, (24, 3, 3): number 4·d + k is TILTS[d], then k·90° about z
AXIS_ROTATIONS = np.stack([yaw_rotation(90.0 * k) @ tilt for tilt in TILTS for k in range(4)])


def turn_rotations(yaw_step: float) -> np.ndarray:
    """(24 + 4·(m − 1), 3, 3): the 24 axis rotations, then the upright turns about z on a
    grid of `yaw_step` degrees that are not quarter turns (m = 90 / yaw_step steps per
    quarter): the rotations over which shapes turned about up at random are compared."""
    steps = max(int(round(90.0 / yaw_step)), 1)
    turns = [yaw_rotation(90.0 * k + 90.0 * m / steps) for k in range(4) for m in range(1, steps)]
    return np.concatenate([AXIS_ROTATIONS, np.reshape(turns, (-1, 3, 3))])


def rotation_angle(rotation: np.ndarray) -> float:
    """The angle of a 3 × 3 rotation, degrees: arccos((tr R − 1) / 2)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def describe_rotation(rotation: np.ndarray) -> str:
    """'turned 37° about z' for a rotation (axis and angle, axis named when it is within
    a degree of a coordinate axis, else given as a unit vector); 'unturned' for identity."""
    vector = Rotation.from_matrix(rotation).as_rotvec()
    angle = float(np.degrees(np.linalg.norm(vector)))
    if angle < 0.05:
        return "unturned"
    axis = vector / np.linalg.norm(vector)
    main = int(np.argmax(np.abs(axis)))
    if abs(axis[main]) > np.cos(np.radians(1.0)):
        name = ("-" if axis[main] < 0 else "") + "xyz"[main]
    else:
        name = "(" + ", ".join(f"{a:.2f}" for a in axis) + ")"
    return f"turned {angle:.0f}° about {name}"
