"""What a mesh file declares, checked against what it holds.

trimesh parses the files (core/meshes/reading.py); it trusts their declarations: an OFF whose header
counts more faces than the file holds, an ASCII PLY cut short, a glTF accessor counting
fewer indices than its buffer holds, an OBJ cut in the middle of a line all come back as
a mesh with faces missing. These checks read only the declarations (OFF and PLY headers,
glTF accessors, an ASCII STL's facets, the OBJ's last line) and the shape of the content
(lines and values per record, no control characters in text), and refuse a file whose
content disagrees with them, with a MeshFileError starting with the file's path. What
trimesh read is checked once more: an ASCII STL's triangles against its facets, a file
whose every face is repeated, and the coordinates (`check_coordinates`): every later stage
squares distances in float64, which overflows beyond about 1e154.
"""

from __future__ import annotations

import collections
import json
import re
import struct
from pathlib import Path

import numpy as np

from ..base.errors import MeshFileError

__all__ = ["MAX_COORDINATE", "check_declared", "check_read_faces", "check_coordinates", "check_not_repeated",
           "data_rows", "off_sections"]

#: the largest coordinate magnitude read (1e12: a kilometre-wide scene in nanometres). Far
#: below the float64 overflow of squared distances (~1e154), far above any real model.
MAX_COORDINATE = 1e12


def check_declared(path: Path) -> int | None:
    """Refuse (MeshFileError) a file whose content disagrees with what it declares. Binary
    files are read only as far as their declarations (PLY header, GLB JSON chunk). Returns
    the number of triangles the file declares where the reader must be checked against it
    (an ASCII STL's facets; `check_read_faces`), else None."""
    suffix = path.suffix.lower()
    if suffix == ".off":
        _check_off(path, path.read_bytes())
    elif suffix == ".ply" and _is_ascii_ply(path):
        _check_ply_ascii(path, path.read_bytes())
    elif suffix == ".obj":
        _check_obj_end(path)
    elif suffix in (".glb", ".gltf"):
        _check_gltf_counts(path, _gltf_document(path))
    elif suffix == ".stl" and not _is_binary_stl(path):
        return _check_stl_ascii(path, path.read_bytes())
    return None


def check_read_faces(label: str, declared: int | None, faces: np.ndarray) -> None:
    """Refuse a read that kept fewer or more triangles than the file declares."""
    if declared is not None and len(faces) != declared:
        raise MeshFileError(f"{label}: the file holds {declared} facets but {len(faces)} triangles were read from "
                            "them (a damaged value or line)")


def check_coordinates(label: str, vertices: np.ndarray) -> None:
    """Refuse coordinates that are not finite or beyond `MAX_COORDINATE` (module docstring)."""
    finite = np.isfinite(vertices)
    if not finite.all():
        rows = np.flatnonzero(~finite.all(axis=1))
        more = f" ({len(rows)} vertices have one)" if len(rows) > 1 else ""
        raise MeshFileError(f"{label}: vertex {int(rows[0])} has a NaN or infinite coordinate{more}")
    largest = float(np.abs(vertices).max()) if vertices.size else 0.0
    if largest > MAX_COORDINATE:
        low, high = vertices.min(axis=0), vertices.max(axis=0)
        raise MeshFileError(f"{label}: coordinates range from {_triple(low)} to {_triple(high)}, beyond "
                            f"±{MAX_COORDINATE:g}: too large to compute with (damaged values, or rescale the model)")


def check_not_repeated(label: str, faces: np.ndarray) -> None:
    """Refuse a mesh in which every face appears twice or more with the same winding (the
    file's content repeated, as a file appended to itself). `faces`: the file's triangles
    on welded vertices. Faces repeated with opposite winding (double-sided surfaces) and
    some faces repeated are left to intake."""
    if len(faces) < 2:
        return
    faces = np.asarray(faces)
    first = np.argmin(faces, axis=1)[:, None]  # each triangle from its lowest vertex: the same winding, one form
    rotated = np.take_along_axis(faces, (first + np.arange(3)) % 3, axis=1)
    _, counts = np.unique(rotated, axis=0, return_counts=True)
    if counts.min() >= 2:
        raise MeshFileError(f"{label}: every face appears {int(counts.min())} times or more "
                            "(the file's content is repeated)")


