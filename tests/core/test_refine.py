"""Groupwise refinement after NICP: core/correspond/refine.py and objective.py."""

from dataclasses import replace

import numpy as np
import pytest

from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
from shapegen_core.correspond import Correspondence, CorrespondenceSettings, correspond
from shapegen_core.correspond.settings import RefinementSettings
from shapegen_core.correspond.objective import (CompactnessTerm, LandmarkState, PopulationObjective, compactness,
                                                density, spread)
from shapegen_core.correspond.refine import interpolated_normals, landmark_state, refine_population
from shapegen_core.demo_data import make_vases
from shapegen_core.geometry import TargetSurface

SMALL = dict(iterations=15)


@pytest.fixture(scope="module")
def vases():
    shapes = make_vases(6, seed=3, resolution=(24, 32))
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=200, seed=0))
    nicp = correspond(prepared, CorrespondenceSettings(), jobs=1)
    return shapes, prepared, nicp


def true_error(shapes, prepared, corr: Correspondence) -> float:
    """Mean distance (% of the diagonal) of every landmark to the point at its template
    landmark's surface coordinates (bench/correspondence.py's vs-template error)."""
    t = corr.names.index(corr.template_name)
    lm = prepared.landmarks[t]
    st = shapes[t].surface_coordinates(lm.face_index, lm.barycentric)
    return 100 * float(np.mean([
        np.linalg.norm(prepared.shapes[m].transform.to_input(corr.points[m]) - shapes[m].points_at(st), axis=1).mean()
        / shapes[m].mesh.bbox_diagonal() for m in range(len(shapes))]))


def numeric_gradient(function, x, step=1e-6):
    """Central differences of a scalar function of an array."""
    gradient = np.zeros_like(x)
    for index in np.ndindex(x.shape):
        up, down = x.copy(), x.copy()
        up[index] += step
        down[index] -= step
        gradient[index] = (function(up) - function(down)) / (2 * step)
    return gradient


def test_compactness_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(5, 6, 3))
    value, gradient = compactness(points, delta=0.3)
    assert np.allclose(gradient, numeric_gradient(lambda x: compactness(x, 0.3)[0], points), atol=1e-7)
    # the dual value equals ½ log det(I + Σ/δ) of the 3L × 3L covariance
    y = points.reshape(5, -1) - points.reshape(5, -1).mean(axis=0)
    covariance = y.T @ y / 4
    assert value == pytest.approx(0.5 * np.linalg.slogdet(np.eye(18) + covariance / 0.3)[1], rel=1e-10)


def test_spread_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    points = np.c_[rng.uniform(0, 3, size=(40, 2)), np.zeros(40)]
    normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    normals[:5] *= -1  # the other face of a wall: no interaction with the rest
    start = np.log(density(points, normals, 0.5).values)
    moved = points + np.c_[rng.normal(scale=0.2, size=(40, 2)), np.zeros(40)]
    value, gradient = spread(moved, normals, 0.5, start)
    assert value > 0
    numeric = numeric_gradient(lambda x: spread(x, normals, 0.5, start)[0], moved)
    assert np.allclose(gradient, numeric, atol=1e-6)
    assert spread(points, normals, 0.5, start) == (0.0, pytest.approx(np.zeros((40, 3))))


def test_interpolated_normal_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    triangles = rng.normal(size=(6, 3, 3))
    corners = rng.normal(size=(6, 3, 3))
    corners /= np.linalg.norm(corners, axis=2, keepdims=True)
    corners += 2 * np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])[:, None]
    barys = rng.dirichlet([3, 3, 3], size=6)
    points = np.einsum("nk,nkd->nd", barys, triangles)
    normals, jacobians = interpolated_normals(triangles, corners, barys)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0)
    for row in range(6):
        numeric = numeric_gradient_vector(lambda x: interpolated_normals(
            triangles[row:row + 1], corners[row:row + 1], _barycentric(x, triangles[row]))[0][0], points[row])
        assert np.allclose(jacobians[row], numeric, atol=1e-6)


def _barycentric(point, triangle):
    """Barycentrics of the orthogonal projection of `point` onto the triangle's plane."""
    e1, e2 = triangle[1] - triangle[0], triangle[2] - triangle[0]
    gram = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
    v, w = np.linalg.solve(gram, [e1 @ (point - triangle[0]), e2 @ (point - triangle[0])])
    return np.array([[1 - v - w, v, w]])


