"""The correspondence of a collection (`Correspondence`) and its versioned .npz file.

The file records how the correspondence was computed (`CorrespondenceSettings`) and how
its collection was prepared (`PrepareSettings`), each as one JSON string ("null": not
recorded); files written before held the correspondence settings as repr strings by key
and no Prepare settings, and still load. Likewise the files its collection's folder left
out because they could not be read (`unreadable`, carried from the prepared collection):
none in files written before. Likewise each shape's pose in the model frame from its
landmarks (`poses`, rigid, prepared → model frame, posing.py): files written before hold
none, and their shapes enter the model as Prepare left them. How the correspondence came
about (iterations, the start each shape took, the notes of posing, the outcome of feature
matches' checks) is an optional record beside it, `diagnostics` (diagnostics.py), saved
in the same file as optional arrays (the format version stays 1).

Frames: `points`, `transforms`, `face_index` and `barycentric` stay in the prepared frame,
where the correspondence was made on the prepared meshes (Blender marks them on the
prepared copies). The shape model learns `model_points` (`landmark_matrix`), each shape
moved by its pose, and its meshes are the prepared meshes moved likewise; so anything that
maps model-frame results back to a shape's input takes `model_transforms` (the pose after
Prepare's transform), never `transforms` alone."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..preprocess.collection import PrepareSettings, recorded_unreadable, unreadable_arrays
from ..base.errors import ModelFileError
from ..base.npzfile import ArraySpec, load_npz, save_npz, validate_arrays
from ..base.settings import recorded_settings
from .diagnostics import CorrespondenceDiagnostics
from .posing import apply_pose
from .features import FALLBACK_SHARE, keeps_features, uses_features
from .settings import CorrespondenceSettings

__all__ = ["Correspondence", "CORRESPONDENCE_FORMAT", "CORRESPONDENCE_SPEC", "CORRESPONDENCE_VERSION"]

CORRESPONDENCE_FORMAT = "shapegen.correspondence"
CORRESPONDENCE_VERSION = 1


@dataclass
class Correspondence:
    """Corresponding landmarks over a collection (the output of `correspond`)."""

    names: list[str]
    points: np.ndarray  # (M, L, 3) normalised (prepared) frame
    points_input: np.ndarray  # (M, L, 3) each shape's input coordinates
    face_index: np.ndarray  # (M, L) face of each point on its shape's prepared mesh
    barycentric: np.ndarray  # (M, L, 3)
    edges: np.ndarray  # (E, 2) symmetrised k-NN graph of the template landmarks
    template_points: np.ndarray  # (L, 3) the template of the last round (normalised frame)
    template_name: str  # the shape the first template came from
    transforms: np.ndarray  # (M, 4, 4) input → normalised frame of every shape
    residuals: np.ndarray  # (M,) fit residual / the shape's bounding-box diagonal
    outliers: np.ndarray  # (M,) bool: fits badly (see outlier_reasons)
    outlier_reasons: list[str]  # "" for shapes that fit
    settings: CorrespondenceSettings | None = None  # how it was computed (None: not recorded)
    prepare: PrepareSettings | None = None  # how its collection was prepared (None: not recorded)
    unreadable: dict[str, str] = field(default_factory=dict)  # files left out of the folder: {file name: why}
    poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # (M, 4, 4) prepared → model, or (0,)
    diagnostics: CorrespondenceDiagnostics | None = None  # how it came about (None: not recorded)

    @property
    def recorded(self) -> CorrespondenceDiagnostics:
        """The diagnostics, or an empty record when there are none (as files written
        before each record read)."""
        return self.diagnostics if self.diagnostics is not None else CorrespondenceDiagnostics()

    @property
    def model_poses(self) -> np.ndarray:
        """(M, 4, 4) each shape's rigid pose, prepared → model frame (identity for every
        shape of a file that records none)."""
        if len(self.poses):
            return np.asarray(self.poses, dtype=np.float64)
        return np.tile(np.eye(4), (len(self.names), 1, 1))

    @property
    def posed(self) -> np.ndarray:
        """(M,) bool: the shapes whose pose moves them (not the identity)."""
        return np.array([not np.array_equal(pose, np.eye(4)) for pose in self.model_poses], dtype=bool)

    def model_points(self) -> np.ndarray:
        """(M, L, 3) the landmarks in the model frame: each posed shape's moved by its pose,
        the others' exactly as corresponded (posing.py)."""
        points = np.array(self.points, dtype=np.float64)
        for index in np.flatnonzero(self.posed):
            points[index] = apply_pose(self.poses[index], points[index])
        return points

    def model_transforms(self) -> np.ndarray:
        """(M, 4, 4) each shape's similarity from its input coordinates to the model frame:
        its pose after Prepare's transform (`transforms`, where it is not posed)."""
        transforms = np.array(self.transforms, dtype=np.float64)
        for index in np.flatnonzero(self.posed):
            transforms[index] = self.poses[index] @ transforms[index]
        return transforms

    @property
    def start_used(self) -> str:
        """The start the correspondence took: as recorded, else (files written before the
        record) the one its settings name, "closest" when they name none."""
        if self.recorded.start:
            return self.recorded.start
        return "closest" if self.settings is None else self.settings.data_term.initialisation

    def start_summary(self) -> str:
        """"spectral start (the shapes lie 11.1× farther apart in space …)": the start
        `initialisation="auto"` chose for the collection and why ("" when the settings
        named the start, and in files written before the record)."""
        reason = self.recorded.start_reason
        if not reason or reason == "asked for":
            return ""
        return f"{self.start_used} start ({reason})"

    def __len__(self) -> int:
        return len(self.names)

    @property
    def n_landmarks(self) -> int:
        return int(self.points.shape[1])

    @property
    def feature_matches_ran(self) -> bool:
        """Whether feature matches (features.py) registered the collection, not closest
        points: never unless the settings asked for them; always when they were not checked
        against closest points (files written before the check); else as the check decided
        (`features.keeps_features`)."""
        if self.settings is None or not uses_features(self.settings):
            return False
        return keeps_features(self.recorded.feature_fit_worse)

    def matching_summary(self) -> str:
        """One line for people: which data term matched the landmarks, and whether the fit
        check (groupwise.py `_checked_feature_fits`) chose closest points instead of feature matches."""
        if self.settings is None:
            return "matches not recorded"
        if not uses_features(self.settings):
            return "closest points"
        worse = np.asarray(self.recorded.feature_fit_worse, dtype=bool)
        count = f"{int(worse.sum())} of {len(self)} shapes"
        if not self.feature_matches_ran:
            return (f"closest points: feature matches fitted {count} worse "
                    f"(more than {FALLBACK_SHARE:.0%})")
        summary = "feature matches" + (f" (they fitted {count} worse than closest points)" if len(worse) else "")
        merged = int(np.count_nonzero(self.recorded.plain_shares))
        if merged:  # features.merged_regions
            summary += (f"; template regions merged on {merged} of {len(self)} shapes, matched there by position "
                        "and normal")
        return summary

    def pose_summary(self) -> str:
        """"12 of 19 shapes posed by their landmarks, 1 kept by request" (posing.py; "" when
        no shape was posed or kept)."""
        posed = int(self.posed.sum())
        kept = sum(note.startswith("pose kept by request") for note in self.recorded.pose_notes)
        if not posed and not kept:
            return ""
        return f"{posed} of {len(self)} shapes posed by their landmarks" + (f", {kept} kept by request" if kept else "")

    def landmark_matrix(self) -> np.ndarray:
        """Y = N × 3L (docs/method.md §4), rows in the model frame (`model_points`)."""
        return self.model_points().reshape(len(self.names), -1)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "names": np.asarray(self.names, dtype=str),
            "points": self.points,
            "points_input": self.points_input,
            "face_index": self.face_index.astype(np.int64),
            "barycentric": self.barycentric,
            "edges": self.edges.astype(np.int64),
            "template_points": self.template_points,
            "template_name": np.asarray(self.template_name, dtype=str),
            "transforms": self.transforms,
            "residuals": self.residuals,
            "outliers": self.outliers.astype(bool),
            "outlier_reasons": np.asarray(self.outlier_reasons, dtype=str),
            "settings": np.asarray(_json(self.settings)),
            "prepare_settings": np.asarray(_json(self.prepare)),
            **unreadable_arrays(self.unreadable),
            "poses": np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4),
            **({} if self.diagnostics is None else self.diagnostics.to_arrays()),
        }

    def save(self, path: str | os.PathLike) -> Path:
        return save_npz(path, CORRESPONDENCE_FORMAT, CORRESPONDENCE_VERSION, self.to_arrays())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Correspondence":
        """Read a file written by `save`; refuses anything else (ModelFileError naming it)."""
        arrays = load_npz(path, CORRESPONDENCE_FORMAT, CORRESPONDENCE_VERSION, CORRESPONDENCE_SPEC)
        return cls._from_validated(arrays, str(path))

    @classmethod
    def from_arrays(cls, arrays, source: str = "correspondence arrays") -> "Correspondence":
        """Rebuild from `to_arrays()` output held in memory (e.g. inside a model file),
        with the same validation as `load`; errors start with `source`."""
        arrays = {k: np.asarray(v) for k, v in dict(arrays).items()}
        validate_arrays(arrays, CORRESPONDENCE_SPEC, source)
        return cls._from_validated(arrays, source)

    @classmethod
    def _from_validated(cls, a: dict, label: str) -> "Correspondence":
        """Checks beyond dtypes and shapes (graph indices, unique names), then build."""
        n_landmarks = a["points"].shape[1]
        edges = a["edges"]
        if edges.size and (edges.min() < 0 or edges.max() >= n_landmarks):
            raise ModelFileError(f"{label}: landmark graph refers to landmarks outside [0, {n_landmarks})")
        if len(set(a["names"].tolist())) != len(a["names"]):
            raise ModelFileError(f"{label}: shape names are not unique")
        return cls(
            names=a["names"].tolist(), points=a["points"], points_input=a["points_input"],
            face_index=a["face_index"], barycentric=a["barycentric"], edges=edges,
            template_points=a["template_points"], template_name=str(a["template_name"]),
            transforms=a["transforms"], residuals=a["residuals"],
            outliers=a["outliers"], outlier_reasons=a["outlier_reasons"].tolist(),
            settings=recorded_settings(CorrespondenceSettings, a, label),
            prepare=recorded_settings(PrepareSettings, a, label, "prepare_settings") if "prepare_settings" in a else None,
            unreadable=recorded_unreadable(a, label), poses=_optional_poses(a, label),
            diagnostics=CorrespondenceDiagnostics.from_arrays(a, len(a["names"]), label),
        )