def _triple(values: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.3g}" for v in values) + ")"


# ---------------------------------------------------------------------------- OFF
def _check_off(path: Path, data: bytes) -> None:
    """An OFF file: header `OFF` then `V F E`, V vertex lines of at least 3 values, F face
    lines `k i1 .. ik` (and colours). Fewer lines than declared, or more lines of numbers:
    refused. Text after them is not the mesh's and is ignored, as readers do (PSB Vase 361
    ends with the settings of the tool that wrote it). (io's reader parses the values and
    refuses ones that are not numbers.)"""
    rows = data_rows(_decoded(path, data, "OFF"))
    if not rows or not re.fullmatch(r"C?N?OFF", rows[0][0]):
        return  # not recognisable as OFF: trimesh's refusal says so
    try:
        n_vertices, n_faces, body = off_sections(rows)
    except (IndexError, ValueError):
        raise MeshFileError(f"{path}: the OFF header has no vertex and face counts") from None
    after = [row for row in body[n_vertices + n_faces:] if _all_numbers(" ".join(row))]
    if len(body) < n_vertices + n_faces or after:
        held = n_vertices + n_faces + len(after) if after else len(body)
        raise MeshFileError(f"{path}: the OFF header declares {n_vertices} vertices and {n_faces} faces "
                            f"({n_vertices + n_faces} lines) but the file holds {held} lines of data")
    body = body[:n_vertices + n_faces]
    short = np.flatnonzero(_lengths(body[:n_vertices]) < 3)
    if len(short):
        raise MeshFileError(f"{path}: OFF vertex {short[0]} is not three numbers: {' '.join(body[short[0]])[:60]!r}")
    faces = body[n_vertices:]
    try:
        sizes = np.array([row[0] for row in faces], dtype=np.int64)
    except ValueError:
        sizes = np.array([int(row[0]) if row[0].isdigit() else -1 for row in faces], dtype=np.int64)
    bad = np.flatnonzero((sizes < 3) | (_lengths(faces) < 1 + sizes))  # indices out of range: intake names them
    if len(bad):
        raise MeshFileError(f"{path}: OFF face {bad[0]} is not a corner count and that many vertex indices: "
                            f"{' '.join(faces[bad[0]])[:60]!r}")


# ---------------------------------------------------------------------------- PLY
def _is_ascii_ply(path: Path) -> bool:
    with open(path, "rb") as handle:
        return [line.strip() for line in handle.read(4096).splitlines()[:2]] == [b"ply", b"format ascii 1.0"]


def _check_ply_ascii(path: Path, data: bytes) -> None:
    """An ASCII PLY: as many data lines as its elements declare records, each with the
    numbers its properties declare (a list: its count, then that many). trimesh reads a
    line up to its first value that is not a number, so the values are checked here."""
    end = data.find(b"end_header")
    if end < 0:
        return  # trimesh refuses a header with no end
    elements: list[tuple[str, int, list]] = []
    for line in data[:end].decode("ascii", errors="replace").splitlines():
        words = line.split()
        if words[:1] == ["element"] and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[:1] == ["property"] and elements:
            elements[-1][2].append("list" if words[1:2] == ["list"] else "scalar")
    body = _decoded(path, data[end + len(b"end_header"):], "PLY")
    if not _all_numbers(body):
        raise MeshFileError(f"{path}: the PLY data holds a value that is not a number (a damaged file)")
    rows = data_rows(body)
    declared = sum(count for _, count, _ in elements)
    if len(rows) != declared:
        raise MeshFileError(f"{path}: the PLY header declares {declared} records "
                            f"({', '.join(f'{n} {name}' for name, n, _ in elements)}) but the file holds "
                            f"{len(rows)} lines of data")
    start = 0
    for name, count, properties in elements:
        block = rows[start:start + count]
        bad = np.flatnonzero(_lengths(block) != _ply_lengths(block, properties))
        if len(bad):
            raise MeshFileError(f"{path}: PLY {name} {bad[0]} does not hold the values its header declares: "
                                f"{' '.join(block[bad[0]])[:60]!r}")
        start += count