def numeric_gradient_vector(function, x, step=1e-6):
    """Central-difference Jacobian (out, in) of a vector function of a vector."""
    columns = []
    for index in range(len(x)):
        up, down = x.copy(), x.copy()
        up[index] += step
        down[index] -= step
        columns.append((function(up) - function(down)) / (2 * step))
    return np.stack(columns, axis=1)


def test_population_gradient_matches_finite_differences():
    """The whole objective on landmarks lying on triangles, with every shape's similarity
    removed (fixed scale and rotation, centroid at every evaluation) and the smooth
    normals in the compactness term: the gradient along each landmark's face matches."""
    rng = np.random.default_rng(2)
    n_shapes, n_landmarks = 4, 10
    base = rng.normal(size=(n_landmarks, 3, 3))
    triangles = np.stack([1.5 * base @ np.linalg.qr(rng.normal(size=(3, 3)))[0] + rng.normal(size=3)
                          + 0.05 * rng.normal(size=base.shape) for _ in range(n_shapes)])
    corners = rng.normal(size=triangles.shape)
    corners /= np.linalg.norm(corners, axis=3, keepdims=True)
    face_normals = np.cross(triangles[..., 1, :] - triangles[..., 0, :], triangles[..., 2, :] - triangles[..., 0, :])
    face_normals /= np.linalg.norm(face_normals, axis=2, keepdims=True)
    corners += 2 * face_normals[:, :, None]

    def state(points):
        barys = np.stack([np.concatenate([_barycentric(p, t) for p, t in zip(x, tri)])
                          for x, tri in zip(points, triangles)])
        smooth = [interpolated_normals(tri, c, b) for tri, c, b in zip(triangles, corners, barys)]
        return LandmarkState(points, face_normals, np.stack([n for n, _ in smooth]), np.stack([j for _, j in smooth]))

    start = np.einsum("mlk,mlkd->mld", rng.dirichlet([4, 4, 4], size=(n_shapes, n_landmarks)), triangles)
    objective = PopulationObjective(state(start), [20.0] * n_shapes, 1.0, 2.0, 0.05, 1.0, "similarity", 0.7)
    moved = np.einsum("mlk,mlkd->mld", rng.dirichlet([4, 4, 4], size=(n_shapes, n_landmarks)), triangles)
    value, gradient = objective.evaluate(state(moved))
    assert value.total == pytest.approx(value.compactness + 2.0 * value.spread)
    numeric = numeric_gradient(lambda x: objective.evaluate(state(x))[0].total, moved)
    # the objective only sees moves along each face: compare the tangential parts
    tangential = lambda g: g - np.einsum("mld,mld->ml", g, face_normals)[..., None] * face_normals  # noqa: E731
    assert np.allclose(tangential(gradient), tangential(numeric), atol=1e-6)
    assert np.abs(tangential(gradient)).max() > 1e-3


def test_refinement_stays_on_surfaces_and_descends(vases):
    shapes, prepared, nicp = vases
    refined = correspond(prepared, CorrespondenceSettings(refinement=RefinementSettings(method="population", **SMALL)),
                         jobs=1)
    assert refined.refinement == "population"
    trace = refined.refinement_trace
    assert len(trace) >= 3 and np.all(np.diff(trace[:, 0]) < 0)  # every accepted step lowers E
    assert np.allclose(trace[:, 0], trace[:, 1] + trace[:, 2])
    assert not np.array_equal(refined.points, nicp.points)
    for m, shape in enumerate(prepared.shapes):
        mesh = shape.mesh
        diagonal = mesh.bbox_diagonal()
        corners = mesh.vertices[mesh.faces[refined.face_index[m]]]
        assert np.all(refined.barycentric[m] >= -1e-12)
        assert np.allclose(refined.barycentric[m].sum(axis=1), 1.0)
        on_face = np.einsum("nk,nkd->nd", refined.barycentric[m], corners)
        assert np.abs(on_face - refined.points[m]).max() <= 1e-9 * diagonal
        distance = TargetSurface(mesh.vertices, mesh.faces).closest(refined.points[m]).distance
        assert distance.max() <= 1e-9 * diagonal
        assert np.allclose(refined.points_input[m], shape.transform.to_input(refined.points[m]))


