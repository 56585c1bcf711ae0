"""A generated corpus of damaged mesh files, one list of cases per format ShapeGen reads:
truncations at several lengths, byte flips at seeded positions, count and
index damage, non-finite and extreme coordinates, wrong encodings and an empty file.

Needs numpy and trimesh only (the Blender tier imports it too). Every case is
`(name, data)`: the bytes of one damaged copy of the undamaged file of a small closed
mesh. A reader must either read a case exactly as the undamaged file or refuse it.
"""

from __future__ import annotations

import json
import struct

import numpy as np

#: formats and the suffix their files carry
FORMATS = {"off": ".off", "obj": ".obj", "ply_ascii": ".ply", "ply_binary": ".ply", "stl_ascii": ".stl",
           "stl_binary": ".stl", "glb": ".glb", "gltf": ".gltf"}

#: fractions of the file kept by the truncation cases
TRUNCATIONS = (0.02, 0.1, 0.25, 0.4, 0.5, 0.6, 0.75, 0.9, 0.97, 0.995)
#: seed and number of the byte-flip cases (one byte each, then three bytes each)
FLIP_SEED, SINGLE_FLIPS, TRIPLE_FLIPS = 32, 8, 4


def file_bytes(file_format: str, vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """The file of `file_format` holding the mesh, written by trimesh (an independent writer)."""
    import trimesh

    shape = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces), process=False)
    with np.errstate(all="ignore"):  # the normals of extreme or non-finite coordinates
        return _exported(shape, file_format)


def _exported(shape, file_format: str) -> bytes:
    if file_format in ("ply_ascii", "ply_binary"):
        return shape.export(file_type="ply", encoding=file_format[4:])
    if file_format == "stl_ascii":
        return shape.export(file_type="stl_ascii").encode()
    if file_format == "stl_binary":
        return shape.export(file_type="stl")
    if file_format == "gltf":
        return shape.export(file_type="gltf", embed_buffers=True)["model.gltf"]
    data = shape.export(file_type=file_format)
    return data.encode() if isinstance(data, str) else data