def _ply_lengths(rows: list[list[str]], properties: list[str]) -> np.ndarray:
    """The number of values each row must have for these properties (-1: cannot tell)."""
    lists = [i for i, kind in enumerate(properties) if kind == "list"]
    if not lists:
        return np.full(len(rows), len(properties))
    if len(lists) == 1:  # the usual face element: one list, its count at a fixed place
        at = lists[0]
        counts = np.array([row[at] if len(row) > at else "-1" for row in rows], dtype=np.float64).astype(np.int64)
        return len(properties) + counts
    return np.array([_ply_row_length(row, properties) for row in rows], dtype=np.int64)


def _ply_row_length(row: list[str], properties: list[str]) -> int:
    position = 0
    for kind in properties:
        if position >= len(row):
            return -1
        position += 1 + (int(float(row[position])) if kind == "list" else 0)
    return position


# ---------------------------------------------------------------------------- OBJ
def _last_obj_line(path: Path) -> list[bytes] | None:
    """The words of an OBJ's last line when it has no line end, else None."""
    with open(path, "rb") as handle:
        handle.seek(max(0, path.stat().st_size - 4096))
        stripped = handle.read().rstrip(b" \t")
    if not stripped or stripped.endswith((b"\n", b"\r")):
        return None
    return stripped.rsplit(b"\n", 1)[-1].split()


def obj_unterminated(path: Path) -> bool:
    """Whether an OBJ's last line is a vertex or face without a line end: valid OBJ (many
    hand-written files end so), but also what a file cut short between two numbers looks
    like, so the reader reports it (`MeshReport.unterminated`)."""
    last = _last_obj_line(path)
    return bool(last) and last[0] in (b"v", b"f", b"vt", b"vn")


def _check_obj_end(path: Path) -> None:
    """An OBJ whose last line, without its line end, is visibly incomplete (a vertex with
    fewer than three coordinates, a face with fewer than three corners, a number or index
    cut after its sign, exponent or slash): the file was cut short. A complete last line
    without a line end is read, and reported (`obj_unterminated`)."""
    last = _last_obj_line(path)
    if last is None:
        return
    least = {b"v": 4, b"vn": 4, b"vt": 2, b"f": 4}.get(last[0] if last else b"")
    if least is None:
        return
    if len(last) < least or last[-1].endswith((b"/", b"e", b"E", b"-", b"+", b".")):
        raise MeshFileError(f"{path}: ends in the middle of a line ({last[0].decode()} ...): the file looks cut short")


# ---------------------------------------------------------------------------- STL
def _is_binary_stl(path: Path) -> bool:
    """A binary STL: 80 header bytes, a triangle count, 50 bytes per triangle (the test
    trimesh makes too: an ASCII STL never has exactly that size by chance)."""
    with open(path, "rb") as handle:
        start = handle.read(84)
    return len(start) == 84 and path.stat().st_size == 84 + 50 * struct.unpack("<I", start[80:84])[0]


def _check_stl_ascii(path: Path, data: bytes) -> int:
    """An ASCII STL (or a binary one whose size disagrees with its triangle count): every
    facet opened and closed, three `vertex` lines each. Returns the number of facets, which
    the triangles trimesh read must match (it reads by position and drops what it cannot)."""
    if not data.lstrip().lower().startswith(b"solid"):
        with open(path, "rb") as handle:
            handle.seek(80)
            count = struct.unpack("<I", handle.read(4).ljust(4, b"\0"))[0]
        raise MeshFileError(f"{path}: a binary STL of {path.stat().st_size} bytes, but its header counts {count} "
                            f"triangles ({84 + 50 * count} bytes)")
    text = _decoded(path, data, "STL").lower()
    ended, closed = text.count("endfacet"), text.count("endloop")
    facets, loops, vertices = text.count("facet") - ended, text.count("loop") - closed, text.count("vertex")
    if not (facets == ended == loops == closed and vertices == 3 * facets):
        raise MeshFileError(f"{path}: {facets} facets, {ended} ended, with {vertices} vertex lines: not an ASCII STL "
                            "of whole facets (damaged or cut short)")
    return facets