def test_refine_none_is_nicp_exactly(vases):
    shapes, prepared, nicp = vases
    assert CorrespondenceSettings().refinement.method == "none"
    assert nicp.refinement == "none" and nicp.refinement_trace.shape == (0, 3)
    # no refinement step at all: the population run hands NICP's landmarks through untouched
    still = correspond(prepared, CorrespondenceSettings(refinement=RefinementSettings(method="population", iterations=0)), jobs=1)
    for name in ("points", "points_input", "face_index", "barycentric", "template_points", "residuals"):
        assert np.array_equal(getattr(still, name), getattr(nicp, name)), name
    assert still.refinement == "population" and len(still.refinement_trace) == 1


def test_a_given_compactness_term_replaces_the_settings_one(vases):
    """refine_population(compactness=...) (how bench/refine_objectives.py measures candidate
    objectives): the settings' own term given this way changes nothing; a term without
    gradient leaves the spread term alone, which is 0 at the start, so nothing moves."""
    shapes, prepared, nicp = vases
    settings = CorrespondenceSettings(refinement=RefinementSettings(method="population", **SMALL))
    meshes = [s.mesh for s in prepared.shapes]
    start = (nicp.points, nicp.face_index, nicp.barycentric)
    default = refine_population(meshes, *start, settings, edges=nicp.edges)
    same = refine_population(meshes, *start, settings, edges=nicp.edges, compactness=lambda state: CompactnessTerm(
        state, settings.refinement.regulariser, settings.refinement.alignment, settings.refinement.normals))
    assert len(default.trace) > 2
    assert np.array_equal(same.points, default.points) and np.array_equal(same.trace, default.trace)

    class Flat(CompactnessTerm):
        def evaluate(self, state):
            return 1.0, np.zeros_like(state.points)

    flat = refine_population(meshes, *start, settings, edges=nicp.edges,
                             compactness=lambda state: Flat(state, 0.001, "similarity"))
    assert np.array_equal(flat.points, nicp.points) and flat.trace.tolist() == [[1.0, 1.0, 0.0]]


def test_identical_shapes_are_left_alone(vases):
    """Identical shapes with identical landmarks: the population has no variance and no
    landmark is crowded, so the gradient is zero and nothing moves."""
    shapes, prepared, nicp = vases
    mesh = prepared.shapes[0].mesh
    copies = 4
    stack = lambda a: np.repeat(a[None], copies, axis=0)  # noqa: E731
    result = refine_population([mesh] * copies, stack(nicp.points[0]), stack(nicp.face_index[0]),
                               stack(nicp.barycentric[0]), CorrespondenceSettings(refinement=RefinementSettings(method="population")))
    assert np.array_equal(result.points, stack(nicp.points[0]))
    assert np.array_equal(result.face_index, stack(nicp.face_index[0]))
    assert len(result.trace) == 1 and result.trace[0, 0] == 0.0


def test_spread_term_alone_keeps_a_uniform_sampling_uniform(vases):
    """Spread only: Prepare's near-uniform landmarks stay where they are; a landmark pushed
    onto its neighbour is pushed back out, the rest stay spread."""
    shapes, prepared, nicp = vases
    settings = CorrespondenceSettings(refinement=RefinementSettings(method="population", compactness=0.0, iterations=30))
    meshes = [s.mesh for s in prepared.shapes[:3]]
    count = min(len(l) for l in prepared.landmarks[:3])  # Prepare's counts differ by a few
    lms = prepared.landmarks[:3]
    points = np.stack([l.points[:count] for l in lms])
    faces, barys = np.stack([l.face_index[:count] for l in lms]), np.stack([l.barycentric[:count] for l in lms])
    uniform = refine_population(meshes, points, faces, barys, settings)
    assert np.array_equal(uniform.points, points)

    # a landmark moved next to its nearest neighbour: the spread term (anchored at the
    # uniform start) is positive and its descent direction moves it away from the neighbour
    objective = PopulationObjective(landmark_state(meshes, points, faces, barys), [m.area() for m in meshes], 0.0,
                                    1.0, 0.001, 1.0, "similarity")
    crowded = points.copy()
    for m in range(3):
        j = int(np.argsort(np.linalg.norm(points[m] - points[m, 0], axis=1))[1])
        crowded[m, 0] = 0.8 * points[m, j] + 0.2 * points[m, 0]
    crowded_state = lambda p: replace(landmark_state(meshes, points, faces, barys), points=p)  # noqa: E731
    value, gradient = objective.evaluate(crowded_state(crowded))
    assert value.spread > 0
    for m in range(3):
        j = int(np.argsort(np.linalg.norm(points[m] - points[m, 0], axis=1))[1])
        apart = crowded[m, 0] - crowded[m, j]
        step = -gradient[m, 0] / np.linalg.norm(gradient[m, 0]) * 0.2 * np.linalg.norm(apart)
        relieved = crowded.copy()
        relieved[m, 0] += step
        assert np.linalg.norm(relieved[m, 0] - crowded[m, j]) > np.linalg.norm(apart)
        assert objective.evaluate(crowded_state(relieved))[0].spread < value.spread



