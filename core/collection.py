"""A prepared collection: aligned, scaled and landmarked shapes, saved as one `.npz`.

This is the hand-off from intake (§3.4 alignment, §4.2.1 landmarks) to correspondence.
`prepare_meshes` runs both steps; `PreparedCollection.save/load` persist the result
(meshes in the normalised frame, the per-shape transforms back to input coordinates, the
landmarks and the settings used).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .errors import CollectionError, ModelFileError
from .landmarks import DEFAULT_LANDMARKS, Landmarks, select_landmarks
from . import meshset
from .mesh import Mesh
from .npzfile import ArraySpec, load_npz, save_npz
from .preprocess import PreparedShape, ShapeTransform, prepare_collection

__all__ = ["PreparedCollection", "prepare_meshes", "PREPARED_FORMAT", "PREPARED_VERSION"]

PREPARED_FORMAT = "shapegen.prepared"
PREPARED_VERSION = 1


@dataclass
class PreparedCollection:
    shapes: list[PreparedShape]
    landmarks: list[Landmarks]
    settings: dict = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.shapes]

    def __len__(self) -> int:
        return len(self.shapes)

    def landmarks_input(self, index: int) -> np.ndarray:
        """Landmarks of shape `index` in that input mesh's own coordinates."""
        return self.shapes[index].transform.to_input(self.landmarks[index].points)

    # ------------------------------------------------------------------ persistence
    def to_arrays(self) -> dict[str, np.ndarray]:
        l_off = np.cumsum([0] + [len(l) for l in self.landmarks])
        return {
            "names": np.asarray(self.names, dtype=str),
            **meshset.pack([s.mesh.vertices for s in self.shapes], [s.mesh.faces for s in self.shapes]),
            "transforms": np.stack([s.transform.matrix for s in self.shapes]),
            "orientation_changed": np.asarray([s.orientation_changed for s in self.shapes]),
            "landmarks": np.concatenate([l.points for l in self.landmarks]),
            "landmark_faces": np.concatenate([l.face_index for l in self.landmarks]),
            "landmark_barycentric": np.concatenate([l.barycentric for l in self.landmarks]),
            "landmark_offsets": l_off.astype(np.int64),
            "landmark_radius": np.asarray([l.radius for l in self.landmarks]),
            "settings_keys": np.asarray(list(self.settings.keys()), dtype=str),
            "settings_values": np.asarray([str(v) for v in self.settings.values()], dtype=str),
        }

    def save(self, path: str | os.PathLike) -> Path:
        return save_npz(path, PREPARED_FORMAT, PREPARED_VERSION, self.to_arrays())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "PreparedCollection":
        spec = {
            "names": ArraySpec("U", ("M",)),
            **meshset.spec(),
            "transforms": ArraySpec("f", ("M", 4, 4)),
            "orientation_changed": ArraySpec("b", ("M",)),
            "landmarks": ArraySpec("f", ("Ltot", 3)),
            "landmark_faces": ArraySpec("i", ("Ltot",)),
            "landmark_barycentric": ArraySpec("f", ("Ltot", 3)),
            "landmark_offsets": ArraySpec("i", ("M+1",)),
            "landmark_radius": ArraySpec("f", ("M",)),
            "settings_keys": ArraySpec("U", ("S",)),
            "settings_values": ArraySpec("U", ("S",)),
        }
        a = load_npz(path, PREPARED_FORMAT, PREPARED_VERSION, spec)
        m = len(a["names"])
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
            shapes.append(PreparedShape(mesh, transform, bool(a["orientation_changed"][i])))
            sl = slice(lo[i], lo[i + 1])
            faces = a["landmark_faces"][sl]
            if faces.size and (faces.min() < 0 or faces.max() >= mesh.n_faces):
                raise ModelFileError(f"{path}: shape {name!r} has landmark face indices out of range")
            landmarks.append(Landmarks(a["landmarks"][sl], faces, a["landmark_barycentric"][sl],
                                       float(a["landmark_radius"][i])))
        settings = dict(zip(a["settings_keys"].tolist(), a["settings_values"].tolist()))
        return cls(shapes, landmarks, settings)


def prepare_meshes(
    meshes: Sequence[Mesh],
    n_landmarks: int = DEFAULT_LANDMARKS,
    up_axis: str = "z",
    align: str = "consensus",
    scale: str = "variance",
    centre: str = "centroid",
    seed: int = 0,
    min_shapes: int = 2,
    progress: Callable[[float, str], None] | None = None,
) -> PreparedCollection:
    """Align, scale and landmark a collection (thesis §3.4 and §4.2.1)."""
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
    report = progress or (lambda fraction, message: None)
    shapes = prepare_collection(
        meshes, up_axis=up_axis, align=align, centre=centre, scale=scale, seed=seed,
        progress=lambda f, msg: report(0.6 * f, msg),
    )
    landmarks = []
    for i, shape in enumerate(shapes):
        landmarks.append(select_landmarks(shape.mesh, n_landmarks, seed=seed + i))
        report(0.6 + 0.4 * (i + 1) / len(shapes), f"landmarks on {shape.name}")
    settings = {"n_landmarks": n_landmarks, "up_axis": up_axis, "align": align, "scale": scale,
                "centre": centre, "seed": seed}
    return PreparedCollection(shapes, landmarks, settings)
