"""Registration of dense shapes against their proxies, the final landmarks placed exactly
on the full surfaces.

Every round of the groupwise registration (§4.2.7) needs closest points on each target,
at the scale of the landmarks. A shape with more than 2.5 × `CorrespondenceSettings.proxy_faces` faces (100k)
is registered against its vertex-clustering proxy of about proxy_faces faces (core/meshes/simplify.py), built once per
shape in a worker, so a round costs the same for a sculpt of a million vertices as for a
mesh of the proxy's size. After the last round every template point is placed on the
*full* surface, exactly as `registration._place` does on a surface it registered
against: the closest compatible point (the closest of any normal where none is near),
found by core/geometry/nearby.py from an upper bound, the distance to the nearest
representative vertex of the proxy (a point of the full surface), among the faces near the
points only (core/geometry/nearfaces.py: a pass of integer arithmetic over the vertices and
faces, float work only near the points; no grid or tree over every face, no copy of every
vertex in the registration frame). Shapes below the size are registered against their own
surface as before, and nothing here touches them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.nearby import closest_within
from ..meshes.mesh import Mesh
from ..meshes.simplify import DENSE_RATIO, Proxy, proxy_mesh
from ..meshes.spill import StoredMesh, full_mesh
from .registration import Registration, fit_residual

__all__ = ["DENSE_RATIO", "PlacementTask", "ProxyTask", "build_proxy", "dense_shapes", "face_normals_at",
           "place_dense", "place_on_full_surface", "proxies_of"]


@dataclass(frozen=True)
class ProxyTask:
    """One dense mesh to simplify (picklable; one mesh per worker call): in memory, or
    kept on disk for the run (`spill.StoredMesh`, loaded by the worker)."""

    mesh: Mesh | StoredMesh
    max_faces: int
    above: int


def build_proxy(task: ProxyTask) -> Proxy:
    """The proxy a worker builds for one mesh (core/meshes/simplify.py)."""
    return proxy_mesh(full_mesh(task.mesh), task.max_faces, task.above)


@dataclass(frozen=True)
class PlacementTask:
    """Everything one worker needs to place one registration's points on a full surface
    (picklable): the full mesh and landmarks in the normalised frame, the registration in
    the registration frame (p -> (p − centre) / scale)."""

    vertices: np.ndarray
    faces: np.ndarray
    representatives: np.ndarray  # vertex indices on the full surface (the proxy's)
    landmarks: np.ndarray
    registration: Registration
    min_cos: float | None  # normal compatibility (None: off)
    centre: np.ndarray
    scale: float


def place_on_full_surface(task: PlacementTask) -> Registration:
    """The registration with its points placed exactly on the full surface (closest
    compatible point, else the closest point; see module docstring), the target normals
    there and the residual recomputed, all in the registration frame. Only the
    representatives and the faces near the points are mapped to that frame."""
    representatives = (task.vertices[task.representatives] - task.centre) / task.scale
    points = task.registration.deformed
    reach, _ = cKDTree(representatives).query(points)
    normals = task.registration.deformed_normals if task.min_cos is not None else None
    placed = closest_within(task.vertices, task.faces, points, reach, normals,
                            -1.0 if task.min_cos is None else task.min_cos, task.centre, task.scale)
    corners = (task.vertices[task.faces[placed.face_index].ravel()] - task.centre) / task.scale
    landmarks = (task.landmarks - task.centre) / task.scale
    return replace(task.registration, placed=placed,
                   normals=_triangle_normals(corners.reshape(-1, 3, 3)),
                   residual=fit_residual(placed, landmarks))



def dense_limit(settings) -> int:
    """Shapes with more faces than this (`simplify.DENSE_RATIO` × proxy_faces) are registered
    against a proxy."""
    return int(DENSE_RATIO * settings.proxy_faces)


def dense_shapes(shapes, settings) -> list[int]:
    """Indices of the shapes registered against a proxy: more than `dense_limit` faces
    (none when registration snaps to vertices)."""
    if settings.data_term.snap_to_vertices:
        return []
    return [i for i, shape in enumerate(shapes) if shape.mesh.n_faces > dense_limit(settings)]


def proxies_of(shapes, dense: list[int], settings, runner, progress) -> list[Proxy]:
    """Per shape what its rounds register against: the proxy of a dense shape, else the
    shape's own mesh (`Proxy.is_full`; a stored one loaded). A stored dense shape's proxy
    built by Prepare at full density (`spill.StoredMesh.proxies`) is used as it is; the
    others are built by `runner`, one mesh per call (a stored mesh loaded by the worker)."""
    key = (settings.proxy_faces, dense_limit(settings))
    missing = [i for i in dense if not (isinstance(shapes[i].mesh, StoredMesh) and key in shapes[i].mesh.proxies)]
    built = runner.map(build_proxy, [ProxyTask(shapes[i].mesh, *key) for i in missing], progress,
                       lambda k: f"proxy of {shapes[missing[k]].name}")
    for i, proxy in zip(missing, built):
        if isinstance(shapes[i].mesh, StoredMesh):
            shapes[i].mesh.proxies[key] = proxy
    made, dense_set = dict(zip(missing, built)), set(dense)
    return [made[i] if i in made else shape.mesh.proxies[key] if i in dense_set else Proxy(full_mesh(shape.mesh))
            for i, shape in enumerate(shapes)]


def _place_loaded(item: tuple) -> Registration:
    """`place_on_full_surface` of (mesh, task without the mesh's arrays): a stored mesh is
    loaded here, in the worker."""
    mesh, task = item
    mesh = full_mesh(mesh)
    return place_on_full_surface(replace(task, vertices=mesh.vertices, faces=mesh.faces))


def place_dense(registrations: list[Registration], collection, surfaces: list[Proxy], dense: list[int], settings,
                centre: np.ndarray, scale: float, runner, progress) -> list[Registration]:
    """The registrations with those of the `dense` shapes placed on their full surfaces
    (`place_on_full_surface`, one shape per worker call), in the registration frame."""
    angle = settings.data_term.normal_max_angle
    min_cos = None if angle is None else float(np.cos(np.radians(angle)))
    tasks = [(collection.shapes[i].mesh, PlacementTask(None, None, surfaces[i].representatives,
                                                       collection.landmarks[i].points, registrations[i], min_cos,
                                                       centre, scale)) for i in dense]
    placed = runner.map(_place_loaded, tasks, progress,
                        lambda k: f"landmarks placed on the full surface of {collection.shapes[dense[k]].name}")
    registrations = list(registrations)
    for i, registration in zip(dense, placed):
        registrations[i] = registration
    return registrations


def face_normals_at(mesh: Mesh | StoredMesh, faces: np.ndarray) -> np.ndarray:
    """Unit normals of the given faces only (not of the whole mesh; a stored mesh's faces
    read alone)."""
    return _triangle_normals(mesh.face_corners(faces))


def _triangle_normals(triangles: np.ndarray) -> np.ndarray:
    """Unit normals of (n, 3, 3) triangles (0 for a degenerate one)."""
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    return np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)
