"""Exact closest points near a few queries on a dense mesh (core/geometry/nearby.py,
nearfaces.py): the search over the faces near the queries gives exactly what the search
over every face gives, and both what a brute-force test of every (query, face) pair gives,
on a dense mesh with degenerate faces, a few huge faces, queries far from the surface and
normals whose compatible point is far or missing."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from shapegen_core.correspond.proxy import PlacementTask, place_on_full_surface
from shapegen_core.correspond.registration import Registration
from shapegen_core.demo_data import make_vases
from shapegen_core.geometry import closest_points_on_triangles
from shapegen_core.geometry.nearby import closest_within
from shapegen_core.geometry.nearfaces import NearFaces
from shapegen_core.meshes.simplify import proxy_mesh

CENTRE, SCALE = np.array([0.1, -0.2, 0.3]), 0.7
MIN_COS = 0.5


@pytest.fixture(scope="module")
def dense():
    """A vase subdivided twice (26k faces) with degenerate faces (a repeated corner, three
    collinear corners) and three huge faces across it appended."""
    mesh = make_vases(1, seed=5, resolution=(26, 32))[0].mesh
    vertices, faces = mesh.vertices, mesh.faces
    for _ in range(2):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    n = len(vertices)
    middle = (vertices[faces[0, 0]] + vertices[faces[0, 1]]) / 2
    vertices = np.vstack([vertices, middle])
    extra = [[faces[5, 0], faces[5, 0], faces[5, 1]],  # a repeated corner
             [faces[0, 0], faces[0, 1], n],  # three collinear corners
             [0, n // 2, n - 1], [n // 3, 2 * n // 3, 10], [7, n // 5, 4 * n // 5]]  # huge faces
    return vertices, np.vstack([faces, extra]).astype(np.int32)


def _queries(vertices, faces, rng, count=240):
    """Points in the search frame: near the surface, far from it, on it; normals: the
    surface's there, reversed (the compatible side is across a wall), or random; bounds:
    the distance to the nearest of every 40th vertex (as from a proxy's representatives)."""
    diagonal = np.linalg.norm(np.ptp(vertices, axis=0))
    near = vertices[rng.choice(len(vertices) - 1, count)] + rng.normal(scale=0.01 * diagonal, size=(count, 3))
    near[: count // 8] += rng.normal(size=(count // 8, 3)) * 0.3 * diagonal  # far from the surface
    near[count // 8: count // 4] = vertices[rng.choice(len(vertices) - 1, count // 8)]  # exactly on vertices
    points = (near - CENTRE) / SCALE
    triangles = vertices[faces]
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals = cross[rng.choice(len(faces) - 5, count)]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[count // 4: count // 2] *= -1.0
    normals[count // 2: 5 * count // 8] = rng.normal(size=(count // 8, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    representatives = (vertices[::40] - CENTRE) / SCALE
    reach, _ = cKDTree(representatives).query(points)
    return points, normals, reach


def _brute_force(vertices, faces, points, reach, normals):
    """Every (query, face) pair tested: the closest point (lowest face among equally close),
    and with normals the closest compatible one within 4 × reach, else the closest."""
    frame = (vertices - CENTRE) / SCALE
    triangles = frame[faces]
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    length = np.linalg.norm(cross, axis=1)
    distance, face = np.empty(len(points)), np.empty(len(points), dtype=np.int64)
    for row, point in enumerate(points):
        closest, _ = closest_points_on_triangles(np.repeat(point[None], len(faces), axis=0), triangles)
        gap = np.linalg.norm(closest - point, axis=1)
        if normals is not None:
            cosine = cross @ normals[row] / np.where(length > 0, length, 1.0)
            ok = (length > 0) & (cosine >= MIN_COS) & (gap <= 4.0 * reach[row])
            if ok.any():
                gap = np.where(ok, gap, np.inf)
        face[row] = np.flatnonzero(gap == gap.min())[0]
        distance[row] = gap[face[row]]
    return distance, face


@pytest.mark.parametrize("with_normals", [True, False])
def test_search_near_the_queries_equals_the_full_mesh_search(dense, rng, with_normals):
    vertices, faces = dense
    points, normals, reach = _queries(vertices, faces, rng, 120)  # 15 of each kind; the brute force is the cost
    normals = normals if with_normals else None
    near = closest_within(vertices, faces, points, reach, normals, MIN_COS, CENTRE, SCALE)
    full = closest_within(vertices, faces, points, reach, normals, MIN_COS, CENTRE, SCALE, everywhere=True)
    for field in ("points", "face_index", "barycentric", "distance"):
        np.testing.assert_array_equal(getattr(near, field), getattr(full, field), err_msg=field)
    distance, face = _brute_force(vertices, faces, points, reach, normals)
    np.testing.assert_array_equal(near.distance, distance)
    np.testing.assert_array_equal(near.face_index, face)
    on_face = np.einsum("nk,nkd->nd", near.barycentric, ((vertices - CENTRE) / SCALE)[faces[near.face_index]])
    np.testing.assert_allclose(near.points, on_face, rtol=0, atol=1e-12)
    if with_normals:  # the cases the queries were made for all occur
        plain = closest_within(vertices, faces, points, reach, None, MIN_COS, CENTRE, SCALE)
        assert (near.distance > reach).any()  # compatible points beyond the bound
        assert ((near.distance == plain.distance) & (near.face_index == plain.face_index)).any()
        assert (near.distance > plain.distance).sum() > len(points) // 8


def test_near_faces_pair_every_face_within_the_distance(dense, rng):
    """NearFaces' pairs hold every (query, face) within the distance, the degenerate and
    huge faces included; vertices outside the queries' region are clipped, not lost."""
    vertices, faces = dense
    points = vertices[rng.choice(len(vertices) - 1, 60)] + rng.normal(scale=0.02, size=(60, 3))
    distance = rng.uniform(0.0, 0.08, 60)
    low, high = (points - distance[:, None]).min(axis=0), (points + distance[:, None]).max(axis=0)
    low[0] = high[0] - 0.3 * (high[0] - low[0])  # a narrow region: most of the mesh lies outside it
    inside = (points - distance[:, None] >= low).all(axis=1)
    points, distance = points[inside], distance[inside]
    selected, rows, at, used = NearFaces(vertices, faces, low, high, float(np.median(distance))).pairs(points,
                                                                                                       distance)
    assert np.array_equal(used, distance) and np.all(np.diff(selected) > 0)
    paired = set(zip(rows.tolist(), selected[at].tolist()))
    triangles = vertices[faces]
    for row, point in enumerate(points):
        closest, _ = closest_points_on_triangles(np.repeat(point[None], len(faces), axis=0), triangles)
        within = np.flatnonzero(np.linalg.norm(closest - point, axis=1) <= distance[row])
        assert all((row, face) in paired for face in within.tolist())
    assert len(selected) < 0.5 * len(faces)


def test_placement_equals_the_full_mesh_placement(dense, rng):
    """place_on_full_surface (faces near the landmarks only) equals the same placement over
    every face: points, faces, barycentrics, normals and residual, in the registration frame."""
    vertices, faces = dense
    from shapegen_core.meshes.mesh import Mesh

    mesh = Mesh(vertices, faces[:-5])
    proxy = proxy_mesh(mesh, 3000)
    points, normals, _ = _queries(vertices, faces, rng, 200)
    registration = Registration(None, None, points, 0.0, 1, np.zeros(1), normals)
    task = PlacementTask(vertices, faces, proxy.representatives, points[:50] * SCALE + CENTRE, registration, MIN_COS,
                         CENTRE, SCALE)
    placed = place_on_full_surface(task)
    reach, _ = cKDTree((vertices[proxy.representatives] - CENTRE) / SCALE).query(points)
    full = closest_within(vertices, faces, points, reach, normals, MIN_COS, CENTRE, SCALE, everywhere=True)
    for field in ("points", "face_index", "barycentric", "distance"):
        np.testing.assert_array_equal(getattr(placed.placed, field), getattr(full, field), err_msg=field)
    triangles = ((vertices - CENTRE) / SCALE)[faces[full.face_index]]
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    np.testing.assert_allclose(placed.normals, cross / np.linalg.norm(cross, axis=1, keepdims=True), atol=1e-12)
    assert np.isfinite(placed.residual) and placed.deformed is points
