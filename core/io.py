"""Mesh files <-> `Mesh`, through trimesh (no hand-written parsers).

Supported: OBJ, PLY, STL, OFF, GLB/GLTF. Files are read with `process=False` and
`maintain_order=True` (trimesh neither merges nor reorders), then cleaned by
`intake.clean_mesh`: coincident vertices welded, faces wound outwards, what changed in
`Mesh.report`. A clean file keeps its order: vertex i of the file is vertex i of the
Mesh. Polygons are fan-triangulated by trimesh's readers. Every error message starts with
the file's path.

OBJ: trimesh splits a vertex for every distinct (v, vt, vn) corner it meets and repeats
the whole vertex list once per material / object group, which breaks "vertex i of the
file is vertex i of the Mesh" for ordinary exports (and needs PIL as soon as `vt` is
present). Only geometry is wanted here, so the text handed to trimesh keeps the `v`
lines and the `f` lines with each corner reduced to its vertex index; trimesh still
does the parsing and triangulation.

STL stores each triangle with its own three corners (vertex 3k + j of the file is corner j
of triangle k): welded, they become one connected surface, and `report.vertex_map[3k + j]`
is the Mesh vertex of that corner.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import CollectionError, MeshError, MeshFileError
from .intake import clean_mesh
from .mesh import Mesh

__all__ = ["MESH_SUFFIXES", "read_mesh", "read_folder", "list_mesh_files", "write_mesh", "obj_bytes", "ObjWriter",
           "MeshWriters"]

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")


def read_mesh(path: str | os.PathLike, name: str | None = None) -> Mesh:
    """Read one mesh file. The mesh is named after the file's stem unless `name` is given."""
    import trimesh  # imported here: the Blender layer never needs it

    path = Path(path)
    label = str(path)
    name = path.stem if name is None else name
    if not path.is_file():
        raise MeshFileError(f"{label}: no such file")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshFileError(
            f"{label}: unsupported file type '{suffix}' (supported: {', '.join(MESH_SUFFIXES)})"
        )
    if path.stat().st_size == 0:
        raise MeshFileError(f"{label}: file is empty")
    try:
        if suffix == ".obj":
            source = dict(file_obj=io.BytesIO(_obj_geometry_text(path)), file_type="obj")
        else:
            source = dict(file_obj=str(path))
        loaded = trimesh.load(
            **source, force="mesh", process=False, maintain_order=True, skip_materials=True
        )
    except IndexError as exc:
        raise MeshFileError(f"{label}: a face refers to a vertex that does not exist ({exc})") from None
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshFileError(f"{label}: not a readable {suffix[1:].upper()} mesh ({type(exc).__name__}: {exc})") from None
    vertices = np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(loaded, "faces", np.empty((0, 3))))
    if vertices.shape[0] == 0:
        if _holds_points_only(trimesh, path, suffix):
            raise MeshFileError(f"{label}: has vertices but no faces (a point cloud is not a mesh)")
        raise MeshFileError(f"{label}: contains no mesh geometry (not a mesh file, or no vertices)")
    if faces.size == 0:
        raise MeshFileError(f"{label}: has vertices but no faces (a point cloud is not a mesh)")
    try:
        return clean_mesh(vertices, faces, name=name)
    except MeshError as exc:
        # replace the mesh label by the file path so the user knows which file to fix
        message = str(exc)
        if message.startswith(f"{name}: "):
            message = message[len(name) + 2:]
        raise MeshFileError(f"{label}: {message}") from None


def _obj_geometry_text(path: Path) -> bytes:
    """The `v` and `f` lines of an OBJ file, face corners reduced to their vertex index
    (see module docstring: keeps vertex order and count, no material / group splitting)."""
    text = path.read_bytes().decode("utf-8", errors="replace")
    text = text.replace("\r\n", "\n").replace("\r", "\n").replace("\\\n", " ")
    kept = []
    for line in text.split("\n"):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            kept.append(line.strip())
        elif parts[0] == "f":
            kept.append("f " + " ".join(corner.split("/", 1)[0] for corner in parts[1:]))
    return ("\n".join(kept) + "\n").encode()


def _holds_points_only(trimesh, path: Path, suffix: str) -> bool:
    """True when the file loads as a point cloud (vertices, no faces); error path only."""
    try:
        if suffix == ".obj":
            loaded = trimesh.load(io.BytesIO(_obj_geometry_text(path)), file_type="obj", process=False)
        else:
            loaded = trimesh.load(str(path), process=False, skip_materials=True)
    except Exception:
        return False
    return isinstance(loaded, trimesh.PointCloud) and len(loaded.vertices) > 0


