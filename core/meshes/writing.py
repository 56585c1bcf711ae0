"""`Mesh` -> mesh files, atomically: OBJ and ASCII PLY by the small writers here, which keep
a mesh's file layout (`layout.FaceLayout` on `Mesh.report.layout`: the file's polygons and
UVs; OBJ `v`, `vt`, `f v/vt`, PLY polygons and per-vertex `s t`), glTF / GLB through trimesh
(triangles, `TEXCOORD_0`), STL and OFF as triangles (reading.py's docstring says what is
read back). `MeshWriters` writes many meshes deformed from a few templates, formatting each
template's faces once.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from ..base.errors import MeshFileError
from .mesh import Mesh
from .reading import MESH_SUFFIXES

__all__ = ["write_mesh", "obj_bytes", "ply_bytes", "ObjWriter", "MeshWriters"]


def write_mesh(mesh: Mesh, path: str | os.PathLike) -> Path:
    """Write `mesh` to `path` (format from the suffix), atomically: a temporary file is
    written first and renamed, so a failure never leaves a half-written file. A mesh that
    carries its file's layout (`report.layout`) is written with those polygons and UVs
    where the format holds them (module docstring)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshFileError(f"{path}: unsupported file type '{suffix}'")
    layout = mesh.report.layout
    if suffix == ".obj":
        return _write_atomically(path, lambda handle: ObjWriter.for_mesh(mesh).write_to(handle, mesh.vertices))
    if suffix == ".ply" and layout is not None:
        return _write_atomically(path, lambda handle: handle.write(ply_bytes(layout, mesh.vertices)))
    return _write_atomically(path, lambda handle: handle.write(_trimesh_bytes(mesh, suffix[1:])))


def _write_atomically(path: Path, write) -> Path:
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    try:
        with open(tmp, "wb") as handle:
            write(handle)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _trimesh_bytes(mesh: Mesh, file_type: str) -> bytes:
    """A file of triangles through trimesh: the layout's vertices, fan-triangulated
    polygons and per-vertex UVs (glTF's TEXCOORD_0) when the mesh carries a layout."""
    import trimesh

    layout = mesh.report.layout
    if layout is None:
        shape = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    else:
        shape = trimesh.Trimesh(layout.positions(mesh.vertices), layout.triangles(), process=False)
        uv = layout.vertex_uv()
        if uv is not None and file_type in ("glb", "gltf"):
            shape.visual = trimesh.visual.TextureVisuals(uv=uv)
    options = {"embed_buffers": True} if file_type == "gltf" else {}
    data = shape.export(file_type=file_type, **options)
    if isinstance(data, dict):  # gltf: {"model.gltf": the JSON, its buffers embedded}
        data = data["model.gltf"]
    return data.encode() if isinstance(data, str) else data


def ply_bytes(layout, vertices: np.ndarray, precision: int = 8) -> bytes:
    """An ASCII PLY of the layout's polygons at mesh vertices `vertices`, with per-vertex
    UVs (`s t`) when the layout's UVs are per vertex. ASCII: trimesh's binary reader
    (ours) assumes every face list has the first one's length, so quads beside n-gons
    need the text form."""
    positions = np.asarray(layout.positions(vertices), dtype=np.float64)
    uv = layout.vertex_uv()
    columns = positions if uv is None else np.hstack([positions, uv])
    header = ["ply", "format ascii 1.0", f"element vertex {len(positions)}",
              "property float x", "property float y", "property float z"]
    if uv is not None:
        header += ["property float s", "property float t"]
    header += [f"element face {len(layout.sizes)}", "property list uchar int vertex_indices", "end_header"]
    if layout.sizes.max() > 255:
        raise MeshFileError(f"a polygon has {int(layout.sizes.max())} corners; PLY's face lists hold at most 255")
    line = " ".join([f"%.{precision}g"] * columns.shape[1]) + "\n"
    vertex_block = (line * len(columns)) % tuple(columns.ravel().tolist())
    faces = "".join(f"{len(p)} " + " ".join(map(str, p.tolist())) + "\n" for p in layout.polygons())
    return ("\n".join(header) + "\n" + vertex_block + faces).encode("ascii")


def obj_face_block(faces: np.ndarray) -> bytes:
    """The 'f' lines of an OBJ file (1-based indices)."""
    faces = np.ascontiguousarray(faces, dtype=np.int64) + 1
    return (("f %d %d %d\n" * len(faces)) % tuple(faces.ravel().tolist())).encode("ascii")