# ---------------------------------------------------------------------------- glTF
def _check_gltf_counts(path: Path, document) -> None:
    """glTF / GLB: every accessor that has a buffer view to itself (no stride, no other
    accessor in it) must fill that view; one counting fewer elements than the view holds
    was damaged (trimesh reads only what the accessor counts)."""
    if not isinstance(document, dict):
        return  # not parseable: trimesh's refusal says why
    try:
        accessors, views = document.get("accessors", []), document.get("bufferViews", [])
        users: dict[int, int] = {}
        for accessor in accessors:
            if "bufferView" in accessor:
                users[accessor["bufferView"]] = users.get(accessor["bufferView"], 0) + 1
        for number, accessor in enumerate(accessors):
            view_index = accessor.get("bufferView")
            if view_index is None or users[view_index] != 1 or "byteStride" in views[view_index]:
                continue
            size = _COMPONENT_BYTES[accessor["componentType"]] * _TYPE_COMPONENTS[accessor["type"]]
            held = views[view_index]["byteLength"] - accessor.get("byteOffset", 0)
            if held // size != accessor["count"]:
                raise MeshFileError(f"{path}: glTF accessor {number} declares {accessor['count']} elements but its "
                                    f"buffer view holds {held // size}")
    except (KeyError, IndexError, TypeError, AttributeError):
        return  # malformed in a way trimesh refuses itself


_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_TYPE_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def _gltf_document(path: Path):
    """The JSON document of a glTF file or of a GLB's first chunk (None: not parseable)."""
    try:
        with open(path, "rb") as handle:
            start = handle.read(20)
            if start[:4] == b"glTF":
                return json.loads(handle.read(struct.unpack("<I", start[12:16])[0]))
            return json.loads(start + handle.read())
    except (ValueError, struct.error, UnicodeDecodeError):
        return None


# ---------------------------------------------------------------------------- shared
def _decoded(path: Path, data: bytes, kind: str) -> str:
    """The text of a text format: UTF-8 (ASCII) only, so UTF-16 or binary damage is refused
    by name instead of being read as something else."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MeshFileError(f"{path}: not {kind} text (byte {exc.start} is not UTF-8: a binary, UTF-16 or damaged "
                            "file)") from None
    control = _CONTROL.search(text) if len(data.translate(None, _CONTROL_BYTES)) != len(data) else None
    if control:
        raise MeshFileError(f"{path}: not {kind} text (a control character, {control.group()!r}, at character "
                            f"{control.start()}: a damaged file)")
    return text


#: characters no text mesh file holds (whitespace other than tab, line ends and space)
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x0c\x0e-\x1f\x7f]")
_CONTROL_BYTES = bytes([*range(0x00, 0x09), 0x0b, 0x0c, *range(0x0e, 0x20), 0x7f])


def off_sections(rows: list[list[str]]) -> tuple[int, int, list[list[str]]]:
    """(vertex count, face count, the rows after the header) of an OFF file's data rows
    (`data_rows`): the counts stand on the `OFF` line or on the next. IndexError or
    ValueError when they are missing."""
    counts = rows[0][1:] or (rows[1] if len(rows) > 1 else [])
    body = rows[1:] if rows[0][1:] else rows[2:]
    return int(counts[0]), int(counts[1]), body


def data_rows(text: str) -> list[list[str]]:
    """The words of each line that has any, `#` comments left out."""
    lines = text.splitlines()
    if "#" in text:
        lines = [line.split("#", 1)[0] for line in lines]
    return [words for words in map(str.split, lines) if words]


def _lengths(rows: list[list[str]]) -> np.ndarray:
    return np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))


def _all_numbers(text: str) -> bool:
    """Every whitespace-separated word of `text` is a number. Python's own `float` parses
    each word (faster than numpy's text parsers here, and it has no half-read state:
    `np.fromstring(text, sep=" ")` stops at the first word that is not a number, which
    numpy deprecated and, from 2.3 on, refuses with a ValueError)."""
    try:
        collections.deque(map(float, text.split()), maxlen=0)
    except ValueError:
        return False
    return True
