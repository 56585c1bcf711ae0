"""The quality gate: flipped triangles, edge distortion, self-intersections and
extent of generated meshes against their template and the training shapes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from shapegen_core.demo_data import make_vases
from shapegen_core.geometry.intersections import _segments_cross, candidate_pairs, intersecting_pairs
from shapegen_core.meshes.mesh import Mesh
from shapegen_core.generate.quality import QualityGate, QualitySettings, training_extents


@pytest.fixture(scope="module")
def vases():
    return [s.mesh for s in make_vases(4, seed=2, resolution=(14, 20), pose=False)]


@pytest.fixture(scope="module")
def gate(vases):
    return QualityGate(vases, training_extents(vases))


def brute_force_pairs(vertices: np.ndarray, faces: np.ndarray) -> set:
    """Every crossing pair by testing all pairs (no broad phase)."""
    tri = vertices[faces]
    i, j = np.triu_indices(len(faces), 1)
    shares = (faces[i][:, :, None] == faces[j][:, None, :]).any(axis=(1, 2))
    i, j = i[~shares], j[~shares]
    hit = np.zeros(len(i), dtype=bool)
    for one, other in ((tri[i], tri[j]), (tri[j], tri[i])):
        for k in range(3):
            hit |= _segments_cross(one[:, k], one[:, (k + 1) % 3], other)
    return set(zip(i[hit].tolist(), j[hit].tolist()))


def test_two_crossing_triangles_are_one_pair_and_neighbours_none():
    vertices = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0],  # in z = 0
                         [0.5, 0.5, -1], [0.5, 0.5, 1], [1.5, 1.5, 0.5],  # pierces the first
                         [3, 3, 1], [4, 3, 1], [3, 4, 1]], dtype=float)  # far away
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [1, 7, 8]])  # face 3 shares corners with 0 and 2
    assert intersecting_pairs(vertices, faces).tolist() == [[0, 1]]


def test_broad_phase_finds_every_crossing_of_a_triangle_soup():
    rng = np.random.default_rng(4)
    centres = rng.uniform(0, 3, size=(150, 1, 3))
    sizes = rng.choice([0.05, 0.3, 1.2], size=(150, 1, 1))  # small, middle and a few large ones
    vertices = (centres + sizes * rng.normal(size=(150, 3, 3))).reshape(-1, 3)
    faces = np.arange(450).reshape(-1, 3)
    found = {tuple(p) for p in intersecting_pairs(vertices, faces).tolist()}
    assert found == brute_force_pairs(vertices, faces)
    assert len(found) > 20
    assert len(candidate_pairs(vertices[faces])) < 150 * 149 // 2


def test_the_template_passes(vases, gate):
    for index, mesh in enumerate(vases):
        quality = gate.check(mesh, index)
        assert quality.ok, quality.summary()
        assert quality.flipped == 0 and quality.self_intersections == 0 and quality.edge_stretch < 1e-9


def test_an_exploded_mesh_fails_on_extent(vases, gate):
    """A broken mug sample: a flat disc five times the class's size."""
    exploded = vases[0].vertices * np.array([5.0, 5.0, 0.05])
    quality = gate.check(exploded, 0)
    assert not quality.ok
    assert any(reason.startswith("extent:") for reason in quality.reasons), quality.reasons
    assert quality.extent_ratio > 4


def test_flipped_triangles_are_counted(vases, gate):
    mesh = vases[1]
    vertices = mesh.vertices.copy()
    # slide one vertex of the side along the surface past its neighbour: part of its fan turns over
    side = np.flatnonzero(np.abs(mesh.vertex_normals()[:, 2]) < 0.3)[10]
    edges = mesh.edges_unique()
    neighbour = edges[edges[:, 0] == side, 1][0]
    vertices[side] = vertices[neighbour] + 0.8 * (vertices[neighbour] - vertices[side])
    quality = gate.check(mesh.with_vertices(vertices), 1)
    assert quality.flipped >= 2
    assert any(reason.startswith("flipped:") for reason in quality.reasons)
    assert QualityGate(vases, training_extents(vases), QualitySettings(max_flipped=1000)).check(
        vertices, 1).flipped == quality.flipped


def test_a_self_intersecting_mesh_fails(vases, gate):
    mesh = vases[2]
    vertices = mesh.vertices.copy()
    centre = vertices.mean(axis=0)
    # a band of the side pushed through the axis to the far wall: the surface crosses itself
    radial = vertices[:, :2] - centre[:2]
    height = vertices[:, 2]
    band = (np.abs(height - np.median(height)) < 0.1 * np.ptp(height)) & (radial[:, 0] > 0)
    vertices[band, 0] -= 1.6 * np.abs(radial[band, 0]).max()
    quality = gate.check(vertices, 2)
    assert quality.self_intersections > 0
    assert any(reason.startswith("self-intersections:") for reason in quality.reasons)


