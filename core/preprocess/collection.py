"""A prepared collection: aligned, scaled and landmarked shapes, saved as one `.npz`.

This is the hand-off from intake (§3.4 alignment, §4.2.1 landmarks) to correspondence.
`prepare_meshes` runs both steps with one `PrepareSettings`; `PreparedCollection.save/load`
persist the result (meshes in the normalised frame, the per-shape transforms back to input
coordinates, each shape's pose report — `pose_change`, `pose_rotation`, `pose_outlier` —,
the landmarks and the settings used, as one JSON string). `keep_pose` names the shapes
whose pose Prepare must not turn, recorded per shape (`pose_kept`, so the
correspondence does not pose them by their landmarks either; files written before read as
not kept). A collection read from a folder that left out files it could not read
(`reading.read_readable`) records them by file name with the reader's message (`unreadable`),
so every later file says which inputs it lacks; files written before the record load
with none.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..base.errors import CollectionError, ModelFileError
from .landmarks import DEFAULT_LANDMARKS, MIN_LANDMARKS, Landmarks, select_landmarks
from ..meshes import meshset
from ..meshes.mesh import Mesh
from ..base.npzfile import ArraySpec, load_npz, save_npz, validate_arrays
from . import ALIGN_MODES, CENTRE_MODES, SCALE_MODES, UP_AXES, PreparedShape, ShapeTransform, prepare_collection
from .prepare import turn_as_flagged
from ..base.progress import CancelCheck, Progress, sub_range
from ..base.settings import Settings, option, recorded_settings
from ..meshes.spill import REGISTRATION_PROXY, StoredMesh, loaded

__all__ = ["PrepareSettings", "PreparedCollection", "prepare_meshes", "kept_poses", "pose_notes", "PREPARED_FORMAT",
           "PREPARED_VERSION", "unreadable_arrays", "recorded_unreadable"]

PREPARED_FORMAT = "shapegen.prepared"
PREPARED_VERSION = 1


@dataclass(frozen=True)
class PrepareSettings(Settings):
    """How a collection is aligned, scaled and landmarked (thesis §3.4, §4.2.1)."""

    n_landmarks: int = option(DEFAULT_LANDMARKS, "landmarks per shape", flag="--landmarks", minimum=MIN_LANDMARKS)
    up_axis: str = option("z", "input axis that points up", flag="--up", choices=UP_AXES)
    align: str = option("consensus", "orientation: per-shape PCA, PCA then agreement with the collection "
                        "(consensus), or none", flag="--align", choices=ALIGN_MODES)
    scale: str = option("variance", "scaling rule", flag="--scale", choices=SCALE_MODES)
    centre: str = option("centroid", "horizontal centring", flag="--centre", choices=CENTRE_MODES)
    seed: int = option(0, "random seed", flag="--seed", minimum=0)


#: Arrays of a prepared-collection file besides its settings (one JSON string, "null": not
#: recorded; `settings.recorded_settings` also reads the key/value strings of older files).
_SPEC = {
    "names": ArraySpec("U", ("M",)),
    **meshset.spec(),
    "transforms": ArraySpec("f", ("M", 4, 4)),
    "orientation_changed": ArraySpec("b", ("M",)),
    "landmarks": ArraySpec("f", ("Ltot", 3)),
    "landmark_faces": ArraySpec("i", ("Ltot",)),
    "landmark_barycentric": ArraySpec("f", ("Ltot", 3)),
    "landmark_offsets": ArraySpec("i", ("M+1",)),
    "landmark_radius": ArraySpec("f", ("M",)),
}

#: The pose report of each shape; files written before it was saved have none (read as
#: kept, identity, not flagged).
_POSE_SPEC = {
    "pose_change": ArraySpec("U", ("M",)),
    "pose_rotation": ArraySpec("f", ("M", 3, 3)),
    "pose_outlier": ArraySpec("U", ("M",)),
}

#: Keep Pose per shape (optional: files written before the record read as not kept).
_KEPT_SPEC = {"pose_kept": ArraySpec("b", ("M",))}

#: The turn each flag suggests (identity: none); files written before Turn Flagged have
#: none (read as no suggestion).
_FLAG_SPEC = {"flag_turn": ArraySpec("f", ("M", 3, 3))}

#: The files of the source folder left out because they could not be read: file names and
#: the reader's messages (optional: files written before the record have none).
_UNREADABLE_SPEC = {"unreadable_files": ArraySpec("U", ("K",)), "unreadable_reasons": ArraySpec("U", ("K",))}


def unreadable_arrays(unreadable: dict[str, str]) -> dict[str, np.ndarray]:
    """The arrays recording the files left out as unreadable ({file name: message})."""
    return {"unreadable_files": np.asarray(list(unreadable), dtype=str).reshape(-1),
            "unreadable_reasons": np.asarray(list(unreadable.values()), dtype=str).reshape(-1)}


def recorded_unreadable(arrays, label: str) -> dict[str, str]:
    """{file name: message} of the files a file records as left out unreadable (none when
    it has no record); a malformed record is a ModelFileError starting with `label`."""
    if not any(key in arrays for key in _UNREADABLE_SPEC):
        return {}
    validate_arrays(arrays, _UNREADABLE_SPEC, label)
    return dict(zip(arrays["unreadable_files"].tolist(), arrays["unreadable_reasons"].tolist()))


@dataclass
class PreparedCollection:
    """Prepared shapes with their landmarks; `settings` says how they were prepared (None:
    not recorded, e.g. a collection assembled from shapes prepared elsewhere)."""

    shapes: list[PreparedShape]
    landmarks: list[Landmarks]
    settings: PrepareSettings | None = None
    unreadable: dict[str, str] = field(default_factory=dict)  # files left out of the folder: {file name: why}

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.shapes]

    def __len__(self) -> int:
        return len(self.shapes)

    def pose_notes(self) -> list[str]:
        """What Prepare did to the poses, one line per turned or flagged shape (`pose_notes`)."""
        return pose_notes(self.names, [s.pose_change for s in self.shapes], [s.pose_outlier for s in self.shapes])

    def flagged(self) -> list[str]:
        """Names of the shapes whose flag suggests a turn (what Turn Flagged turns)."""
        return [s.name for s in self.shapes if s.flag_turn is not None]

    def turn_flagged(self, names: Sequence[str] | None = None) -> "PreparedCollection":
        """A copy with the named flagged shapes (None: every one) turned as their flags
        suggest (`preprocess.turn_as_flagged`), their landmarks carried along; the user's
        answer to a flag, the one way Prepare's doubt becomes a turn."""
        wanted = set(self.flagged() if names is None else names)
        unknown = wanted - set(self.names)
        if unknown:
            raise CollectionError(f"no shape named {', '.join(sorted(unknown))} in this collection")
        centre = self.settings.centre if self.settings is not None else "centroid"
        shapes, landmarks = [], []
        for shape, marks in zip(self.shapes, self.landmarks):
            if shape.name in wanted and shape.flag_turn is not None:
                shape, step = turn_as_flagged(shape, centre)
                marks = Landmarks(step.to_normalised(marks.points), marks.face_index, marks.barycentric, marks.radius)
            shapes.append(shape)
            landmarks.append(marks)
        return PreparedCollection(shapes, landmarks, self.settings, dict(self.unreadable))

    def landmarks_input(self, index: int) -> np.ndarray:
        """Landmarks of shape `index` in that input mesh's own coordinates."""
        return self.shapes[index].transform.to_input(self.landmarks[index].points)

    # ------------------------------------------------------------------ persistence
    def to_arrays(self, lazy: bool = False) -> dict[str, np.ndarray]:
        """The file's arrays (`lazy`: the meshes as `npzfile.Concatenation`s)."""
        l_off = np.cumsum([0] + [len(l) for l in self.landmarks])
        return {
            "names": np.asarray(self.names, dtype=str),
            **meshset.pack([s.mesh.vertices for s in self.shapes], [s.mesh.faces for s in self.shapes], lazy=lazy),
            "transforms": np.stack([s.transform.matrix for s in self.shapes]),
            "orientation_changed": np.asarray([s.orientation_changed for s in self.shapes]),
            "pose_change": np.asarray([s.pose_change for s in self.shapes], dtype=str),
            "pose_rotation": np.stack([s.pose_rotation for s in self.shapes]),
            "pose_outlier": np.asarray([s.pose_outlier for s in self.shapes], dtype=str),
            "flag_turn": np.stack([np.eye(3) if s.flag_turn is None else s.flag_turn for s in self.shapes]),
            "pose_kept": np.asarray([s.pose_kept for s in self.shapes], dtype=bool),
            "landmarks": np.concatenate([l.points for l in self.landmarks]),
            "landmark_faces": np.concatenate([l.face_index for l in self.landmarks]),
            "landmark_barycentric": np.concatenate([l.barycentric for l in self.landmarks]),
            "landmark_offsets": l_off.astype(np.int64),
            "landmark_radius": np.asarray([l.radius for l in self.landmarks]),
            "settings": np.asarray("null" if self.settings is None else self.settings.to_json()),
            **unreadable_arrays(self.unreadable),
        }

    def save(self, path: str | os.PathLike) -> Path:
        return save_npz(path, PREPARED_FORMAT, PREPARED_VERSION, self.to_arrays(lazy=True), stored=meshset.stored())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "PreparedCollection":
        a = load_npz(path, PREPARED_FORMAT, PREPARED_VERSION, _SPEC)
        m = len(a["names"])
        pose = {key: a[key] for key in _POSE_SPEC if key in a}
        if pose:
            validate_arrays(a, _SPEC | _POSE_SPEC, str(path))
        else:
            pose = {"pose_change": np.full(m, ""), "pose_rotation": np.tile(np.eye(3), (m, 1, 1)),
                    "pose_outlier": np.full(m, "")}
        turns = a["flag_turn"] if "flag_turn" in a else np.tile(np.eye(3), (m, 1, 1))
        if "flag_turn" in a:
            validate_arrays(a, _SPEC | _FLAG_SPEC, str(path))
            if not np.all(np.isfinite(turns)) or not np.allclose(turns @ np.swapaxes(turns, 1, 2), np.eye(3), atol=1e-6):
                raise ModelFileError(f"{path}: array 'flag_turn' holds a matrix that is not a rotation")
        kept = np.zeros(m, dtype=bool)
        if "pose_kept" in a:
            validate_arrays(a, _SPEC | _KEPT_SPEC, str(path))
            kept = a["pose_kept"]
        lo = a["landmark_offsets"]
        if len(lo) != m + 1 or lo[0] != 0 or lo[-1] != len(a["landmarks"]) or np.any(np.diff(lo) < 0):
            raise ModelFileError(f"{path}: array 'landmark_offsets' is inconsistent with the data it indexes")
        meshes = meshset.unpack(a, a["names"].tolist(), str(path))
        shapes, landmarks = [], []
        for i, mesh in enumerate(meshes):
            name = mesh.name
            try:
                transform = ShapeTransform.from_matrix(a["transforms"][i])
            except ValueError as exc:
                raise ModelFileError(f"{path}: shape {name!r} is invalid: {exc}") from None
            turn = None if np.allclose(turns[i], np.eye(3)) else turns[i]
            shapes.append(PreparedShape(mesh, transform, bool(a["orientation_changed"][i]), pose["pose_rotation"][i],
                                        str(pose["pose_change"][i]), str(pose["pose_outlier"][i]), turn,
                                        bool(kept[i])))
            sl = slice(lo[i], lo[i + 1])
            faces = a["landmark_faces"][sl]
            if faces.size and (faces.min() < 0 or faces.max() >= mesh.n_faces):
                raise ModelFileError(f"{path}: shape {name!r} has landmark face indices out of range")
            landmarks.append(Landmarks(a["landmarks"][sl], faces, a["landmark_barycentric"][sl],
                                       float(a["landmark_radius"][i])))
        return cls(shapes, landmarks, recorded_settings(PrepareSettings, a, str(path)),
                   recorded_unreadable(a, str(path)))


