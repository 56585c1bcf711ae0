"""Mesh files -> `Mesh`, through trimesh (OFF, the simplest format, read here: below).

Supported: OBJ, PLY, STL, OFF, GLB/GLTF. Files are read with `process=False` and
`maintain_order=True` (trimesh neither merges nor reorders), then cleaned by
`intake.clean_mesh`: coincident vertices welded, faces wound outwards, what changed in
`Mesh.report`. A clean file keeps its order: vertex i of the file is vertex i of the
Mesh. Polygons are fan-triangulated by trimesh's readers. Every error message starts with
the file's path.

Damaged files: trimesh trusts what a file declares, so before and after it reads
one, core/meshes/file_checks.py compares the declarations (OFF and ASCII PLY counts, ASCII STL facets,
glTF accessor counts, an OBJ's last line) with the content, and refuses coordinates that are
not finite or too large to square in float64, before any geometry runs.

OBJ: trimesh splits a vertex for every distinct (v, vt, vn) corner it meets and repeats
the whole vertex list once per material / object group, which breaks "vertex i of the
file is vertex i of the Mesh" for ordinary exports (and needs PIL as soon as `vt` is
present). Only geometry is wanted here, so the text handed to trimesh keeps the `v`
lines and the `f` lines with each corner reduced to its vertex index; trimesh still
does the parsing and triangulation.

OFF: read here from the rows core/meshes/file_checks.py has already checked against the header
(`_read_off`), polygons fan-cut from their first corner as trimesh does. trimesh 5's reader
cuts a file of mixed polygon sizes with numpy string arithmetic that numpy 2.5 refuses, and
refuses an out-of-range index before intake can name the face.

Faces as the file had them: OBJ polygons and `vt` UVs (parsed from the same lines), PLY
polygons (trimesh keeps the raw face lists) and per-vertex UVs, glTF per-vertex UVs are
kept as a `layout.FaceLayout` on `Mesh.report.layout` (when the file has polygons beyond
triangles or UVs), and `write_mesh` / `MeshWriters` (writing.py) write a mesh that carries
one with the file's polygons and UVs: OBJ (`v`, `vt`, `f v/vt`) and ASCII PLY (polygons,
per-vertex `s t`) by small writers of their own (trimesh writes triangles only), glTF / GLB
through trimesh (triangles, `TEXCOORD_0`), STL and OFF as triangles.

STL stores each triangle with its own three corners (vertex 3k + j of the file is corner j
of triangle k): welded, they become one connected surface, and `report.vertex_map[3k + j]`
is the Mesh vertex of that corner.
"""

from __future__ import annotations

import io
import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..base.child_process import MEMORY_ADVICE, exit_with_parent
from ..base.errors import CollectionError, MeshError, MeshFileError, ShapeGenError, WorkerDied
from .file_checks import (check_coordinates, check_declared, check_not_repeated, check_read_faces, data_rows,
                          obj_unterminated, off_sections)
from .intake import clean_mesh, weld_vertices
from .layout import FaceLayout
from .mesh import Mesh
from .spill import SpillStore, keep_dense

__all__ = ["MESH_SUFFIXES", "file_faces", "read_mesh", "check_mesh_file", "read_folder", "read_readable",
           "list_mesh_files"]

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")