def test_edge_stretch_ignores_overall_scale_and_catches_a_stretched_region(vases, gate):
    mesh = vases[3]
    assert gate.check(mesh.vertices * 1.2, 3).edge_stretch < 1e-9
    vertices = mesh.vertices.copy()
    top = vertices[:, 2] > np.percentile(vertices[:, 2], 80)
    vertices[top, 2] += 8.0 * (vertices[top, 2] - np.percentile(vertices[:, 2], 80))
    quality = gate.check(vertices, 3)
    assert any(reason.startswith("edge stretch:") for reason in quality.reasons), quality.reasons


def two_parts(shift: float) -> Mesh:
    """A box with a smaller box (the 'handle') pushed `shift` into it along x."""
    body = trimesh.creation.box(extents=(2, 2, 2))
    handle = trimesh.creation.box(extents=(1, 0.5, 0.5))
    handle.apply_translation((1.5 - shift, 0, 0))
    return Mesh(np.vstack([body.vertices, handle.vertices]),
                np.vstack([body.faces, handle.faces + len(body.vertices)]))


def test_crossings_between_parts_that_cross_in_the_template_do_not_count():
    template = two_parts(0.6)  # the handle's end inside the body: crossings in the template
    gate = QualityGate([template], training_extents([template, two_parts(0.2)]),
                       QualitySettings(max_edge_stretch=10, max_edge_stretch_p99=10))
    assert len(intersecting_pairs(template.vertices, template.faces)) > 0
    assert gate.check(template, 0).ok
    moved = two_parts(0.8).vertices  # the crossing slides along the parts
    assert gate.check(moved, 0).self_intersections == 0
    apart = QualityGate([two_parts(-0.2)], training_extents([two_parts(-0.2), two_parts(0.2)]),
                        QualitySettings(max_edge_stretch=10, max_edge_stretch_p99=10))
    assert apart.check(two_parts(-0.2), 0).ok
    pushed = apart.check(two_parts(0.4).vertices, 0)  # parts that did not cross now do
    assert pushed.self_intersections > 0 and not pushed.ok


def test_wrong_vertex_count_is_refused(gate):
    with pytest.raises(Exception, match="vertices"):
        gate.check(np.zeros((5, 3)), 0)


def test_settings_are_checked():
    with pytest.raises(Exception, match="max_edge_stretch"):
        QualitySettings(max_edge_stretch=0.0)
    assert QualitySettings.from_json(QualitySettings(max_redraws=3).to_json()).max_redraws == 3


# ---------------------------------------------------------------------------- renders like its template
def test_a_crumpled_mesh_fails_on_roughness(vases, gate):
    mesh = vases[1]
    assert gate.check(mesh, 1).roughness_ratio == pytest.approx(1.0)
    bumps = np.random.default_rng(0).normal(0.0, 0.15 * mesh.mean_edge_length(), mesh.n_vertices)
    quality = gate.check(mesh.vertices + bumps[:, None] * mesh.vertex_normals(), 1)
    assert quality.roughness_ratio > QualitySettings().max_roughness_ratio
    assert any(reason.startswith("roughness:") for reason in quality.reasons), quality.reasons


def test_roughness_is_the_mean_angle_between_adjacent_normals():
    """Two triangles folded by a known angle: the one adjacent pair's angle."""
    from shapegen_core.generate.quality import roughness

    angle = 0.7
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -np.cos(angle), np.sin(angle)]])
    faces = np.array([[0, 1, 2], [1, 0, 3]])
    assert roughness(vertices, faces, np.array([0]), np.array([1])) == pytest.approx(angle)


def test_a_z_fighting_mesh_fails_on_coincident_faces():
    """A second box moved onto the first: every face of one lies on a face of the other."""
    box = trimesh.creation.box(extents=(1, 1, 1))

    def boxes(gap: float) -> Mesh:
        return Mesh(np.vstack([box.vertices, box.vertices + [gap, 0, 0]]),
                    np.vstack([box.faces, box.faces + len(box.vertices)]))

    template = boxes(2.0)
    gate = QualityGate([template], training_extents([template, boxes(0.0)]))
    assert gate.check(template, 0).coincident_faces == 0 and gate.check(template, 0).ok
    quality = gate.check(boxes(0.0).vertices, 0)
    assert quality.coincident_faces == len(box.faces)
    assert any(reason.startswith("coincident:") for reason in quality.reasons), quality.reasons
