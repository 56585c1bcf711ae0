"""Part labels of faces, read beside the training meshes and carried to every sample.

A training mesh `<name>.<ext>` may have part labels beside it in `<name>_labels.txt`, the
Princeton Segmentation Benchmark's form: blocks of a part-name line followed by a line of
the file's 1-based face ids in that part. A sample is its template training mesh moved
(§6: embedded deformation keeps the template's faces), so every face of a sample has the
part of the template face it is, and labelled training data comes at no extra cost.

* `mesh_face_labels`: the part of every face of a mesh as the core read it (`Mesh.faces`,
  welded triangles) from its file's labels: each triangle is matched to the file polygon
  it was cut from by its corners; the few the intake made itself (none of a polygon's fan
  triangles) take a neighbour's part.
* `written_face_labels`: the part of every face of a written copy of that mesh, in the
  file's face order (the template's file polygons for OBJ and PLY when it has a layout,
  their fan triangles for OFF, STL and glTF, else the mesh triangles).
* `PartLabels`: the parts of every training mesh's faces, one list of part names for the
  model (the model file's `label_names` and `mesh_face_labels`).
* `read_label_file` / `write_label_file`: the text form; a written file covers every face
  (faces no part names, if any, are the part "unlabelled").
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..base.errors import ShapeGenError
from .mesh import Mesh

__all__ = ["LABELS_SUFFIX", "UNLABELLED", "LabelFileError", "PartLabels", "label_path", "labels_beside",
           "read_label_file", "write_label_file", "mesh_face_labels", "written_face_labels"]

LABELS_SUFFIX = "_labels.txt"
#: the part name of faces no label names, in written label files
UNLABELLED = "unlabelled"


class LabelFileError(ShapeGenError, ValueError):
    """A labels file that cannot be read as part labels (the message names the file)."""


def label_path(mesh_path: str | os.PathLike) -> Path:
    """Where the labels of a mesh file are: `<stem>_labels.txt` beside it."""
    mesh_path = Path(mesh_path)
    return mesh_path.with_name(mesh_path.stem + LABELS_SUFFIX)


def read_label_file(path: str | os.PathLike, n_faces: int) -> tuple[list[str], np.ndarray]:
    """(part names, part index of each of the file's `n_faces` faces, -1 where none)."""
    path = Path(path)
    try:
        lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise LabelFileError(f"{path}: cannot read the labels file ({exc})") from None
    if len(lines) % 2:
        raise LabelFileError(f"{path}: labels come in pairs of lines (a part name, then its face ids); "
                             f"the last part '{lines[-1][:40]}' has no face ids")
    names: list[str] = []
    part = np.full(n_faces, -1, dtype=np.int64)
    for name, ids_line in zip(lines[0::2], lines[1::2]):
        try:
            ids = np.asarray(ids_line.split(), dtype=np.int64)
        except ValueError:
            raise LabelFileError(f"{path}: part '{name}': face ids must be whole numbers") from None
        if ids.size and (ids.min() < 1 or ids.max() > n_faces):
            bad = int(ids[(ids < 1) | (ids > n_faces)][0])
            raise LabelFileError(f"{path}: part '{name}': face {bad} does not exist (the mesh file has "
                                 f"{n_faces} faces, numbered from 1)")
        index = names.index(name) if name in names else len(names)
        if index == len(names):
            names.append(name)
        taken = part[ids - 1]
        if np.any((taken >= 0) & (taken != index)):
            face = int(ids[(taken >= 0) & (taken != index)][0])
            raise LabelFileError(f"{path}: face {face} is in two parts ('{names[part[face - 1]]}' and '{name}')")
        part[ids - 1] = index
    return names, part


def write_label_file(path: str | os.PathLike, names: list[str], part: np.ndarray) -> Path:
    """The labels file of faces with parts `part` (index into `names`, -1: none), every
    face in one part (`UNLABELLED` for -1), written whole (temporary name, then renamed)."""
    part = np.asarray(part, dtype=np.int64)
    blocks = []
    for index, name in [(i, n) for i, n in enumerate(names)] + [(-1, UNLABELLED)]:
        ids = np.flatnonzero(part == index) + 1
        if ids.size:
            blocks.append(f"{name}\n{' '.join(map(str, ids.tolist()))}\n")
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        tmp.write_text("".join(blocks))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _triple_keys(triangles: np.ndarray, n: int) -> np.ndarray:
    """One int64 per triangle of vertex indices < n, the same for any order of its corners."""
    t = np.sort(np.asarray(triangles, dtype=np.int64), axis=1)
    return (t[:, 0] * n + t[:, 1]) * n + t[:, 2]


def _fans(sizes: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) the fan triangles of polygons (sizes, corners), and the polygon of each."""
    first = np.repeat(np.cumsum(sizes) - sizes, sizes - 2)
    offset = np.concatenate([np.arange(1, s - 1) for s in sizes.tolist()])
    return corners[np.stack([first, first + offset, first + offset + 1], axis=1)], np.repeat(np.arange(len(sizes)),
                                                                                             sizes - 2)


def _lookup(keys: np.ndarray, values: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """values[i] where keys[i] == query, -1 where no key matches."""
    order = np.argsort(keys, kind="stable")
    keys, values = keys[order], values[order]
    at = np.clip(np.searchsorted(keys, queries), 0, max(len(keys) - 1, 0))
    found = (len(keys) > 0) & (keys[at] == queries) if len(keys) else np.zeros(len(queries), bool)
    return np.where(found, values[at], -1)


def _fill_from_neighbours(faces: np.ndarray, part: np.ndarray, n_vertices: int) -> np.ndarray:
    """Faces without a part (-1) take the part of a face sharing a vertex, repeatedly; those
    with no labelled face near them stay -1."""
    part = part.copy()
    for _ in range(20):
        missing = part < 0
        if not missing.any() or missing.all():
            break
        vertex_part = np.full(n_vertices, -1, dtype=np.int64)
        labelled = ~missing
        vertex_part[faces[labelled].ravel()] = np.repeat(part[labelled], 3)
        near = vertex_part[faces[missing]].max(axis=1)
        if not np.any(near >= 0):
            break
        part[np.flatnonzero(missing)] = near
    return part


def mesh_face_labels(mesh: Mesh, file_sizes: np.ndarray, file_corners: np.ndarray,
                     file_part: np.ndarray) -> np.ndarray:
    """The part (-1: none) of every face of `mesh` (as the core read it from a file whose
    polygons are `file_sizes`, `file_corners` in file vertex indices, `file_part` the part
    of each polygon): through the mesh vertex of each file vertex (`report.vertex_map`)."""
    sizes, corners = np.asarray(file_sizes, dtype=np.int64), np.asarray(file_corners, dtype=np.int64)
    vertex_map = mesh.report.vertex_map
    on_mesh = corners if vertex_map is None else np.asarray(vertex_map)[corners]
    fans, polygon = _fans(sizes, on_mesh)
    n = mesh.n_vertices
    part = _lookup(_triple_keys(fans, n), np.asarray(file_part, dtype=np.int64)[polygon],
                   _triple_keys(mesh.faces, n))
    return _fill_from_neighbours(np.asarray(mesh.faces, dtype=np.int64), part, n)


def written_face_labels(template: Mesh, face_part: np.ndarray, file_format: str) -> np.ndarray:
    """The part of every face of a written copy of `template` (its faces' parts
    `face_part`) in `file_format`, in the written file's face order (module docstring)."""
    face_part = np.asarray(face_part, dtype=np.int64)
    layout = template.report.layout
    if layout is None:
        return face_part
    fans, polygon = _fans(layout.sizes, layout.vertex_map[layout.corners])
    n = template.n_vertices
    fan_part = _lookup(_triple_keys(template.faces, n), face_part, _triple_keys(fans, n))
    polygon_part = np.full(len(layout.sizes), -1, dtype=np.int64)
    np.maximum.at(polygon_part, polygon, fan_part)  # any fan triangle the mesh has
    if np.any(polygon_part < 0):  # a polygon the intake cut otherwise: the part at its first corner
        vertex_part = np.full(n, -1, dtype=np.int64)
        vertex_part[template.faces.ravel()] = np.repeat(face_part, 3)
        first = layout.vertex_map[layout.corners[np.cumsum(layout.sizes) - layout.sizes]]
        polygon_part = np.where(polygon_part < 0, vertex_part[first], polygon_part)
    if file_format.lower().lstrip(".") in ("obj", "ply"):
        return polygon_part
    return np.repeat(polygon_part, layout.sizes - 2)


def labels_beside(mesh_path: str | os.PathLike, mesh: Mesh) -> tuple[list[str], np.ndarray] | None:
    """(part names, part of each face of `mesh`) from the labels beside its file, None when
    it has none. `mesh` is the file as the core read it (its vertices may have moved)."""
    from .reading import file_faces

    path = label_path(mesh_path)
    if not path.is_file():
        return None
    sizes, corners = file_faces(mesh_path)
    names, file_part = read_label_file(path, len(sizes))
    return names, mesh_face_labels(mesh, sizes, corners, file_part)


@dataclass(frozen=True)
class PartLabels:
    """Part names and, per training mesh, the part of each face (-1: none; all -1 for a
    mesh whose file had no labels)."""

    names: tuple[str, ...]
    parts: tuple[np.ndarray, ...]

    @classmethod
    def merge(cls, found: list[tuple[list[str], np.ndarray] | None], n_faces: list[int]) -> "PartLabels | None":
        """One name list for every mesh's labels (`labels_beside` results, None where a mesh
        has none); None when no mesh has labels."""
        if all(item is None for item in found):
            return None
        names: list[str] = []
        parts = []
        for item, count in zip(found, n_faces):
            if item is None:
                parts.append(np.full(count, -1, dtype=np.int64))
                continue
            local, part = item
            for name in local:
                if name not in names:
                    names.append(name)
            to_global = np.asarray([names.index(name) for name in local] + [-1], dtype=np.int64)
            parts.append(to_global[np.asarray(part, dtype=np.int64)])  # -1 -> the appended -1
        return cls(tuple(names), tuple(parts))