def file_faces(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """The faces of a mesh file as it stores them: (sizes (P,), corners (C,) in file vertex
    indices), the polygons its face ids number (part labels, core/meshes/labels.py)."""
    sizes, corners = _parsed(path)[6][:2]
    return np.asarray(sizes, dtype=np.int64), np.asarray(corners, dtype=np.int64)


def read_mesh(path: str | os.PathLike, name: str | None = None) -> Mesh:
    """Read one mesh file. The mesh is named after the file's stem unless `name` is given."""
    label, name, suffix, vertices, faces, loaded, file_faces = _parsed(path, name)
    try:
        mesh = clean_mesh(vertices, faces, name=name, polygon_of=_polygon_of(file_faces, faces))
    except MeshError as exc:
        raise _file_error(label, name, exc) from None
    welded = faces if mesh.report.vertex_map is None else mesh.report.vertex_map[faces]
    check_not_repeated(label, welded)
    unused = mesh.n_vertices - len(np.unique(welded))  # of the file's faces: intake may leave slivers out
    unterminated = suffix == ".obj" and obj_unterminated(Path(path))
    if unused or unterminated:  # reported: a file cut short may still read as a mesh
        mesh = Mesh(mesh.vertices, mesh.faces, name=mesh.name,
                    report=replace(mesh.report, vertices_unused=unused, unterminated=unterminated))
    return _with_layout(mesh, file_faces, len(vertices))


def check_mesh_file(path: str | os.PathLike) -> None:
    """Refuse (MeshFileError starting with the path) a file `read_mesh` refuses as damaged
    or as no mesh: what it declares against what it holds, coordinates, face indices,
    every face repeated. Intake's cleaning (winding, twins, walls), the costly part of
    reading, is left out: for a caller that reads the file's content itself (Blender's
    importers, which accept damaged files silently) and cleans it later, as Prepare does."""
    label, name, _, vertices, faces, _, _ = _parsed(path)
    try:
        Mesh.from_polygons(vertices, faces, name=name)
    except MeshError as exc:
        raise _file_error(label, name, exc) from None
    check_not_repeated(label, weld_vertices(vertices)[1][faces])


def _file_error(label: str, name: str, exc: MeshError) -> MeshFileError:
    """`exc` about the mesh `name` as an error about the file `label` (the user knows which
    file to fix)."""
    message = str(exc)
    if message.startswith(f"{name}: "):
        message = message[len(name) + 2:]
    return MeshFileError(f"{label}: {message}")


def _parsed(path: str | os.PathLike, name: str | None = None):
    """(label, name, suffix, vertices, triangles, what trimesh loaded, the file's faces) of
    a mesh file, parsed and checked against its declarations (module docstring), before
    intake: MeshFileError starting with the path for a file that is damaged or no mesh."""
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
    file_faces = None
    declared = check_declared(path)  # what the file declares against what it holds (core/meshes/file_checks.py)
    try:
        if suffix == ".obj":
            text, file_faces = _obj_geometry_text(path, with_faces=True)
            loaded = _load_geometry(trimesh, io.BytesIO(text), "obj")
        elif suffix == ".off":
            loaded, file_faces = _read_off(path)
        else:
            with open(path, "rb") as handle:
                loaded = _load_geometry(trimesh, handle, suffix[1:])
        vertices = np.asarray(loaded.get("vertices", np.empty((0, 3))), dtype=np.float64)
        faces = np.asarray(loaded.get("faces", np.empty((0, 3))))
        if faces.size and (faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer)):
            raise ValueError(f"faces of shape {faces.shape} and type {faces.dtype} are not triangles")
    except IndexError as exc:
        raise MeshFileError(f"{label}: a face refers to a vertex that does not exist ({exc})") from None
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshFileError(f"{label}: not a readable {suffix[1:].upper()} mesh ({type(exc).__name__}: {exc})") from None
    check_read_faces(label, declared, faces)
    check_coordinates(label, vertices)  # before any geometry: squared distances must not overflow
    if vertices.shape[0] == 0:
        if _holds_points_only(trimesh, path, suffix):
            raise MeshFileError(f"{label}: has vertices but no faces (a point cloud is not a mesh)")
        raise MeshFileError(f"{label}: contains no mesh geometry (not a mesh file, or no vertices)")
    if faces.size == 0:
        raise MeshFileError(f"{label}: has vertices but no faces (a point cloud is not a mesh)")
    if file_faces is None:
        try:
            file_faces = _loaded_faces(loaded, faces, len(vertices))
        except (ValueError, TypeError) as exc:  # face lists trimesh kept but cannot be polygons
            raise MeshFileError(f"{label}: its face lists are not polygons ({exc})") from None
    return label, name, suffix, vertices, faces, loaded, file_faces