def _optional_poses(a: dict, label: str) -> np.ndarray:
    """The optional poses of a correspondence file (none in files written before them):
    one rigid motion (rotation with det +1, last row 0 0 0 1) per shape, or none."""
    n = len(a["names"])
    poses = np.asarray(a["poses"]) if "poses" in a else np.zeros((0, 4, 4))
    validate_arrays({"poses": poses}, {"poses": ArraySpec("f", ("S", 4, 4))}, label)
    if len(poses) not in (0, n):
        raise ModelFileError(f"{label}: poses must be empty or one per shape ({n}), got {len(poses)}")
    rotations = poses[:, :3, :3]
    if len(poses) and (not np.all(np.isfinite(poses))
                       or not np.allclose(rotations @ np.swapaxes(rotations, 1, 2), np.eye(3), atol=1e-6)
                       or not np.allclose(np.linalg.det(rotations), 1.0, atol=1e-6)
                       or not np.allclose(poses[:, 3], [0.0, 0.0, 0.0, 1.0])):
        raise ModelFileError(f"{label}: array 'poses' holds a matrix that is not a rigid motion")
    return poses.astype(np.float64)


def _json(settings) -> str:
    return "null" if settings is None else settings.to_json()


#: Arrays of a correspondence file / of `Correspondence.to_arrays()`, as checked on load
#: (the settings are read by `settings.recorded_settings`).
CORRESPONDENCE_SPEC = {
    "names": ArraySpec("U", ("M",)),
    "points": ArraySpec("f", ("M", "L", 3)),
    "points_input": ArraySpec("f", ("M", "L", 3)),
    "face_index": ArraySpec("i", ("M", "L")),
    "barycentric": ArraySpec("f", ("M", "L", 3)),
    "edges": ArraySpec("i", ("E", 2)),
    "template_points": ArraySpec("f", ("L", 3)),
    "template_name": ArraySpec("U", ()),
    "transforms": ArraySpec("f", ("M", 4, 4)),
    "residuals": ArraySpec("f", ("M",)),
    "outliers": ArraySpec("b", ("M",)),
    "outlier_reasons": ArraySpec("U", ("M",)),
}
