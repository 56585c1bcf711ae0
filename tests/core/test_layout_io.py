"""The template's faces in written files: quads, n-gons and UVs of the input
file come back in `shapegen sample`'s OBJ, PLY and glTF output; only positions change."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from shapegen_core.meshes.reading import read_mesh
from shapegen_core.meshes.writing import write_mesh
from shapegen_core.meshes.layout import FaceLayout, pack_layouts, unpack_layouts

SHAPEGEN = str(Path(sys.executable).parent / "shapegen")
AROUND, RINGS = 12, 6


def run(*args):
    return subprocess.run([SHAPEGEN, *map(str, args)], capture_output=True, text=True, timeout=600)


def vessel(rng) -> tuple[np.ndarray, list[list[int]], np.ndarray]:
    """A closed vessel: rings of quads, a 12-gon cap at each end; vertices, polygons and a
    cylindrical UV per vertex (one seam-free chart per vertex: u around, v up)."""
    height, bulge, phase = rng.uniform(1.5, 2.5), rng.uniform(0.1, 0.5), rng.uniform(0, 1)
    vertices, uv = [], []
    for i in range(RINGS):
        t = i / (RINGS - 1)
        radius = 0.6 + bulge * np.sin(np.pi * (t + phase))
        for k in range(AROUND):
            a = 2 * np.pi * k / AROUND
            vertices.append((radius * np.cos(a), radius * np.sin(a), height * t))
            uv.append((k / AROUND, t))
    polygons = []
    for i in range(RINGS - 1):
        for k in range(AROUND):
            nxt = (k + 1) % AROUND
            polygons.append([i * AROUND + k, i * AROUND + nxt, (i + 1) * AROUND + nxt, (i + 1) * AROUND + k])
    polygons.append(list(reversed(range(AROUND))))
    polygons.append(list(range((RINGS - 1) * AROUND, RINGS * AROUND)))
    return np.array(vertices), polygons, np.array(uv)


def write_obj(path: Path, vertices, polygons, uv) -> None:
    """OBJ with per-corner `vt` indices (UVs shared by vertex index)."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uv]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}" for i in polygon) for polygon in polygons]
    path.write_text("\n".join(lines) + "\n")


def read_obj_faces(path: Path):
    """(face sizes, corner vertex indices, UV of every corner) of an OBJ file."""
    vt, sizes, corners, corner_uv = [], [], [], []
    for line in path.read_text().splitlines():
        parts = line.split()
        if parts and parts[0] == "vt":
            vt.append([float(parts[1]), float(parts[2])])
        elif parts and parts[0] == "f":
            sizes.append(len(parts) - 1)
            for corner in parts[1:]:
                v, t = corner.split("/")[:2]
                corners.append(int(v) - 1)
                corner_uv.append(vt[int(t) - 1])
    return sizes, corners, np.array(corner_uv)


@pytest.fixture(scope="module")
def collection(tmp_path_factory):
    folder = tmp_path_factory.mktemp("vessels")
    rng = np.random.default_rng(11)
    for i in range(6):
        write_obj(folder / f"vessel_{i}.obj", *vessel(rng))
    return folder


@pytest.fixture(scope="module")
def model(collection, tmp_path_factory):
    """`shapegen fit` of the vessels (PPCA, 60 landmarks): the model file the tests below read."""
    path = tmp_path_factory.mktemp("model") / "model.npz"
    result = run("fit", collection, "-o", path, "--model", "ppca", "--landmarks", 60, "--jobs", 1)
    assert result.returncode == 0, result.stderr
    return path


def test_an_obj_with_quads_ngons_and_uvs_is_read_with_its_layout(collection):
    mesh = read_mesh(collection / "vessel_0.obj")
    layout = mesh.report.layout
    vertices, polygons, uv = vessel(np.random.default_rng(11))
    assert layout is not None and layout.sizes.tolist() == [len(p) for p in polygons]
    assert layout.corners.tolist() == [i for p in polygons for i in p]  # outward already: kept as given
    np.testing.assert_allclose(layout.uv, uv[layout.corners], atol=1e-6)
    assert mesh.n_faces == sum(len(p) - 2 for p in polygons)


