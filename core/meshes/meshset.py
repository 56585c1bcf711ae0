"""Many meshes in a few arrays: concatenated vertices and faces plus offsets.

One layout for every file that holds a collection of meshes (prepared collections, model
files, and the "shapegen.meshes" hand-off from Blender to a worker): `pack` writes it,
`unpack` checks the offsets against the data and cuts the meshes out again.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..base.errors import ModelFileError, ShapeGenError
from .intake import clean_mesh
from .mesh import Mesh
from ..base.npzfile import ArraySpec, Concatenation, load_npz, save_npz, validate_arrays

__all__ = ["pack", "stored", "unpack", "save_mesh_set", "load_mesh_set", "MESHES_FORMAT", "MESHES_VERSION"]

MESHES_FORMAT = "shapegen.meshes"
MESHES_VERSION = 1


def pack(vertices: Sequence[np.ndarray], faces: Sequence[np.ndarray], prefix: str = "",
         lazy: bool = False) -> dict[str, np.ndarray]:
    """`{prefix}vertices`, `{prefix}faces` (concatenated, indices local to each mesh) and
    `{prefix}vertex_offsets`, `{prefix}face_offsets` (M + 1 each). `lazy`: vertices and
    faces as `npzfile.Concatenation`s that `save_npz` streams into the file (no copy of
    every mesh in memory; a stored mesh's arrays, `spill.StoredArray`, read one at a time)."""
    join = Concatenation if lazy else (lambda parts: np.concatenate([np.asarray(part) for part in parts]))
    return {
        f"{prefix}vertices": join(list(vertices)),
        f"{prefix}faces": join(list(faces)),
        f"{prefix}vertex_offsets": np.cumsum([0] + [len(v) for v in vertices]).astype(np.int64),
        f"{prefix}face_offsets": np.cumsum([0] + [len(f) for f in faces]).astype(np.int64),
    }


def spec(prefix: str = "", finite: bool = True) -> dict[str, ArraySpec]:
    """The ArraySpecs of `pack`'s arrays (for load_npz). `finite=False` leaves NaN checks
    to the per-mesh validation of `unpack`, whose error names the mesh, not just the file."""
    return {
        f"{prefix}vertices": ArraySpec("f", (None, 3), finite=finite),
        f"{prefix}faces": ArraySpec("i", (None, 3)),
        f"{prefix}vertex_offsets": ArraySpec("i", ("M+1",)),
        f"{prefix}face_offsets": ArraySpec("i", ("M+1",)),
    }


def unpack(arrays, names: Sequence[str], label: str, prefix: str = "",
           build: Callable[..., Mesh] = Mesh) -> list[Mesh]:
    """The meshes of `pack`'s arrays, named `names`. Offsets that do not match the shape
    count or the data, and invalid meshes, raise ModelFileError starting with `label`.
    `build` makes each mesh: `Mesh` (data already clean) or `intake.clean_mesh` (raw)."""
    vertices, faces = arrays[f"{prefix}vertices"], arrays[f"{prefix}faces"]
    vo, fo = arrays[f"{prefix}vertex_offsets"], arrays[f"{prefix}face_offsets"]
    m = len(names)
    for offsets, total, what in ((vo, len(vertices), "vertex"), (fo, len(faces), "face")):
        if len(offsets) != m + 1 or offsets[0] != 0 or offsets[-1] != total or np.any(np.diff(offsets) < 0):
            raise ModelFileError(f"{label}: {what} offsets do not match the {m} shapes and their data")
    meshes = []
    for i, name in enumerate(names):
        try:
            meshes.append(build(vertices[vo[i]:vo[i + 1]], faces[fo[i]:fo[i + 1]], name=str(name)))
        except ShapeGenError as exc:
            raise ModelFileError(f"{label}: mesh {str(name)!r} is invalid: {exc}") from None
    return meshes


def stored(prefix: str = "") -> tuple[str, ...]:
    """The keys of `pack`'s large arrays, written without compression (`save_npz(stored=)`)."""
    return f"{prefix}vertices", f"{prefix}faces"


def save_mesh_set(path: str | os.PathLike, names: Sequence[str], vertices: Sequence[np.ndarray],
                  faces: Sequence[np.ndarray], compress: bool = True,
                  face_polygons: Sequence[np.ndarray] | None = None) -> Path:
    """A "shapegen.meshes" file: names plus `pack`'s arrays, and optionally the polygon
    each triangle was cut from (`face_polygons`, one (F,) array per mesh: Blender's
    n-gons, so a double-sided polygon is recognised however its two sides were cut;
    intake.clean_mesh `polygon_of`)."""
    arrays = {"names": np.asarray(list(names), dtype=str), **pack(vertices, faces)}
    if face_polygons is not None:
        arrays["face_polygons"] = np.concatenate([np.asarray(p, dtype=np.int64) for p in face_polygons])
    return save_npz(path, MESHES_FORMAT, MESHES_VERSION, arrays, compress=compress)


def load_mesh_set(path: str | os.PathLike) -> list[Mesh]:
    """The meshes of a "shapegen.meshes" file, cleaned like a file's (triangles as read from
    Blender: degenerate ones dropped, duplicates welded, faces wound outwards; see
    intake.clean_mesh), with their polygons when the file records them."""
    specs = {"names": ArraySpec("U", ("M",)), **spec(finite=False)}
    arrays = load_npz(path, MESHES_FORMAT, MESHES_VERSION, specs)
    if "face_polygons" not in arrays:
        return unpack(arrays, arrays["names"].tolist(), str(path), build=clean_mesh)
    validate_arrays(arrays, {"faces": specs["faces"], "face_polygons": ArraySpec("i", ("F",))}, str(path))
    if len(arrays["face_polygons"]) != len(arrays["faces"]):
        raise ModelFileError(f"{path}: face_polygons does not match the faces")
    offsets = arrays["face_offsets"]
    mesh_index = iter(range(len(offsets) - 1))

    def with_polygons(vertices, faces, name):
        i = next(mesh_index)
        return clean_mesh(vertices, faces, name=name, polygon_of=arrays["face_polygons"][offsets[i]:offsets[i + 1]])

    return unpack(arrays, arrays["names"].tolist(), str(path), build=with_polygons)
