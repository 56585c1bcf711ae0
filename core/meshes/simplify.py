"""A coarse proxy of a dense surface in time linear in its size: vertex clustering
(Rossignac & Borrel 1993), split by normal direction.

Dense meshes (sculpts of a million vertices) cost the pose search, the signatures and
the registration time and memory in proportion to their faces, while what those steps
need is the shape at the scale of the landmarks. `proxy_mesh` gives a mesh above a size
a stand-in of at most about `max_faces` faces: vertices are grouped by the
cell of a uniform grid they fall in *and* by the main direction of their normal (one of
±x, ±y, ±z), so the two sides of a thin wall never merge; each group becomes one vertex at
its members' mean, every face whose corners land in three different groups is kept with
its winding (duplicates dropped). The proxy stays within about one cell of the surface.

Measured (1.8M-vertex subdivided PSB fish to 20k–40k faces, loaded machine):
quadric simplification took 23–37 s (fast-simplification 0.2.0) and 55–123 s (pyfqmr
0.5.0, which stopped at 133k faces) against the ~1 s budget of a whole registration,
so the proxy is built here in numpy (sorts and bincounts) and the quadric libraries are
not a dependency. Final landmarks are placed exactly on the full surface
(core/correspond/proxy.py), so the proxy's coarseness never reaches a result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .mesh import Mesh

__all__ = ["DENSE_FACES", "DENSE_RATIO", "POSE_PROXY_FACES", "REGISTRATION_PROXY_FACES", "Proxy", "proxy_mesh"]

#: Faces of the proxy a registration round registers against (the size of a 20k-vertex mesh).
REGISTRATION_PROXY_FACES = 40_000
#: a shape with more than this many times `CorrespondenceSettings.proxy_faces` faces is
#: registered against its proxy (core/correspond/proxy.py)
DENSE_RATIO = 2.5
#: Meshes with more faces than this (100k: DENSE_RATIO × REGISTRATION_PROXY_FACES) are dense
#: and get a proxy (about 50k vertices: every mesh of the shared test and benchmark
#: collections is below, so their results are unchanged).
DENSE_FACES = int(DENSE_RATIO * REGISTRATION_PROXY_FACES)
#: Faces of the proxy Prepare's pose search and signatures see (they compare coarse shape).
POSE_PROXY_FACES = 20_000
#: Grid refinements tried when the first cell size leaves too many faces.
_MAX_TRIES = 6


@dataclass(frozen=True, eq=False)
class Proxy:
    """A mesh and the coarse stand-in the expensive steps use (the mesh itself when small).

    representatives: for every proxy vertex, one vertex of the full mesh in its group (a
    point on the full surface near it; None when the proxy is the mesh itself)."""

    mesh: Mesh
    representatives: np.ndarray | None = None

    @property
    def is_full(self) -> bool:
        return self.representatives is None


def proxy_mesh(mesh: Mesh, max_faces: int = REGISTRATION_PROXY_FACES, above: int | None = None) -> Proxy:
    """The vertex-clustering proxy of `mesh` with at most about `max_faces` faces; the mesh
    itself when it has at most `above` faces (default `max_faces`). The cell size starts
    from the area per wanted vertex (a closed surface has about twice as many faces as
    vertices) and grows until the face count fits."""
    if mesh.n_faces <= (max_faces if above is None else max(above, max_faces)):
        return Proxy(mesh)
    used = mesh.used_vertices()
    points = mesh.vertices[used]
    direction = _normal_class(mesh)[used]
    lower = points.min(axis=0)
    cell = float(np.sqrt(2.0 * mesh.area() / max_faces))
    for _ in range(_MAX_TRIES):
        grid = np.floor((points - lower) / cell).astype(np.int64)
        size = grid.max(axis=0) + 1
        key = ((grid[:, 0] * size[1] + grid[:, 1]) * size[2] + grid[:, 2]) * 6 + direction
        _, first, group = np.unique(key, return_index=True, return_inverse=True)
        group = group.ravel()
        vertex_group = np.full(mesh.n_vertices, -1, dtype=np.int64)
        vertex_group[used] = group
        faces = _kept_faces(vertex_group[mesh.faces])
        if len(faces) <= max_faces * 1.05:
            break
        cell *= float(np.sqrt(len(faces) / max_faces)) * 1.05
    counts = np.bincount(group).astype(np.float64)
    centres = np.stack([np.bincount(group, weights=points[:, d]) for d in range(3)], axis=1) / counts[:, None]
    coarse = Mesh.from_polygons(centres, faces, name=mesh.name)
    return Proxy(coarse, used[first])


def _normal_class(mesh: Mesh) -> np.ndarray:
    """Per vertex, the axis and sign of its normal's largest component (0..5): of the sum
    of its faces' area-weighted normals (the vertex normal before normalising), summed by
    one sparse product with the face–vertex incidence."""
    corners = mesh.faces.ravel()
    incidence = sp.csr_matrix((np.ones(len(corners)), corners, np.arange(0, len(corners) + 1, 3)),
                              shape=(mesh.n_faces, mesh.n_vertices))
    normals = np.asarray(incidence.T @ mesh.face_normals_unnormalised())
    axis = np.argmax(np.abs(normals), axis=1)
    negative = normals[np.arange(len(normals)), axis] < 0
    return 2 * axis + negative


def _kept_faces(corners: np.ndarray) -> np.ndarray:
    """Faces whose three corner groups differ, each once (the same triangle with the same
    winding listed twice is one face; a rotation of the corners is the same triangle)."""
    distinct = (corners[:, 0] != corners[:, 1]) & (corners[:, 1] != corners[:, 2]) & (corners[:, 0] != corners[:, 2])
    corners = corners[distinct]
    start = np.argmin(corners, axis=1)
    rolled = np.stack([corners[np.arange(len(corners)), (start + k) % 3] for k in range(3)], axis=1)
    return np.unique(rolled, axis=0)
