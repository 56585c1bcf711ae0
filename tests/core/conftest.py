"""Shared fixtures of the core-tier intake tests (no bpy)."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from pathlib import Path

# before numpy is imported: OpenBLAS reads it once, when the library loads (set after the
# import, numpy's BLAS ran on every core while scipy's ran on one)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Python keeps what it compiles (__pycache__), here and in every process a test starts: the
# environments are installed without compiling (Makefile), and where PYTHONDONTWRITEBYTECODE
# is set every `shapegen` a test ran compiled numpy, scipy, trimesh and the core anew (1-1.7
# CPU-s a launch, against 0.3-0.7 with the compiled files kept)
sys.dont_write_bytecode = False
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from shapegen_core.demo_data import make_vases  # noqa: E402
from shapegen_core.meshes.mesh import Mesh  # noqa: E402
from shapegen_core.preprocess import ShapeTransform  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: shared_data, where the real collections are
from shared_data import folder_or_skip  # noqa: E402


def pytest_collection_modifyitems(config, items):
    """The files holding `quality` tests (the long ones) run first: with a file per worker
    (`--dist loadfile`) a tier that ends on one of them keeps one core busy while the other
    idles. The order is otherwise the collected one."""
    long_files = {item.path for item in items if item.get_closest_marker("quality")}
    items.sort(key=lambda item: item.path not in long_files)


@pytest.fixture(scope="session")
def small_vases():
    """Six coarse procedural vases in random input poses (yaw, scale, translation)."""
    return make_vases(6, seed=1, resolution=(12, 18))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def random_mesh(rng: np.random.Generator, n_vertices: int = 40, n_faces: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Random vertices and non-degenerate triangles (no repeated index)."""
    vertices = rng.normal(size=(n_vertices, 3))
    faces = []
    while len(faces) < n_faces:
        f = rng.choice(n_vertices, 3, replace=False)
        faces.append(f)
    return vertices, np.asarray(faces, dtype=np.int64)


def random_surface(rng: np.random.Generator, subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A clean mesh in random vertex and face order: an icosphere with jittered radii
    (closed, outward-wound, no coincident vertices), so intake keeps it exactly as it is."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions)
    order = rng.permutation(len(sphere.vertices))
    vertices = np.asarray(sphere.vertices)[order] * rng.uniform(0.8, 1.2, (len(order), 1))
    faces = np.argsort(order)[np.asarray(sphere.faces)][rng.permutation(len(sphere.faces))]
    return vertices, faces.astype(np.int64)


def unit_cube() -> Mesh:
    """Closed unit cube [0, 1]^3, 12 outward-facing triangles."""
    import trimesh

    box = trimesh.creation.box(extents=(1, 1, 1))
    return Mesh(np.asarray(box.vertices) + 0.5, np.asarray(box.faces), name="cube")


def subdivided(mesh: Mesh, steps: int, name: str | None = None) -> Mesh:
    """The same surface with 4^steps times the faces (midpoint subdivision): a dense mesh."""
    import trimesh

    vertices, faces = mesh.vertices, mesh.faces
    for _ in range(steps):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return Mesh(vertices, faces, name=name or mesh.name)


#: a y-up file among z-up ones (the other common file convention): a quarter turn about x
Y_UP_FILE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def placed(meshes, seed: int) -> list[Mesh]:
    """Each shape at a random size and position, not turned: its pose as given is its own."""
    rng = np.random.default_rng(seed)
    return [m.with_vertices(ShapeTransform(np.eye(3), rng.uniform(0.5, 2), rng.uniform(-1, 1, 3))
                            .to_normalised(m.vertices)) for m in meshes]


def on_a_floor(meshes, seed: int) -> list[Mesh]:
    """Random size, every shape's lowest point on z = 0 and its origin near the middle of
    its base: files that share a floor (scans, statues, one Blender ground plane)."""
    rng = np.random.default_rng(seed)
    floored = []
    for mesh in meshes:
        vertices = mesh.vertices * rng.uniform(0.5, 2.0)
        low = vertices.min(axis=0)
        middle = (low + vertices.max(axis=0)) / 2
        floored.append(mesh.with_vertices(vertices - [middle[0], middle[1], low[2]]
                                          + [*rng.uniform(-0.05, 0.05, 2), 0]))
    return floored


def turned(meshes, turns: dict) -> list[Mesh]:
    """The files re-saved turned: mesh i's vertices by turns[i] about its origin."""
    return [m.with_vertices(m.vertices @ turns[i].T) if i in turns else m for i, m in enumerate(meshes)]


def tosca_class(name: str) -> Path:
    """The TOSCA folder `name` (an animal, or people); the test is skipped, naming it, when absent."""
    return folder_or_skip("tosca", name)


def psb_class(name: str) -> Path:
    """The PSB class folder `name`; the test is skipped, naming it, when absent."""
    return folder_or_skip("psb", name)


def central_diff(f, x, h=1e-5):
    """Fourth-order central differences, one coordinate at a time."""
    out = np.empty_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        out[i] = (8 * (f(x + e) - f(x - e)) - (f(x + 2 * e) - f(x - 2 * e))) / (12 * h)
    return out


def in_process(*args) -> subprocess.CompletedProcess:
    """`shapegen ARGS` run by `shapegen_core.app.cli.main` in this process, its exit status,
    stdout and stderr given as a subprocess gives them (argparse's exits included). For the
    checks of parsing, validation and their one-line errors: a `shapegen` process costs a
    second of CPU before it reads its arguments. The runs that check the installed entry
    point end to end stay subprocesses."""
    from shapegen_core.app.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = main([str(arg) for arg in args])
        except SystemExit as exc:  # argparse: a usage error (2), --help or --version (0)
            status = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    return subprocess.CompletedProcess(["shapegen", *map(str, args)], status, out.getvalue(), err.getvalue())