def test_an_inside_out_file_keeps_its_layout_turned_with_the_mesh(tmp_path):
    vertices, polygons, uv = vessel(np.random.default_rng(3))
    write_obj(tmp_path / "inside_out.obj", vertices, [list(reversed(p)) for p in polygons], uv)
    mesh = read_mesh(tmp_path / "inside_out.obj")
    assert mesh.report.parts_turned_outward == 1
    layout = mesh.report.layout
    normals = mesh.face_normals()
    centre = mesh.vertices.mean(axis=0)
    assert np.mean(np.einsum("ij,ij->i", normals, mesh.triangles.mean(axis=1) - centre) > 0) > 0.9
    # the layout's polygons now run like the mesh's faces: first corner kept, the rest reversed
    first = layout.corners[:4].tolist()
    reversed_quad = list(reversed(polygons[0]))
    assert first == [reversed_quad[0]] + reversed_quad[1:][::-1]


def test_layouts_pack_and_unpack():
    a = FaceLayout(np.array([0, 1, 2, 3, 1]), np.array([4, 3]), np.array([0, 1, 2, 3, 4, 1, 2]),
                   np.arange(14, dtype=float).reshape(7, 2))
    b = FaceLayout(np.arange(3), np.array([3]), np.array([0, 1, 2]))
    back = unpack_layouts(pack_layouts([a, None, b]), 3, "test")
    assert back[1] is None and back[2].uv is None
    np.testing.assert_array_equal(back[0].uv, a.uv)
    assert back[0].corners.tolist() == a.corners.tolist() and back[2].sizes.tolist() == [3]
    assert unpack_layouts({}, 2, "old file") == [None, None]


def test_fit_and_sample_write_the_template_faces_and_uvs(collection, model, tmp_path):
    result = run("sample", model, "-n", 3, "-o", tmp_path / "obj", "--seed", 1)
    assert result.returncode == 0, result.stderr
    templates = [str(t) for t in np.load(tmp_path / "obj" / "landmarks.npz")["templates"]]
    for i, template in enumerate(templates):
        out = tmp_path / "obj" / f"sample_{i:04d}.obj"
        sizes, corners, corner_uv = read_obj_faces(out)
        source_sizes, source_corners, source_uv = read_obj_faces(collection / f"{template}.obj")
        assert sizes == source_sizes and corners == source_corners  # quads and 12-gons as in the file
        np.testing.assert_allclose(corner_uv, source_uv, atol=1e-6)
        moved = trimesh.load(out, process=False, maintain_order=True, skip_materials=True)
        source = read_mesh(collection / f"{template}.obj")
        assert len(moved.vertices) == source.n_vertices
        assert np.abs(np.asarray(moved.vertices) - source.vertices).max() > 1e-3  # positions differ

    for file_format in ("ply", "glb"):
        result = run("sample", model, "-n", 2, "-o", tmp_path / file_format, "--seed", 1, "--format", file_format)
        assert result.returncode == 0, result.stderr
        loaded = trimesh.load(tmp_path / file_format / f"sample_0000.{file_format}", process=False, force="mesh")
        template = read_mesh(collection / f"{templates[0]}.obj")
        np.testing.assert_allclose(np.asarray(loaded.visual.uv)[:, 0] % 1.0,
                                   template.report.layout.vertex_uv()[:, 0] % 1.0, atol=1e-5)
        if file_format == "ply":
            raw = loaded.metadata["_ply_raw"]["face"]["data"]["vertex_indices"]
            assert sorted({len(p) for p in raw}) == [4, AROUND]


def test_a_model_file_keeps_the_layouts_and_older_files_load(model, tmp_path):
    from shapegen_core.base.npzfile import save_npz
    from shapegen_core.app.shape_model import MODEL_FILE_FORMAT, GenerativeShapeModel

    fitted = GenerativeShapeModel.load(model)
    assert all(m.report.layout is not None and m.report.layout.uv is not None for m in fitted.meshes)
    # a version-1 file (before layouts): loads, meshes without layouts
    arrays = dict(np.load(model))
    old = {k: v for k, v in arrays.items()
           if not k.startswith("mesh_layout_") and k not in ("format", "format_version")}
    save_npz(tmp_path / "old.npz", MODEL_FILE_FORMAT, 1, old)
    loaded = GenerativeShapeModel.load(tmp_path / "old.npz")
    assert all(m.report.layout is None for m in loaded.meshes)
    write_mesh(loaded.meshes[0], tmp_path / "plain.obj")
    assert all(line.count(" ") == 3 for line in (tmp_path / "plain.obj").read_text().splitlines() if line[0] == "f")
    assert json.loads(run("info", tmp_path / "old.npz", "--json").stdout)["shapes"] == 6