def obj_layout_block(layout) -> bytes:
    """The 'vt' and 'f' lines of a layout: polygons as the file had them, `v/vt` corners
    when it has UVs (each distinct UV written once)."""
    vertex = layout.corners + 1
    if layout.uv is None:
        fields = [str(v) for v in vertex.tolist()]
        texture = b""
    else:
        unique, which = np.unique(layout.uv, axis=0, return_inverse=True)
        texture = (("vt %.8g %.8g\n" * len(unique)) % tuple(unique.ravel().tolist())).encode("ascii")
        fields = [f"{v}/{t}" for v, t in zip(vertex.tolist(), (np.ravel(which) + 1).tolist())]
    lines, start = [], 0
    for size in layout.sizes.tolist():
        lines.append("f " + " ".join(fields[start:start + size]))
        start += size
    return texture + ("\n".join(lines) + "\n").encode("ascii")


def obj_vertex_block(vertices: np.ndarray, precision: int = 8) -> bytes:
    """The 'v' lines of an OBJ file."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    line = f"v %.{precision}g %.{precision}g %.{precision}g\n"
    return ((line * len(vertices)) % tuple(vertices.ravel().tolist())).encode("ascii")


def obj_bytes(mesh: Mesh, precision: int = 8) -> bytes:
    """OBJ text of a mesh: v and f lines, or, when it carries its file's layout, the file's
    vertices, UVs and polygons.

    trimesh's OBJ exporter formats row by row (≈ 180 ms for 20k vertices), which alone
    would break the mass-generation target (1000 OBJ samples of a 20k-vertex mesh in 30 s);
    one C-level %-format over the whole array takes ≈ 35 ms for the vertices, and samples
    deformed from one template share their face block (`ObjWriter`). The output is read
    back by `read_mesh` (trimesh) with identical vertex order (tests/core/test_mesh_io.py)."""
    buffer = io.BytesIO()
    ObjWriter.for_mesh(mesh, precision).write_to(buffer, mesh.vertices)
    return buffer.getvalue()


class ObjWriter:
    """Writes many meshes that share one face list (deformed copies of a template) as OBJ,
    formatting the face block once: the template's triangles, or its file's layout
    (polygons and UVs, vertices through the layout's vertex map)."""

    def __init__(self, faces: np.ndarray, precision: int = 8, layout=None):
        self.faces = np.asarray(faces)
        self.precision = precision
        self.layout = layout
        self._face_block = obj_face_block(self.faces) if layout is None else obj_layout_block(layout)

    @classmethod
    def for_mesh(cls, mesh: Mesh, precision: int = 8) -> "ObjWriter":
        return cls(mesh.faces, precision, mesh.report.layout)

    def write_to(self, handle, vertices: np.ndarray) -> None:
        positions = vertices if self.layout is None else self.layout.positions(vertices)
        handle.write(obj_vertex_block(positions, self.precision))
        handle.write(self._face_block)

    def write(self, vertices: np.ndarray, path: str | os.PathLike) -> Path:
        return _write_atomically(Path(path), lambda handle: self.write_to(handle, vertices))


class MeshWriters:
    """Writes deformed copies of template meshes (same faces, new positions): OBJ through
    one `ObjWriter` per template (its face block formatted once), other formats through
    `write_mesh`; both with the template's file layout when it has one. `file_axes`
    (3 × 3, rows: the model frame's axes in the files' coordinates; None: the same) turns
    every written mesh from the model's Z-up frame into the axes the training files were
    read in (`GenerativeShapeModel.file_axes`)."""

    def __init__(self, templates: Sequence[Mesh], file_axes: np.ndarray | None = None):
        self.templates = list(templates)
        self.file_axes = None if file_axes is None or np.array_equal(file_axes, np.eye(3)) else file_axes
        self._obj: dict[int, ObjWriter] = {}

    def write(self, mesh: Mesh, template_index: int, path: str | os.PathLike) -> Path:
        path = Path(path)
        if self.file_axes is not None:
            mesh = mesh.with_vertices(mesh.vertices @ self.file_axes)
        if path.suffix.lower() != ".obj":
            return write_mesh(mesh, path)
        if template_index not in self._obj:
            self._obj[template_index] = ObjWriter.for_mesh(self.templates[template_index])
        return self._obj[template_index].write(mesh.vertices, path)
