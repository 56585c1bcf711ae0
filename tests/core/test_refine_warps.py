"""Groupwise refinement by kernel warps (issue 13, third round): core/correspond/warps.py."""

import numpy as np
import pytest

from shapegen_core.collection import PrepareSettings, prepare_meshes
from shapegen_core.correspond import CorrespondenceSettings, correspond
from shapegen_core.correspond.objective import CompactnessTerm, combined
from shapegen_core.correspond.shards import Shards
from shapegen_core.correspond.warps import _Stage, refine_warps, warp_basis
from shapegen_core.datasets import make_vases
from shapegen_core.geometry import TargetSurface
from shapegen_core.geometry.affine_graph import knn_graph
from shapegen_core.mesh import Mesh

SETTINGS = CorrespondenceSettings(refine="population", refine_iterations=8)


@pytest.fixture(scope="module")
def vases():
    shapes = make_vases(5, seed=3, resolution=(24, 32))
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=150, seed=0))
    nicp = correspond(prepared, CorrespondenceSettings(), jobs=1)
    return [s.mesh for s in prepared.shapes], nicp


def test_kernels_cover_the_graph_and_do_not_cross_a_thin_wall():
    # two parallel sheets 0.01 apart, facing away from each other, joined in the k-NN graph
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 10), np.linspace(0, 1, 10)), -1).reshape(-1, 2)
    points = np.r_[np.c_[grid, np.zeros(100)], np.c_[grid, np.full(100, 0.01)]]
    normals = np.r_[np.tile([0, 0, -1.0], (100, 1)), np.tile([0, 0, 1.0], (100, 1))]
    edges = knn_graph(points, 6)
    assert np.any((edges[:, 0] < 100) != (edges[:, 1] < 100))  # the graph itself crosses the wall
    basis = warp_basis(points, normals, edges, 4, 1.0)
    assert basis.weights.shape == (4, 200)
    assert np.allclose(basis.weights[np.arange(4), basis.centres], 1.0)
    sheet = basis.centres >= 100
    assert sheet.any() and (~sheet).any()  # both sheets get kernels (farthest-point sampling)
    assert np.all(basis.weights[sheet][:, :100] == 0) and np.all(basis.weights[~sheet][:, 100:] == 0)
    # frames are tangent to the centre's normal
    assert np.allclose(np.einsum("kjd,kd->kj", basis.directions, normals[basis.centres]), 0, atol=1e-12)


def _sheets(n_shapes=4, n_landmarks=60, seed=0):
    """Flat square sheets of different sizes (z = 0, normals +z) with landmarks inside
    them: the closest point of a tangent move is the move itself, so the chain rule is
    exact there."""
    rng = np.random.default_rng(seed)
    u = np.linspace(0.0, 1.0, 9)
    grid = np.stack(np.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)
    quads = np.array([[i * 9 + j, (i + 1) * 9 + j, (i + 1) * 9 + j + 1, i * 9 + j + 1]
                      for i in range(8) for j in range(8)])
    faces = np.r_[quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]
    meshes, points, face_index, barycentric = [], [], [], []
    layout = rng.uniform(0.3, 0.7, size=(n_landmarks, 2))
    for m in range(n_shapes):
        size = 1.0 + 0.3 * m
        mesh = Mesh(np.c_[size * grid, np.zeros(len(grid))], faces)
        wobble = layout + 0.03 * rng.normal(size=layout.shape)
        placed = TargetSurface(mesh.vertices, mesh.faces).closest(np.c_[size * wobble, np.zeros(n_landmarks)])
        meshes.append(mesh)
        points.append(placed.points), face_index.append(placed.face_index), barycentric.append(placed.barycentric)
    return meshes, np.stack(points), np.stack(face_index), np.stack(barycentric), knn_graph(layout_points(layout), 6)


def layout_points(layout):
    return np.c_[layout, np.zeros(len(layout))]


def test_chain_rule_gradient_matches_finite_differences():
    meshes, points, face_index, barycentric, edges = _sheets()
    shards = Shards(meshes, points, face_index, barycentric, SETTINGS.refine_sigma)
    state = shards.propose(None).state
    term = CompactnessTerm(state, 0.01, "similarity", 1.0)
    stage = _Stage(warp_basis(term.aligned(state.points).mean(axis=0), state.face_normals[0], edges, 5, 1.0), term,
                   state.face_normals)

    def energy(a):
        moved = shards.propose(stage.field(a))
        value_c, grad_c = term.evaluate(moved.state)
        value, gradient = combined((1.0, 1.0), value_c, grad_c, moved.spread, moved.spread_gradient)
        return value.total, stage.chain(gradient, moved.state.face_normals)

    rng = np.random.default_rng(1)
    base = 0.05 * rng.normal(size=(4, 5, 2))
    assert energy(base)[0] != energy(np.zeros_like(base))[0]
    _, gradient = energy(base)
    for _ in range(3):
        direction = rng.normal(size=base.shape)
        step = 1e-6
        numeric = (energy(base + step * direction)[0] - energy(base - step * direction)[0]) / (2 * step)
        assert np.sum(gradient * direction) == pytest.approx(numeric, rel=1e-5, abs=1e-8)


def test_refinement_lowers_the_objective_and_keeps_landmarks_on_their_surfaces(vases):
    meshes, nicp = vases
    result = refine_warps(meshes, nicp.points, nicp.face_index, nicp.barycentric, SETTINGS, nicp.edges,
                          kernels=(4, 8))
    assert len(result.trace) > 1 and np.all(np.diff(result.trace[:, 0]) < 0)  # every recorded E lower
    assert result.points.shape == nicp.points.shape and not np.allclose(result.points, nicp.points)
    for mesh, points, faces, barys in zip(meshes, result.points, result.face_index, result.barycentric):
        surface = TargetSurface(mesh.vertices, mesh.faces)
        assert np.max(surface.closest(points).distance) <= 1e-9 * mesh.bbox_diagonal()
        assert np.allclose(np.einsum("lk,lkd->ld", barys, mesh.vertices[mesh.faces[faces]]), points, atol=1e-12)


def test_identical_shapes_are_left_as_they_are(vases):
    meshes, nicp = vases
    copies = [meshes[0]] * 3
    points = np.repeat(nicp.points[:1], 3, axis=0)
    result = refine_warps(copies, points, np.repeat(nicp.face_index[:1], 3, axis=0),
                          np.repeat(nicp.barycentric[:1], 3, axis=0), SETTINGS, nicp.edges, kernels=(4,))
    assert np.array_equal(result.points, points) and len(result.trace) == 1