def prepare_meshes(
    meshes: Sequence[Mesh],
    settings: PrepareSettings = PrepareSettings(),
    min_shapes: int = 2,
    progress: Progress | None = None,
    should_cancel=None,
    keep_pose: Sequence[str] | Sequence[bool] | None = None,
) -> PreparedCollection:
    """Align, scale and landmark a collection (thesis §3.4 and §4.2.1). `keep_pose`: the
    names of the shapes whose pose is kept (never turned beyond the up axis, still
    checked and flagged), or one bool per mesh. `progress` and `should_cancel` as in
    core/base/progress.py; cancel is checked at every progress step. Dense meshes kept on disk
    (`spill.StoredMesh`, from `reading.read_folder(spill=...)`) stay there: each is loaded for
    its own steps, its prepared shape is stored beside it with its registration proxy
    (`spill.REGISTRATION_PROXY`, built here at full density, once)."""
    meshes = list(meshes)
    if len(meshes) < min_shapes:
        names = ", ".join(m.name or "?" for m in meshes) or "none"
        raise CollectionError(
            f"a collection needs at least {min_shapes} meshes to learn from, got {len(meshes)} ({names})"
        )
    names = [m.name for m in meshes]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise CollectionError(f"shape names must be unique; repeated: {duplicates}")
    keep = kept_poses(names, keep_pose)
    report = CancelCheck(should_cancel, "prepare").before(progress)
    shapes = prepare_collection(
        meshes, up_axis=settings.up_axis, align=settings.align, centre=settings.centre, scale=settings.scale,
        seed=settings.seed, progress=sub_range(report, 0.0, 0.6), keep_pose=keep,
    )
    landmarks = []
    for i, shape in enumerate(shapes):
        with loaded(shape.mesh) as mesh:  # a stored dense mesh (core/meshes/spill.py): loaded for its own steps only
            landmarks.append(select_landmarks(mesh, settings.n_landmarks, seed=settings.seed + i))
            if isinstance(shape.mesh, StoredMesh):  # built here, at full density, once (correspondence reuses it)
                shape.mesh.keep_proxy(mesh, REGISTRATION_PROXY)
        report(0.6 + 0.4 * (i + 1) / len(shapes), f"landmarks on {shape.name}")
    return PreparedCollection(shapes, landmarks, settings)