def list_mesh_files(folder: str | os.PathLike) -> list[Path]:
    """Mesh files directly inside `folder`, sorted by name (deterministic order)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CollectionError(f"{folder}: not a folder")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)


def read_folder(folder: str | os.PathLike, min_shapes: int = 2) -> list[Mesh]:
    """Read every mesh file in `folder`.

    All files are tried; if any fail, one single-line MeshFileError names every failing
    file with its problem (starting with that file's path when only one fails).
    A folder with fewer than `min_shapes` meshes is a CollectionError.
    """
    folder = Path(folder)
    files = list_mesh_files(folder)
    if not files:
        raise CollectionError(
            f"{folder}: no mesh files found (looked for {', '.join(MESH_SUFFIXES)})"
        )
    meshes, failures = [], []
    for path in files:
        try:
            meshes.append(read_mesh(path))
        except MeshFileError as exc:
            failures.append(str(exc))
    if failures:
        # one line (the CLI prints errors as one line): the failing file first when it is the
        # only one, so the message starts with the path of the file to fix
        if len(failures) == 1:
            raise MeshFileError(f"{failures[0]} (1 of {len(files)} files in {folder})")
        raise MeshFileError(
            f"{folder}: {len(failures)} of {len(files)} files could not be read: "
            + "; ".join(failures)
        )
    names = [m.name for m in meshes]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise CollectionError(
            f"{folder}: several files share the name(s) {duplicates} (different extensions); "
            "shape names must be unique"
        )
    if len(meshes) < min_shapes:
        raise CollectionError(
            f"{folder}: a collection needs at least {min_shapes} meshes to learn from, "
            f"found {len(meshes)} ({', '.join(p.name for p in files)})"
        )
    return meshes


def write_mesh(mesh: Mesh, path: str | os.PathLike) -> Path:
    """Write `mesh` to `path` (format from the suffix), atomically: a temporary file is
    written first and renamed, so a failure never leaves a half-written file."""
    import trimesh

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshFileError(f"{path}: unsupported file type '{suffix}'")
    tmp = path.with_name(f".{path.name}.tmp{suffix}")
    try:
        if suffix == ".obj":
            tmp.write_bytes(obj_bytes(mesh))
        else:
            trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(str(tmp), file_type=suffix[1:])
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def obj_face_block(faces: np.ndarray) -> bytes:
    """The 'f' lines of an OBJ file (1-based indices)."""
    faces = np.ascontiguousarray(faces, dtype=np.int64) + 1
    return (("f %d %d %d\n" * len(faces)) % tuple(faces.ravel().tolist())).encode("ascii")


def obj_vertex_block(vertices: np.ndarray, precision: int = 8) -> bytes:
    """The 'v' lines of an OBJ file."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    line = f"v %.{precision}g %.{precision}g %.{precision}g\n"
    return ((line * len(vertices)) % tuple(vertices.ravel().tolist())).encode("ascii")


def obj_bytes(mesh: Mesh, precision: int = 8) -> bytes:
    """Plain OBJ text (v and f lines only) of a mesh.

    trimesh's OBJ exporter formats row by row (≈ 180 ms for 20k vertices), which alone
    would break the mass-generation target (1000 OBJ samples of a 20k-vertex mesh in 30 s);
    one C-level %-format over the whole array takes ≈ 35 ms for the vertices, and samples
    deformed from one template share their face block (`ObjWriter`). The output is read
    back by `read_mesh` (trimesh) with identical vertex order (tests/core/test_mesh_io.py)."""
    return obj_vertex_block(mesh.vertices, precision) + obj_face_block(mesh.faces)


class ObjWriter:
    """Writes many meshes that share one face list (deformed copies of a template) as OBJ,
    formatting the face block once."""

    def __init__(self, faces: np.ndarray, precision: int = 8):
        self.faces = np.asarray(faces)
        self.precision = precision
        self._face_block = obj_face_block(self.faces)

    def write(self, vertices: np.ndarray, path: str | os.PathLike) -> Path:
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp.obj")
        try:
            with open(tmp, "wb") as handle:
                handle.write(obj_vertex_block(vertices, self.precision))
                handle.write(self._face_block)
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
        return path


class MeshWriters:
    """Writes deformed copies of template meshes (same faces, new positions): OBJ through
    one `ObjWriter` per template (its face block formatted once), other formats through
    `write_mesh`."""

    def __init__(self, templates: Sequence[Mesh]):
        self.templates = list(templates)
        self._obj: dict[int, ObjWriter] = {}

    def write(self, mesh: Mesh, template_index: int, path: str | os.PathLike) -> Path:
        path = Path(path)
        if path.suffix.lower() != ".obj":
            return write_mesh(mesh, path)
        if template_index not in self._obj:
            self._obj[template_index] = ObjWriter(self.templates[template_index].faces)
        return self._obj[template_index].write(mesh.vertices, path)