def _fans(sizes: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each polygon (`sizes[p]` corners, concatenated in `corners`) cut into a fan from its
    first corner, as trimesh's readers cut them: the (T, 3) triangles, polygon by polygon,
    and the polygon each came from (T,)."""
    polygon = np.repeat(np.arange(len(sizes)), sizes - 2)
    first = (np.cumsum(sizes) - sizes)[polygon]
    step = np.arange(len(polygon)) - np.repeat(np.cumsum(sizes - 2) - (sizes - 2), sizes - 2)
    triangles = np.stack([corners[first], corners[first + step + 1], corners[first + step + 2]], axis=1)
    return triangles, polygon


def _polygon_of(file_faces, triangles: np.ndarray) -> np.ndarray | None:
    """(T,) the file polygon each triangle trimesh read was cut from, or None when the file
    holds triangles only or a triangle is not one of its polygons' fans. Intake needs the
    map to recognise a double-sided quad or n-gon, whose back may be cut along the other
    diagonal. trimesh fans every polygon from its first corner but orders the
    triangles its own way (an all-quad OBJ: every quad's first triangle, then every
    second), so each triangle is matched to a fan triangle with the same corners in the
    same cyclic order (a polygon and its reverse on the same vertices have opposite ones)."""
    sizes, corners = np.asarray(file_faces[0], dtype=np.int64), np.asarray(file_faces[1], dtype=np.int64)
    triangles = np.asarray(triangles, dtype=np.int64)
    if len(sizes) == 0 or np.all(sizes == 3) or sizes.min() < 3 or int(np.sum(sizes - 2)) != len(triangles):
        return None
    fans, polygon = _fans(sizes, corners)
    fan_keys, read_keys = _cyclic_rows(fans), _cyclic_rows(triangles)
    keys = np.concatenate([fan_keys, read_keys])
    n = int(keys.max()) + 1
    if n <= 2_000_000:  # one int64 per triple (n³ < 2⁶³): a flat sort
        _, inverse = np.unique((keys[:, 0] * n + keys[:, 1]) * n + keys[:, 2], return_inverse=True)
    else:
        _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = np.asarray(inverse).ravel()
    owner = np.full(int(inverse.max()) + 1, -1)
    owner[inverse[:len(fans)]] = polygon
    polygon_of = owner[inverse[len(fans):]]
    return None if (polygon_of < 0).any() else polygon_of


def _cyclic_rows(triangles: np.ndarray) -> np.ndarray:
    """Each triangle's corners turned cyclically to start at its smallest index (the
    winding kept)."""
    shift = np.argmin(triangles, axis=1)
    order = (shift[:, None] + np.arange(3)) % 3
    return np.take_along_axis(triangles, order, axis=1)


def _load_geometry(trimesh, handle, file_type: str) -> dict:
    """What trimesh's reader of `file_type` gives (vertices, faces, metadata, visual), read
    with `process=False`: for PLY and STL straight from trimesh's mesh loader (issue
    15: wrapping the arrays in a Trimesh, a Scene and a merged copy of it costs more than
    parsing a binary PLY of a million vertices), for other formats (OBJ's loader returns a
    scene) and files with several objects through `trimesh.load(force="mesh")`."""
    options = dict(process=False, maintain_order=True, skip_materials=True)
    loader = trimesh.exchange.load.mesh_loaders.get(file_type) if file_type in _DIRECT_FORMATS else None
    if loader is not None:
        start = handle.tell()
        found = loader(file_obj=handle, file_type=file_type, resolver=None, metadata=None, **options)
        if isinstance(found, dict) and "vertices" in found and "geometry" not in found:
            return found
        handle.seek(start)
    loaded = trimesh.load(file_obj=handle, file_type=file_type, force="mesh", **options)
    return {"vertices": getattr(loaded, "vertices", np.empty((0, 3))), "faces": getattr(loaded, "faces", None),
            "metadata": getattr(loaded, "metadata", {}), "visual": getattr(loaded, "visual", None)}


#: formats read straight from trimesh's mesh loader (`_load_geometry`)
_DIRECT_FORMATS = ("ply", "stl")


def _loaded_faces(loaded: dict, faces: np.ndarray, n_vertices: int):
    """(sizes, corners, uv per corner or None) of a mesh trimesh loaded: PLY polygons from
    its raw face lists, UVs per vertex where trimesh found them (PLY, glTF). Face lists of
    one length (a binary PLY's record array) are taken whole, without a loop over faces."""
    raw = (loaded.get("metadata") or {}).get("_ply_raw", {}).get("face", {}).get("data", {})
    lists = None
    if isinstance(raw, np.ndarray) and raw.dtype.names:
        name = next((n for n in ("vertex_indices", "vertex_index") if n in raw.dtype.names), None)
        lists = None if name is None else raw[name]
    elif hasattr(raw, "get"):
        lists = raw.get("vertex_indices", raw.get("vertex_index"))
    if isinstance(lists, np.ndarray) and lists.dtype.names and "f1" in lists.dtype.names:
        lists = lists["f1"]  # binary PLY: (count, indices) records of one length
    if isinstance(lists, np.ndarray) and lists.dtype != object and lists.ndim == 2 and len(lists):
        sizes = np.full(len(lists), lists.shape[1], dtype=np.int64)
        corners = lists.astype(np.int64).ravel()
    else:
        if lists is not None and len(lists):
            polygons = [np.asarray(p, dtype=np.int64).ravel() for p in lists]
        else:
            polygons = list(np.asarray(faces, dtype=np.int64))
        sizes = np.array([len(p) for p in polygons], dtype=np.int64)
        corners = np.concatenate(polygons) if polygons else np.empty(0, dtype=np.int64)
    uv = getattr(loaded.get("visual"), "uv", None)
    per_corner = None
    if uv is not None and len(uv) == n_vertices:
        per_corner = np.asarray(uv, dtype=np.float64)[corners]
    return sizes, corners, per_corner


def _with_layout(mesh: Mesh, file_faces, n_file_vertices: int) -> Mesh:
    """`mesh` carrying the file's polygons and UVs (layout.FaceLayout) when the file has
    polygons beyond triangles or UVs; as it is otherwise, or when they do not fit."""
    sizes, corners, uv = file_faces
    if len(sizes) == 0 or (uv is None and np.all(sizes == 3)):
        return mesh
    vertex_map = mesh.report.vertex_map if mesh.report.vertex_map is not None else np.arange(mesh.n_vertices)
    if len(vertex_map) != n_file_vertices:
        return mesh
    try:
        layout = FaceLayout.wound_like(vertex_map, sizes, corners, uv, mesh.faces).one_sided()
    except ShapeGenError:
        return mesh
    return Mesh(mesh.vertices, mesh.faces, name=mesh.name, report=replace(mesh.report, layout=layout))


def _obj_geometry_text(path: Path, with_faces: bool = False):
    """The `v` and `f` lines of an OBJ file, face corners reduced to their vertex index
    (see module docstring: keeps vertex order and count, no material / group splitting).
    With `with_faces` also the file's faces: (sizes, corners as 0-based vertex indices, UVs
    per corner from `vt` or None when a corner has none)."""
    text = path.read_bytes().decode("utf-8", errors="replace")
    text = text.replace("\r\n", "\n").replace("\r", "\n").replace("\\\n", " ")
    kept, sizes, corners, corner_uv, uvs = [], [], [], [], []
    n_vertices = 0
    for line in text.split("\n"):
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            kept.append(line.strip())
            n_vertices += 1
        elif parts[0] == "vt" and with_faces:
            uvs.append([float(value) for value in (parts[1:3] + ["0"])[:2]])
        elif parts[0] == "f":
            indices = [corner.split("/") for corner in parts[1:]]
            kept.append("f " + " ".join(fields[0] for fields in indices))
            if with_faces:
                sizes.append(len(indices))
                for fields in indices:
                    v = int(fields[0])
                    corners.append(v - 1 if v > 0 else n_vertices + v)
                    t = int(fields[1]) if len(fields) > 1 and fields[1] else 0
                    corner_uv.append(t - 1 if t > 0 else (len(uvs) + t if t < 0 else -1))
    data = ("\n".join(kept) + "\n").encode()
    if not with_faces:
        return data
    corner_uv = np.asarray(corner_uv, dtype=np.int64)
    uv = None
    if len(corner_uv) and uvs and corner_uv.min() >= 0 and corner_uv.max() < len(uvs):
        uv = np.asarray(uvs, dtype=np.float64)[corner_uv]
    return data, (np.asarray(sizes, dtype=np.int64), np.asarray(corners, dtype=np.int64), uv)


def _read_off(path: Path) -> tuple[dict, tuple]:
    """An OFF file's vertices (first three values of each vertex line) and triangles (each
    face's polygon cut into a fan from its first corner), and the file's faces (sizes,
    corners, no UVs). The file's structure was checked by `check_declared`: a header with
    counts, as many vertex and face lines as it declares, each face `k i1 .. ik`; comments
    and anything after the declared lines are left out."""
    n_vertices, n_faces, body = off_sections(data_rows(path.read_bytes().decode("utf-8")))
    vertices = np.array([words[:3] for words in body[:n_vertices]], dtype=np.float64).reshape(n_vertices, 3)
    face_rows = body[n_vertices:n_vertices + n_faces]
    sizes = np.array([int(words[0]) for words in face_rows], dtype=np.int64)
    corners = np.array([index for words in face_rows for index in words[1:1 + int(words[0])]], dtype=np.int64)
    return {"vertices": vertices, "faces": _fans(sizes, corners)[0]}, (sizes, corners, None)


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


def read_folder(folder: str | os.PathLike, min_shapes: int = 2, jobs: int | None = 1,
                spill: "SpillStore | None" = None) -> list:
    """Read every mesh file in `folder`, in `jobs` worker processes (None: all cores; 1:
    in this process), one file per task, in file order either way. With a `spill` store
    (core/meshes/spill.py), a mesh above its size is written there by the process that read it
    and comes back as a `StoredMesh` (no full-density copy reaches this process).

    All files are tried; if any fail, one single-line MeshFileError names every failing
    file with its problem (starting with that file's path when only one fails).
    A folder with fewer than `min_shapes` meshes is a CollectionError.
    """
    folder = Path(folder)
    files, outcomes = _read_files(folder, jobs, spill)
    failures = [m for m in outcomes if isinstance(m, str)]
    if failures:
        # one line (the CLI prints errors as one line): the failing file first when it is the
        # only one, so the message starts with the path of the file to fix
        if len(failures) == 1:
            raise MeshFileError(f"{failures[0]} (1 of {len(files)} files in {folder})")
        raise MeshFileError(
            f"{folder}: {len(failures)} of {len(files)} files could not be read: "
            + "; ".join(failures)
        )
    return _checked_collection(folder, files, outcomes, min_shapes)


def read_readable(folder: str | os.PathLike, min_shapes: int = 2, jobs: int | None = 1,
                  spill: "SpillStore | None" = None) -> tuple[list, dict[str, str]]:
    """`read_folder` that leaves out the files it cannot read instead of refusing the
    folder, so one damaged download does not stop a collection: (the meshes read, {file
    name: its MeshFileError's message} of the files left out, in file order). Fewer than
    `min_shapes` readable meshes is still a CollectionError, naming every file left out."""
    folder = Path(folder)
    files, outcomes = _read_files(folder, jobs, spill)
    unreadable = {path.name: m for path, m in zip(files, outcomes) if isinstance(m, str)}
    meshes = [m for m in outcomes if not isinstance(m, str)]
    if unreadable and len(meshes) < min_shapes:
        raise CollectionError(
            f"{folder}: a collection needs at least {min_shapes} meshes to learn from, {len(meshes)} of "
            f"{len(files)} files could be read; unreadable: " + "; ".join(unreadable.values())
        )
    return _checked_collection(folder, files, meshes, min_shapes), unreadable


def _read_files(folder: Path, jobs: int | None, spill: "SpillStore | None") -> tuple[list[Path], list]:
    """The mesh files of `folder` and, for each, its mesh or its MeshFileError's message
    (`_read_or_error`), read in `jobs` worker processes (see `read_folder`)."""
    files = list_mesh_files(folder)
    if not files:
        raise CollectionError(
            f"{folder}: no mesh files found (looked for {', '.join(MESH_SUFFIXES)})"
        )
    jobs = min(len(files), (os.cpu_count() or 1) if jobs is None else max(1, int(jobs)))
    target = None if spill is None else spill.target
    if jobs > 1:
        import concurrent.futures as futures
        import multiprocessing

        from concurrent.futures.process import BrokenProcessPool

        try:
            with futures.ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=exit_with_parent) as pool:
                outcomes = list(pool.map(_read_or_error, files, [target] * len(files)))
        except BrokenProcessPool:
            raise WorkerDied(f"{folder}: a worker process reading its files ended without a result, {MEMORY_ADVICE}; "
                             f"this run used {jobs}") from None
    else:
        outcomes = [_read_or_error(path, target) for path in files]
    return files, outcomes


def _checked_collection(folder: Path, files: list[Path], meshes: list, min_shapes: int) -> list:
    """`meshes` (read from `files` of `folder`) when their names are unique and there are
    at least `min_shapes` of them; else a CollectionError saying why."""
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


def _read_or_error(path: Path, spill: tuple[str, int] | None = None):
    """The mesh of one file (kept in the spill store `spill` = (folder, above) when it is
    dense: `spill.keep_dense`), or its MeshFileError's message (a worker task of `read_folder`)."""
    try:
        mesh = read_mesh(path)
    except MeshFileError as exc:
        return str(exc)
    return mesh if spill is None else keep_dense(mesh, *spill)