def kept_poses(names: Sequence[str], keep_pose: Sequence[str] | Sequence[bool] | None) -> list[bool]:
    """One bool per shape of `names` from `keep_pose`: shape names, or already one bool
    per shape (None: keep none). An unknown name is a CollectionError naming it."""
    keep_pose = [] if keep_pose is None else list(keep_pose)
    if keep_pose and all(isinstance(k, (bool, np.bool_)) for k in keep_pose):
        if len(keep_pose) != len(names):
            raise CollectionError(f"keep_pose has {len(keep_pose)} entries for {len(names)} shapes")
        return [bool(k) for k in keep_pose]
    unknown = [str(k) for k in keep_pose if k not in names]
    if unknown:
        raise CollectionError(f"keep pose: no shape named {', '.join(map(repr, unknown))} in the collection "
                              f"(shapes: {', '.join(names)})")
    kept = set(keep_pose)
    return [n in kept for n in names]


def pose_notes(names: Sequence[str], changes: Sequence[str], outliers: Sequence[str]) -> list[str]:
    """One line per turned shape ("vase_003: turned 180° about x: ..."), then one per shape
    whose pose looks wrong ("vase_007: pose looks wrong: upside down relative to ...");
    `changes` and `outliers` are the shapes' pose_change and pose_outlier."""
    return ([f"{n}: {c}" for n, c in zip(names, changes) if c]
            + [f"{n}: pose looks wrong: {o}" for n, o in zip(names, outliers) if o])