def corrupt_cases(file_format: str, vertices: np.ndarray, faces: np.ndarray) -> list[tuple[str, bytes]]:
    """The damaged copies of the mesh's `file_format` file: [(case name, bytes)]."""
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    good = file_bytes(file_format, vertices, faces)
    cases = [("empty", b"")]
    cases += [(f"truncated_{fraction:g}", good[:int(len(good) * fraction)]) for fraction in TRUNCATIONS]
    cases.append(("truncated_last_byte", good[:-1]))
    rng = np.random.default_rng(FLIP_SEED)
    for flips in [1] * SINGLE_FLIPS + [3] * TRIPLE_FLIPS:
        damaged = bytearray(good)
        places = rng.choice(len(good), flips, replace=False)
        for place in places:
            damaged[place] ^= int(rng.integers(1, 256))
        cases.append((f"flipped_{flips}_at_{'_'.join(map(str, sorted(places.tolist())))}", bytes(damaged)))
    if file_format in ("off", "obj", "ply_ascii", "stl_ascii", "gltf"):
        cases.append(("utf16", good.decode("latin-1").encode("utf-16")))
    else:
        cases.append(("utf16_of_bytes", good.decode("latin-1").encode("utf-16")))
    cases.append(("doubled", good + good))
    for label, value in (("nan", np.nan), ("inf", np.inf), ("minus_inf", -np.inf), ("huge_1e200", 1e200),
                         ("huge_1e39", 1e39)):
        changed = vertices.copy()
        changed[len(changed) // 2, 1] = value
        cases.append((f"vertex_{label}", file_bytes(file_format, changed, faces)))
    cases.append(("all_scaled_1e200", file_bytes(file_format, vertices * 1e200, faces)))
    cases.append(("all_scaled_1e-200", file_bytes(file_format, vertices * 1e-200, faces)))
    cases += _structure_cases(file_format, good, vertices, faces)
    return cases


def _structure_cases(file_format: str, good: bytes, vertices: np.ndarray, faces: np.ndarray):
    """Count and index damage, in the form each format declares its structure."""
    n_vertices, n_faces = len(vertices), len(faces)
    if file_format == "off":
        header_end = good.index(b"\n", 4)
        body = good[header_end:]
        counts = lambda v, f: b"OFF\n%d %d 0" % (v, f) + body  # noqa: E731
        cases = [("vertex_count_plus_1", counts(n_vertices + 1, n_faces)),
                 ("vertex_count_minus_1", counts(n_vertices - 1, n_faces)),
                 ("face_count_plus_1", counts(n_vertices, n_faces + 1)),
                 ("face_count_minus_1", counts(n_vertices, n_faces - 1)),
                 ("counts_missing", b"OFF\n" + body),
                 ("text_in_coordinates", good.replace(b"\n", b"\nabc ", 2).replace(b"\nabc ", b"\n", 1))]
    elif file_format == "obj":
        lines = good.decode().splitlines()
        v_lines = [i for i, line in enumerate(lines) if line.startswith("v ")]
        f_lines = [i for i, line in enumerate(lines) if line.startswith("f ")]
        cases = [("vertex_line_dropped", "\n".join(lines[:v_lines[-1]] + lines[v_lines[-1] + 1:]).encode()),
                 # cut at a line end: nothing in OBJ says faces are missing (read, and reported)
                 ("faces_cut_at_line_end", ("\n".join(lines[:f_lines[len(f_lines) * 4 // 5]]) + "\n").encode()),
                 ("vertex_lines_halved", "\n".join(lines[:v_lines[len(v_lines) // 2]]
                                                    + [line for line in lines if line.startswith("f ")]).encode()),
                 ("text_in_coordinates", good.replace(b"v ", b"v abc ", 1))]
    elif file_format.startswith("ply"):
        declared = lambda text, old, new: good.replace(text + b" %d" % old, text + b" %d" % new, 1)  # noqa: E731
        cases = [("vertex_count_plus_1", declared(b"element vertex", n_vertices, n_vertices + 1)),
                 ("vertex_count_minus_1", declared(b"element vertex", n_vertices, n_vertices - 1)),
                 ("face_count_plus_1", declared(b"element face", n_faces, n_faces + 1)),
                 ("face_count_minus_1", declared(b"element face", n_faces, n_faces - 1)),
                 ("header_unterminated", good.replace(b"end_header", b"end_headex", 1))]
    elif file_format == "stl_binary":
        count = lambda n: good[:80] + struct.pack("<I", n) + good[84:]  # noqa: E731
        cases = [("triangle_count_plus_1", count(n_faces + 1)), ("triangle_count_minus_1", count(n_faces - 1)),
                 ("triangle_count_huge", count(2 ** 31)), ("triangle_count_zero", count(0))]
    elif file_format == "stl_ascii":
        text = good.decode()
        cases = [("vertex_line_dropped", text.replace("vertex", "vertez", 1).encode()),
                 ("endloop_dropped", text.replace("endloop", "", 1).encode()),
                 ("text_in_coordinates", text.replace("vertex ", "vertex abc ", 1).encode())]
    else:  # glTF / GLB: the accessors declare counts, the buffer holds them
        cases = [(f"accessor_{which}_count_{label}", _gltf_with_count(file_format, good, which, change))
                 for which in ("POSITION", "indices") for label, change in (("plus_1", 1), ("minus_1", -1))]
    if file_format not in ("stl_ascii", "stl_binary"):  # STL has no indices
        for label, index in (("out_of_range", n_vertices + 5), ("negative", -n_vertices - 7)):
            damaged = faces.copy()
            damaged[n_faces // 3, 1] = index
            cases.append((f"face_index_{label}", _with_faces(file_format, good, vertices, damaged)))
    return cases


def _with_faces(file_format: str, good: bytes, vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """The file with these (possibly invalid) faces, written as the format writes indices."""
    if file_format == "off":
        header = b"OFF\n%d %d 0\n" % (len(vertices), len(faces))
        body = "".join("%.10f %.10f %.10f\n" % tuple(v) for v in vertices)
        return header + (body + "".join("3 %d %d %d\n" % tuple(f) for f in faces)).encode()
    if file_format == "obj":
        body = "".join("v %.8f %.8f %.8f\n" % tuple(v) for v in vertices)
        return (body + "".join("f %d %d %d\n" % tuple(f + 1) for f in faces)).encode()
    if file_format == "ply_ascii":
        header = good[:good.index(b"end_header\n") + len(b"end_header\n")]
        body = "".join("%.8f %.8f %.8f\n" % tuple(v) for v in vertices)
        return header + (body + "".join("3 %d %d %d\n" % tuple(f) for f in faces)).encode()
    if file_format == "ply_binary":
        header = good[:good.index(b"end_header\n") + len(b"end_header\n")]
        face_records = b"".join(struct.pack("<B3i", 3, *map(int, f)) for f in faces)
        return header + np.asarray(vertices, dtype="<f4").tobytes() + face_records
    return _gltf_with_indices(file_format, good, faces)


def _gltf_parts(file_format: str, good: bytes) -> tuple[dict, bytearray]:
    """(JSON document, binary buffer) of a glTF (embedded base64 buffer) or GLB file."""
    import base64

    if file_format == "glb":
        json_length = struct.unpack("<I", good[12:16])[0]
        document = json.loads(good[20:20 + json_length])
        binary = bytearray(good[20 + json_length + 8:])
    else:
        document = json.loads(good)
        uri = document["buffers"][0]["uri"]
        binary = bytearray(base64.b64decode(uri.split(",", 1)[1]))
    return document, binary


def _gltf_file(file_format: str, document: dict, binary: bytes) -> bytes:
    import base64

    if file_format == "glb":
        text = json.dumps(document).encode()
        text += b" " * (-len(text) % 4)
        binary = bytes(binary) + b"\0" * (-len(binary) % 4)
        body = struct.pack("<I4s", len(text), b"JSON") + text + struct.pack("<I4s", len(binary), b"BIN\0") + binary
        return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body
    document["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(binary).decode()
    return json.dumps(document).encode()


def _gltf_with_count(file_format: str, good: bytes, which: str, change: int) -> bytes:
    document, binary = _gltf_parts(file_format, good)
    primitive = document["meshes"][0]["primitives"][0]
    accessor = primitive["indices"] if which == "indices" else primitive["attributes"][which]
    document["accessors"][accessor]["count"] += change * (3 if which == "indices" else 1)
    return _gltf_file(file_format, document, binary)


def _gltf_with_indices(file_format: str, good: bytes, faces: np.ndarray) -> bytes:
    document, binary = _gltf_parts(file_format, good)
    accessor = document["accessors"][document["meshes"][0]["primitives"][0]["indices"]]
    view = document["bufferViews"][accessor["bufferView"]]
    start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    dtype = {5121: "<u1", 5123: "<u2", 5125: "<u4"}[accessor["componentType"]]
    flat = np.asarray(faces, dtype=np.int64).ravel()
    indices = flat.astype(dtype) if flat.min() >= 0 else flat.astype("<i8").astype(dtype)
    binary[start:start + indices.nbytes] = indices.tobytes()
    return _gltf_file(file_format, document, binary)
