"""Each shape's pose in the model frame from its corresponded landmarks (**beyond** the
thesis, whose shapes all share the pose Prepare gives them, §3.4).

Prepare decides a shape's pose from its surface alone (core/preprocess). On an
articulated collection it can leave a shape lying or upside down: it flags the shape but
does not turn it, and a linear model (§5.3) then learns the turn as a deformation (a
lying body becomes a direction of variation, its samples crouch between standing and
lying). Once landmarks correspond, the landmarks themselves say how a shape lies: the
rigid motion that best fits its landmarks onto the template shape's (Procrustes, Kabsch
1976) is its pose. This module finds that motion for every shape whose landmarks may be
trusted for it (`landmark_poses`):

* only shapes registered from the intrinsic start (start.py): an intrinsic map follows the
  body whatever way it lies, so the landmarks of a lying shape sit on the same body parts
  as the template's. A closest-point registration starts from the template as it lies in
  the prepared frame: on a shape in another pose its landmarks slide to whatever surface
  is near, so their fit says where the template was put, not how the shape lies (and its
  correspondence already lives in the prepared frame, where it was made);
* never a shape the user marked Keep Pose (`PreparedShape.pose_kept`): its pose is theirs;
* not the template shape, the reference itself.

A map that swapped left and right (a mirrored intrinsic map) still tells the up axis: a
body's left–right mirror keeps its up. Its best rotation then turns the shape about its up
to face backwards, where its landmarks lie nearest the template's (measured on TOSCA
people, docs/results.md). Whether a map is mirrored is the correspondence's question (the
start's orientation test, functional_map.py), not the pose's: the best fit with a
reflection did not tell the mirrored maps from the others there (its residual stayed above
the best rotation's on every shape).

The motion is rigid: rotation and translation, no scale. Prepare already made the shapes
one size (§3.4 step 5, from the whole surface), and a scale fitted from landmarks would
confound size with articulation (a crouching body's landmarks spread less than a standing
one's). Rigid, the pose composes with Prepare's similarity into the shape's similarity
from its input to the model frame (`Correspondence.model_transforms`), exactly invertible,
so results still map back to the artist's frame.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..preprocess.rotations import rotation_angle

__all__ = ["rigid_fit", "landmark_poses", "apply_pose", "pose_angle", "POSED_START"]

#: the per-shape start whose landmarks tell a shape's pose (start.py)
POSED_START = "spectral"


def rigid_fit(points: np.ndarray, reference: np.ndarray, proper: bool = True) -> tuple[np.ndarray, float]:
    """(4 × 4 motion T, RMS residual) minimising Σ‖R pᵢ + t − qᵢ‖² over corresponding
    rows of `points` (p) and `reference` (q) (Kabsch 1976, by the SVD of the centred cross
    covariance). `proper`: R a rotation (det +1); else the best orthogonal map with a
    reflection (det −1)."""
    p = np.asarray(points, dtype=np.float64)
    q = np.asarray(reference, dtype=np.float64)
    p_mean, q_mean = p.mean(axis=0), q.mean(axis=0)
    u, _, vt = np.linalg.svd((q - q_mean).T @ (p - p_mean))
    sign = np.sign(np.linalg.det(u @ vt)) or 1.0
    wanted = 1.0 if proper else -1.0
    d = np.diag([1.0, 1.0, sign * wanted])
    rotation = u @ d @ vt
    motion = np.eye(4)
    motion[:3, :3] = rotation
    motion[:3, 3] = q_mean - rotation @ p_mean
    residual = float(np.sqrt((((p @ rotation.T + motion[:3, 3]) - q) ** 2).sum(axis=1).mean()))
    return motion, residual


def apply_pose(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`points` (..., 3) moved by the 4 × 4 rigid `pose`."""
    pose = np.asarray(pose, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ pose[:3, :3].T + pose[:3, 3]


def pose_angle(pose: np.ndarray) -> float:
    """The angle (degrees) of a pose's rotation."""
    return rotation_angle(np.asarray(pose)[:3, :3])


def landmark_poses(points: np.ndarray, template_index: int, shape_starts: Sequence[str], kept: Sequence[bool]
                   ) -> tuple[np.ndarray, list[str]]:
    """Per shape, its pose (M, 4, 4: rigid, prepared → model frame; identity where it is
    not posed) and a note saying how it was posed or why not ("" for the shapes this does
    not concern: closest-point starts and the template shape). `points` (M, L, 3):
    corresponded landmarks in the prepared frame; `template_index`: the template shape,
    whose landmarks are the reference; `shape_starts`: each shape's start ("spectral",
    "closest", "template"); `kept`: each shape's Keep Pose. The rules: the module
    docstring."""
    points = np.asarray(points, dtype=np.float64)
    reference = points[template_index]
    poses = np.tile(np.eye(4), (len(points), 1, 1))
    notes = [""] * len(points)
    for index, (shape, start, keep) in enumerate(zip(points, shape_starts, kept)):
        if index == template_index or start != POSED_START:
            continue
        if keep:
            notes[index] = "pose kept by request (Keep Pose): not posed by its landmarks"
            continue
        motion, _ = rigid_fit(shape, reference)
        poses[index] = motion
        notes[index] = f"posed by its landmarks: turned {pose_angle(motion):.0f}° onto the template"
    return poses, notes