def test_correspondence_file_records_the_refinement(vases, tmp_path):
    shapes, prepared, nicp = vases
    refined = correspond(prepared, CorrespondenceSettings(refinement=RefinementSettings(method="population", iterations=3)), jobs=1)
    loaded = Correspondence.load(refined.save(tmp_path / "refined.npz"))
    assert loaded.refinement == "population" and loaded.settings.refinement.method == "population"
    assert np.array_equal(loaded.refinement_trace, refined.refinement_trace)
    assert np.array_equal(loaded.points, refined.points)
    # a file written before refinement existed (no refinement arrays) loads as "none"
    from shapegen_core.correspond import CORRESPONDENCE_FORMAT, CORRESPONDENCE_VERSION
    from shapegen_core.base.npzfile import save_npz
    arrays = nicp.to_arrays()
    del arrays["refinement"], arrays["refinement_trace"]
    old = Correspondence.load(save_npz(tmp_path / "old.npz", CORRESPONDENCE_FORMAT, CORRESPONDENCE_VERSION, arrays))
    assert old.refinement == "none" and old.refinement_trace.shape == (0, 3)
    arrays["refinement"] = np.asarray("sideways")
    arrays["refinement_trace"] = np.zeros((0, 3))
    from shapegen_core.base.errors import ModelFileError
    with pytest.raises(ModelFileError, match="unknown refinement 'sideways'"):
        Correspondence.load(save_npz(tmp_path / "bad.npz", CORRESPONDENCE_FORMAT, CORRESPONDENCE_VERSION, arrays))


def test_command_line_refine_option():
    from shapegen_core.app.cli import build_parser
    from shapegen_core.app.cli_common import settings_from_args

    for command in (["correspond", "x", "-o", "y"], ["fit", "x", "-o", "y"], ["evaluate", "x", "-o", "y"]):
        args = build_parser().parse_args(command + ["--refine", "population"])
        assert settings_from_args(CorrespondenceSettings, args).refinement.method == "population"
        args = build_parser().parse_args(command)
        assert settings_from_args(CorrespondenceSettings, args) == CorrespondenceSettings()
    with pytest.raises(SystemExit):
        build_parser().parse_args(["correspond", "x", "-o", "y", "--refine", "sideways"])


def test_progress_cancel_and_worker_processes(vases):
    """Refinement reports progress after NICP's share and can be cancelled; its per-shape
    work in two worker processes gives the same landmarks as in this process."""
    from shapegen_core.base.errors import Cancelled

    shapes, prepared, nicp = vases
    seen = []
    settings = CorrespondenceSettings(refinement=RefinementSettings(method="population", iterations=4))
    result = correspond(prepared, settings, jobs=1, progress=lambda f, m: seen.append((f, m)))
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert any(m.startswith("refining") and f > 0.8 for f, m in seen)
    meshes = [s.mesh for s in prepared.shapes]
    with pytest.raises(Cancelled):
        refine_population(meshes, nicp.points, nicp.face_index, nicp.barycentric, settings, should_cancel=lambda: True)
    apart = refine_population(meshes, nicp.points, nicp.face_index, nicp.barycentric, settings, edges=nicp.edges,
                              jobs=2)
    assert np.array_equal(apart.points, result.points) and np.array_equal(apart.trace, result.refinement_trace)
