"""The similarity transform of a prepared shape, input -> normalised frame, with its exact
inverse (thesis §3.4), and the prepared shape that carries it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..meshes.mesh import Mesh

__all__ = ["ShapeTransform", "PreparedShape"]


@dataclass(frozen=True)
class ShapeTransform:
    """Similarity transform input → normalised frame: ``y = scale * R @ x + t``."""

    rotation: np.ndarray  # (3, 3) proper rotation
    scale: float
    translation: np.ndarray  # (3,)

    @property
    def matrix(self) -> np.ndarray:
        """4×4 homogeneous matrix of the forward transform."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def to_normalised(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        return self.scale * points @ self.rotation.T + self.translation

    def to_input(self, points: np.ndarray) -> np.ndarray:
        """Exact inverse: ``x = R^T (y - t) / scale``."""
        points = np.asarray(points, dtype=np.float64)
        return ((points - self.translation) @ self.rotation) / self.scale

    def then(self, rotation=None, scale=1.0, translation=None) -> "ShapeTransform":
        """Compose: apply self, then ``y -> scale * rotation @ y + translation``."""
        rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        translation = np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
        return ShapeTransform(
            rotation @ self.rotation,
            float(scale * self.scale),
            scale * rotation @ self.translation + translation,
        )

    @staticmethod
    def identity() -> "ShapeTransform":
        return ShapeTransform(np.eye(3), 1.0, np.zeros(3))

    @staticmethod
    def from_matrix(matrix: np.ndarray) -> "ShapeTransform":
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
            raise ValueError(f"transform matrix must be a finite 4×4 array, got {matrix.shape}")
        linear = matrix[:3, :3]
        scale = float(np.cbrt(np.linalg.det(linear)))
        if scale <= 0:
            raise ValueError("transform matrix is not a proper similarity (det <= 0)")
        rotation = linear / scale
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-8):
            raise ValueError("transform matrix is not a similarity (rotation part not orthonormal)")
        return ShapeTransform(rotation, scale, matrix[:3, 3].copy())


@dataclass(frozen=True)
class PreparedShape:
    """A shape in the normalised frame with the transform from its input frame."""

    mesh: Mesh  # normalised coordinates
    transform: ShapeTransform
    #: Prepare turned the shape beyond its given up axis (consensus or PCA)
    orientation_changed: bool = False
    #: the turn applied after the up-axis rotation (identity when the pose was kept)
    pose_rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    #: why and how the pose was changed ("turned 180° about x: its 3 nearest shapes
    #: (a, b, c) fit 4.2× better"), empty when it was kept
    pose_change: str = ""
    #: why the pose may be wrong (consensus: flagged and left as it is), empty when it looks right
    pose_outlier: str = ""
    #: the turn (after `pose_rotation`, in the normalised frame) the flag suggests, applied by
    #: `turn_flagged`; None: no suggestion
    flag_turn: np.ndarray | None = None
    #: the user asked to keep its pose (Keep Pose, `--keep-pose`): Prepare never turns it
    #: beyond the up axis, nor does the correspondence pose it by its landmarks
    pose_kept: bool = False

    @property
    def name(self) -> str:
        return self.mesh.name
