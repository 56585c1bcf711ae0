"""Full-density meshes kept on disk for one run instead of in memory.

`shapegen fit` on 20 sculpts of 1.4M vertices held every mesh (float64 vertices, int32
faces: ~70 MB each, 1.4 GB) in the main process from reading to saving, while every stage
after reading needs a mesh at full density only in per-shape steps. A `SpillStore` is a
temporary folder for one run: a mesh above `SpillStore.above` faces (`DENSE_FACES`) is
written there as two uncompressed .npy files where it is first read (a reading worker),
and the main process keeps a `StoredMesh`: its name, sizes, intake report, the small
summaries computed once on the full surface (area, bounds, surface moments: whatever
`Mesh.cached` holds) and the proxies built at full density (Prepare's pose proxy,
correspondence's registration proxy, core/meshes/simplify.py). A per-shape step that needs the
full surface loads one mesh (`StoredMesh.load`, `loaded`, `full_mesh`), in a worker where
the work is already per shape. Closing the store (the end of a `with` block: success,
error or cancel alike) deletes the folder.

Meshes at or below `above` faces are never stored: they stay `Mesh`es in memory and every
stage treats them exactly as before. A stored mesh loads as the same arrays it was
written from (.npy is exact), with its summaries, so what is computed on it is the same.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..base.errors import ShapeGenError
from .mesh import Mesh, MeshReport, MeshSizes
from .simplify import DENSE_FACES, POSE_PROXY_FACES, REGISTRATION_PROXY_FACES, Proxy, proxy_mesh

__all__ = ["POSE_PROXY", "REGISTRATION_PROXY", "SpillStore", "StoredArray", "StoredMesh", "full_mesh",
           "keep_dense", "loaded", "proxy_of"]

#: (max_faces, above) of the proxy Prepare's pose search sees (core/preprocess/prepare.py)
POSE_PROXY = (POSE_PROXY_FACES, DENSE_FACES)
#: (max_faces, above) of the proxy correspondence registers against at the default settings
REGISTRATION_PROXY = (REGISTRATION_PROXY_FACES, DENSE_FACES)


@dataclass(frozen=True)
class StoredArray:
    """One array of a stored mesh: an .npy file, its shape and dtype; `np.asarray` reads it
    (so a `npzfile.Concatenation` streams a model's meshes into its file one at a time)."""

    path: str
    shape: tuple
    dtype: np.dtype

    def __len__(self) -> int:
        return self.shape[0]

    def __array__(self, dtype=None, copy=None):
        array = _read(self.path)
        return array if dtype is None else array.astype(dtype, copy=False)


@dataclass(eq=False)
class StoredMesh(MeshSizes):
    """A mesh kept in a `SpillStore`: what the main process holds of it (module docstring).
    `summaries`: small `Mesh.cached` values of the full surface; `proxies`: its proxies
    by (max_faces, above), built once at full density."""

    name: str
    vertices: StoredArray
    faces: StoredArray
    report: MeshReport = field(default_factory=MeshReport)
    summaries: dict = field(default_factory=dict)
    proxies: dict = field(default_factory=dict)

    @classmethod
    def write(cls, mesh: Mesh, folder: str | os.PathLike) -> "StoredMesh":
        """`mesh` written into `folder` (its summaries kept)."""
        stem = Path(folder) / uuid.uuid4().hex
        stored = cls(mesh.name, _write(f"{stem}-vertices.npy", mesh.vertices), _write(f"{stem}-faces.npy", mesh.faces),
                     mesh.report)
        stored.remember(mesh)
        return stored

    def load(self) -> Mesh:
        """The full mesh (read-only arrays as written), with the summaries known so far."""
        vertices, faces = _read(self.vertices.path), _read(self.faces.path)
        mesh = Mesh(vertices, faces, name=self.name, report=self.report)
        mesh.__dict__["_cached"] = dict(self.summaries)
        return mesh

    def remember(self, mesh: Mesh) -> None:
        """Keep what was computed once on the loaded `mesh` (`Mesh.cached`: small values)."""
        self.summaries.update(mesh.__dict__.get("_cached", {}))

    def cached(self, key: str, compute):
        """`Mesh.cached` on the full surface: loaded once to compute it, then kept."""
        return self._summary(key, lambda mesh: mesh.cached(key, compute))

    def area(self) -> float:
        return self._summary("area", Mesh.area)

    def bounds(self) -> np.ndarray:
        return self._summary("bounds", Mesh.bounds).copy()

    def _summary(self, key: str, ask):
        if key not in self.summaries:
            with loaded(self) as mesh:
                ask(mesh)
        return self.summaries[key]

    def face_corners(self, faces: np.ndarray) -> np.ndarray:
        """(n, 3, 3) corner coordinates of the given faces, read from the files without
        reading the rest (`Mesh.face_corners`)."""
        corners = np.array(np.load(self.faces.path, mmap_mode="r")[np.asarray(faces)])
        return np.array(np.load(self.vertices.path, mmap_mode="r")[corners])

    def with_vertices(self, vertices: np.ndarray) -> "StoredMesh":
        """Same connectivity (the same faces file), new vertex positions written beside it."""
        folder = Path(self.faces.path).parent
        return StoredMesh(self.name, _write(folder / f"{uuid.uuid4().hex}-vertices.npy", np.asarray(vertices)),
                          self.faces, self.report)

    def keep_proxy(self, mesh: Mesh, key: tuple[int, int]) -> None:
        """Build the proxy (max_faces, above) = `key` of this shape's loaded full `mesh` and
        keep it (nothing is kept when the proxy would be the mesh itself)."""
        proxy = proxy_mesh(mesh, *key)
        if not proxy.is_full:
            self.proxies[key] = proxy
        self.remember(mesh)


class SpillStore:
    """A per-run temporary folder of dense meshes (module docstring); use it as a context
    manager (the folder is removed on leaving, whatever happened). `parent`: where the
    folder is made (default: the system's temporary folder)."""

    def __init__(self, above: int = DENSE_FACES, parent: str | os.PathLike | None = None):
        self.above = int(above)
        self.folder = Path(tempfile.mkdtemp(prefix="shapegen-spill-", dir=parent))

    @property
    def target(self) -> tuple[str, int]:
        """(folder, above): what a reading worker needs to keep its mesh here (`keep_dense`)."""
        return str(self.folder), self.above

    def keep(self, mesh: Mesh) -> "Mesh | StoredMesh":
        return keep_dense(mesh, *self.target)

    def close(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> "SpillStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def keep_dense(mesh: Mesh, folder: str, above: int) -> "Mesh | StoredMesh":
    """`mesh` itself when it has at most `above` faces, else stored in `folder` with its
    pose proxy built now, while it is at full density (`POSE_PROXY`)."""
    if mesh.n_faces <= above:
        return mesh
    stored = StoredMesh.write(mesh, folder)
    stored.keep_proxy(mesh, POSE_PROXY)
    return stored


def full_mesh(mesh: "Mesh | StoredMesh") -> Mesh:
    """The mesh at full density: itself, or a stored one loaded."""
    return mesh.load() if isinstance(mesh, StoredMesh) else mesh


@contextmanager
def loaded(mesh: "Mesh | StoredMesh"):
    """The full mesh for one per-shape step; a stored one keeps the summaries computed on it."""
    full = full_mesh(mesh)
    try:
        yield full
    finally:
        if full is not mesh:
            mesh.remember(full)


def proxy_of(mesh: "Mesh | StoredMesh", max_faces: int, above: int) -> Proxy:
    """`simplify.proxy_mesh(mesh, max_faces, above)`; a stored mesh's proxy is built once
    (loading the mesh) and kept with it."""
    if not isinstance(mesh, StoredMesh):
        return proxy_mesh(mesh, max_faces, above)
    key = (max_faces, above)
    if key not in mesh.proxies:
        with loaded(mesh) as full:
            mesh.keep_proxy(full, key)
            if key not in mesh.proxies:  # at most `above` faces: the proxy is the mesh itself
                return Proxy(full)
    return mesh.proxies[key]


def _write(path, array: np.ndarray) -> StoredArray:
    np.save(path, array, allow_pickle=False)
    return StoredArray(str(path), tuple(array.shape), array.dtype)


def _read(path: str) -> np.ndarray:
    """A stored array, read-only (a `Mesh` keeps it without a copy)."""
    try:
        array = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise ShapeGenError(f"{path}: a mesh kept for this run is gone (its spill store was closed: load the "
                            "saved model or prepared file instead)") from None
    array.flags.writeable = False
    return array
