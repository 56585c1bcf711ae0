"""The intrinsic start of correspondence: the Laplace–Beltrami spectrum against
closed forms, the spectral map on known answers, the option's wiring and its file record."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
import trimesh

from conftest import tosca_class
from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
from shapegen_core.correspond import CorrespondenceSettings, correspond
from shapegen_core.correspond.settings import DataTermSettings, IterationSettings, StiffnessSettings
from shapegen_core.correspond.functional_map import spectral_shape, spectral_start
from shapegen_core.correspond.start import _start_on_shape, _StartItem
from shapegen_core.geometry.spectral import SpectrumError, cotangent_laplacian, laplace_beltrami_spectrum
from shapegen_core.base.settings import SettingsError



def _rotation(seed: int) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_sphere_eigenvalues_are_l_l_plus_1_over_r_squared_with_multiplicity_2l_plus_1():
    sphere = trimesh.creation.icosphere(3)  # 642 vertices
    spectrum = laplace_beltrami_spectrum(sphere.vertices * 3.0, sphere.faces, 16)
    # the spectrum is of the unit-area shape: r² = 1 / 4π
    expected = np.concatenate([np.full(2 * l + 1, 4 * np.pi * l * (l + 1)) for l in range(4)])
    assert spectrum.values[0] == pytest.approx(0.0, abs=1e-8)
    np.testing.assert_allclose(spectrum.values[1:], expected[1:], rtol=0.02)
    mass = spectrum.mass
    np.testing.assert_allclose(spectrum.vectors.T @ (mass[:, None] * spectrum.vectors), np.eye(16), atol=1e-8)


def _grid(nx: int, ny: int, width: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.linspace(0, width, nx), np.linspace(0, height, ny), indexing="ij")
    vertices = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    index = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    return vertices, np.r_[np.c_[a, b, c], np.c_[a, c, d]]


def test_flat_rectangle_eigenvalues_are_the_neumann_closed_form():
    vertices, faces = _grid(61, 16, 2.0, 0.5)  # unit area: the spectrum is as computed
    spectrum = laplace_beltrami_spectrum(vertices, faces, 8)
    expected = sorted(np.pi**2 * (m**2 / 4.0 + n**2 / 0.25) for m in range(8) for n in range(3))[:8]
    np.testing.assert_allclose(spectrum.values[1:], expected[1:], rtol=0.02)
    stiffness, _ = cotangent_laplacian(vertices, faces)
    np.testing.assert_allclose(np.asarray(stiffness.sum(axis=1)).ravel(), 0.0, atol=1e-9)  # constants in the kernel


def test_degenerate_faces_add_nothing_and_several_parts_are_reported():
    vertices, faces = _grid(6, 6, 1.0, 1.0)
    pinched = np.r_[faces, [[0, 1, 1]], [[0, 6, 12]]]  # a repeated corner; a sliver on collinear points
    stiffness, mass = cotangent_laplacian(vertices, pinched)
    reference, reference_mass = cotangent_laplacian(vertices, faces)
    assert np.isfinite(stiffness.data).all()
    np.testing.assert_allclose(stiffness.toarray(), reference.toarray(), atol=1e-12)
    np.testing.assert_allclose(mass, reference_mass)
    sphere = trimesh.creation.icosphere(2)
    two = np.r_[sphere.vertices, sphere.vertices * 0.5 + 3.0]
    spectrum = laplace_beltrami_spectrum(two, np.r_[sphere.faces, sphere.faces + len(sphere.vertices)], 6)
    assert spectrum.parts == 2 and spectrum.largest_part_share == pytest.approx(0.8, abs=0.01)
    with pytest.raises(SpectrumError, match="largest of 2 parts holds 80 %"):
        spectral_shape(two, np.r_[sphere.faces, sphere.faces + len(sphere.vertices)])


def _bumpy_sphere(mirror_symmetric: bool) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere with low-frequency bumps: no symmetry at all, or only x → −x."""
    sphere = trimesh.creation.icosphere(3)
    x, y, z = sphere.vertices.T
    lateral = x**2 if mirror_symmetric else x
    radius = 1.0 + 0.35 * y + 0.2 * z**2 + 0.25 * y * z + 0.3 * lateral * (1 + y)
    return sphere.vertices * radius[:, None] * np.array([1.0, 1.6, 0.8]), np.asarray(sphere.faces)


def _moved_shuffled_copy(vertices, faces, seed: int):
    """(vertices, faces, order): the mesh rigidly moved, its vertices and faces reordered;
    copy vertex i is original vertex order[i]."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(vertices))
    moved = vertices[order] @ _rotation(seed).T + rng.normal(size=3) * 5
    return moved, np.argsort(order)[faces][rng.permutation(len(faces))], order


def test_a_shape_maps_to_a_moved_shuffled_copy_of_itself():
    vertices, faces = _bumpy_sphere(mirror_symmetric=False)
    copy, copy_faces, order = _moved_shuffled_copy(vertices, faces, seed=3)
    start = spectral_start(spectral_shape(vertices, faces), vertices, spectral_shape(copy, copy_faces))
    truth = copy[np.argsort(order)]  # where every original vertex went
    exact = np.linalg.norm(start.points - truth, axis=1) < 1e-9
    assert exact.mean() >= 0.95, start.message


@pytest.mark.parametrize("seed", [4, 6])
def test_a_bilaterally_symmetric_shape_is_not_mirrored(seed):
    """The map and its mirror fit the signatures alike (a coin toss between them: without
    the orientation test these motions come out mirrored); the orientation decides."""
    vertices, faces = _bumpy_sphere(mirror_symmetric=True)
    copy, copy_faces, order = _moved_shuffled_copy(vertices, faces, seed)
    start = spectral_start(spectral_shape(vertices, faces), vertices, spectral_shape(copy, copy_faces))
    truth = copy[np.argsort(order)]
    twin = np.argmin(np.linalg.norm(vertices[:, None] * np.array([-1, 1, 1]) - vertices[None], axis=2), axis=1)
    error = np.linalg.norm(start.points - truth, axis=1).mean()
    assert error < 0.25 * np.linalg.norm(start.points - truth[twin], axis=1).mean()
    assert start.orientation > 0.6


def test_a_shape_in_two_parts_falls_back_and_says_why():
    vertices, faces = _bumpy_sphere(mirror_symmetric=False)
    template = spectral_shape(vertices, faces)
    two = np.r_[vertices, vertices + 10.0]
    start = _start_on_shape(_StartItem("pair", template, vertices[:5], two, np.r_[faces, faces + len(vertices)]))
    assert start.points is None
    assert start.message.startswith("closest-point start: spectrum not trusted (its largest of 2 parts holds 50 %")


@pytest.mark.quality
def test_a_tosca_cat_in_another_pose_starts_closer_to_the_truth_than_closest_points():
    """cat0 → cat1 (a cat that moved its limbs): the closest-point start (the files share
    z up and the facing) puts the landmarks far from their true places, the spectral start
    near them."""
    from shapegen_core.geometry import TargetSurface
    from shapegen_core.meshes.reading import read_mesh

    cats = tosca_class("cat")
    meshes = [read_mesh(cats / f"{name}.off") for name in ("cat0", "cat1")]
    maps = [np.loadtxt(cats / "corres" / f"{name}.vts", dtype=np.int64) - 1 for name in ("cat0", "cat1")]
    common = np.arange(0, 5000, 25)  # 200 ground-truth points
    landmarks, truth = meshes[0].vertices[maps[0][common]], meshes[1].vertices[maps[1][common]]
    diagonal = meshes[1].bbox_diagonal()
    start = spectral_start(spectral_shape(meshes[0].vertices, meshes[0].faces), landmarks,
                           spectral_shape(meshes[1].vertices, meshes[1].faces))
    spectral_error = np.linalg.norm(start.points - truth, axis=1).mean() / diagonal
    closest = TargetSurface(meshes[1].vertices, meshes[1].faces).closest(landmarks).points
    closest_error = np.linalg.norm(closest - truth, axis=1).mean() / diagonal
    assert spectral_error < 0.05 and spectral_error < 0.3 * closest_error, (spectral_error, closest_error)


def test_initialisation_is_a_checked_recorded_setting_auto_by_default_and_old_files_read_closest():
    assert CorrespondenceSettings().data_term.initialisation == "auto"
    settings = CorrespondenceSettings(data_term=DataTermSettings(initialisation="spectral"))
    assert CorrespondenceSettings.from_json(settings.to_json()) == settings
    recorded = json.loads(settings.to_json())
    del recorded["data_term"]["initialisation"]  # a file written before the option existed
    assert CorrespondenceSettings.from_dict(recorded, recorded=True).data_term.initialisation == "closest"
    assert CorrespondenceSettings.from_dict(recorded).data_term.initialisation == "auto"  # options asked for now
    with pytest.raises(SettingsError, match="unknown initialisation 'intrinsic'; choose from auto, closest, spectral"):
        DataTermSettings(initialisation="intrinsic")


def _short_correspondence(small_vases, initialisation: str):
    """Three small vases corresponded briefly with the given start: (result, progress messages)."""
    prepared = prepare_meshes([s.mesh for s in small_vases[:3]], PrepareSettings(n_landmarks=40, seed=1))
    messages = []
    settings = CorrespondenceSettings(stiffness=StiffnessSettings(alpha_steps=2),
                                      data_term=DataTermSettings(initialisation=initialisation),
                                      iterations=IterationSettings(max_iterations=4))
    result = correspond(prepared, settings, jobs=1, progress=lambda fraction, message: messages.append(message))
    return result, messages


def test_correspond_with_the_spectral_start_reports_every_shape_s_start(small_vases):
    result, messages = _short_correspondence(small_vases, "spectral")
    others = [n for n in result.names if n != result.template_name]
    for name in others:
        said = [m for m in messages if m.startswith(f"{name}: spectral start") or m.startswith(f"{name}: closest")]
        assert said, f"{name}: no start reported in {messages}"
    assert result.settings.data_term.initialisation == "spectral"
    assert np.isfinite(result.points).all()


def _evidence_of(meshes, landmarks: int = 300):
    """The automatic start's choice for `meshes`, prepared as correspondence sees them."""
    from shapegen_core.correspond.groupwise import chamfer_medoid
    from shapegen_core.correspond.start import chosen_start, pose_evidence

    prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=landmarks, seed=0))
    sets = [l.points for l in prepared.landmarks]
    return chosen_start(pose_evidence([s.mesh for s in prepared.shapes], sets, chamfer_medoid(sets)))


@pytest.mark.quality
def test_auto_takes_the_intrinsic_start_for_an_animal_in_different_poses():
    from shapegen_core.meshes.reading import read_mesh

    choice, why = _evidence_of([read_mesh(tosca_class("cat") / f"cat{i}.off") for i in range(4)])
    assert choice == "spectral", why


def test_auto_takes_closest_points_for_vases_that_differ_in_proportion():
    from shapegen_core.demo_data import make_vases

    choice, why = _evidence_of([s.mesh for s in make_vases(5, seed=11, resolution=(30, 60))])
    assert choice == "closest", why


def test_auto_says_its_choice_for_every_shape_and_the_file_records_it(small_vases, tmp_path):
    from shapegen_core.correspond import Correspondence

    result, messages = _short_correspondence(small_vases, "auto")
    assert result.diagnostics.start in ("closest", "spectral") and result.diagnostics.start_reason
    assert result.start_summary() == f"{result.diagnostics.start} start ({result.diagnostics.start_reason})"
    for name in (n for n in result.names if n != result.template_name):
        assert any(m.startswith(f"{name}: ") and "start" in m and result.diagnostics.start_reason in m for m in messages), messages
    loaded = Correspondence.load(result.save(tmp_path / "auto.npz"))
    assert (loaded.diagnostics.start, loaded.diagnostics.start_reason, loaded.settings.data_term.initialisation) == \
        (result.diagnostics.start, result.diagnostics.start_reason, "auto")
    # a file written before the record and the option: the start its settings name, closest
    arrays = {k: v for k, v in result.to_arrays().items() if k not in ("start", "start_reason")}
    recorded = json.loads(result.settings.to_json())
    del recorded["data_term"]["initialisation"]
    old = Correspondence.from_arrays({**arrays, "settings": np.asarray(json.dumps(recorded))})
    assert old.diagnostics.start == "" and old.start_used == "closest" and old.start_summary() == ""


def test_auto_s_intrinsic_choice_is_said_on_every_shape_s_line(small_vases, monkeypatch):
    """Where the collection takes the intrinsic start, each shape's line names its start
    (or why it fell back) and why the collection took it."""
    from shapegen_core.correspond import starting

    monkeypatch.setattr(starting, "chosen_start", lambda evidence: ("spectral", "as the evidence said"))
    result, messages = _short_correspondence(small_vases, "auto")
    assert result.diagnostics.start == "spectral" and result.start_summary() == "spectral start (as the evidence said)"
    for name in (n for n in result.names if n != result.template_name):
        said = [m for m in messages if m.startswith(f"{name}: ") and m.endswith("chosen for the collection: as the "
                                                                                 "evidence said")]
        assert len(said) == 1 and "start" in said[0], messages


@dataclass(frozen=True)
class _Task:
    """What `checked_spectral_fits` reads of a registration task."""

    index: int
    name: str


class _Runner:
    """Hands back prepared registrations in task order (what `runner.run` returns)."""

    def __init__(self, by_name):
        self.by_name = by_name

    def run(self, tasks, progress, label):
        return [self.by_name[task.name] for task in tasks]


def test_a_spectral_fit_worse_or_no_closer_to_the_signatures_falls_back_to_closest_points():
    from types import SimpleNamespace

    from shapegen_core.correspond.start import checked_spectral_fits

    names = ["kept", "worse fit", "same signatures", "template"]
    closest = [_Task(i, n) for i, n in enumerate(names)]
    spectral = [_Task(i, n) for i, n in enumerate(names[:3])] + [closest[3]]  # the template: no spectral start
    fits = {"kept": 1.0, "worse fit": 2.0, "same signatures": 1.0, "template": 1.0}
    registrations = {n: SimpleNamespace(residual=fits[n], by="spectral") for n in names}
    registrations.update({f"{n} (closest-point start)": SimpleNamespace(residual=1.0, by="closest") for n in names})
    signature = {("kept", "spectral"): 1.0, ("kept", "closest"): 2.0, ("same signatures", "spectral"): 0.95,
                 ("same signatures", "closest"): 1.0}
    chosen, reasons = checked_spectral_fits(spectral, closest, _Runner(registrations), lambda *a: None, "round 1",
                                            lambda i, r: signature.get((names[i], r.by), 1.0))
    assert [r.by for r in chosen] == ["spectral", "closest", "closest", "spectral"]
    assert reasons[0] == "" and reasons[3] == ""
    assert reasons[1] == "closest-point start: the spectral start fit 2.0× worse"
    assert reasons[2].startswith("closest-point start: the spectral start does not match the intrinsic geometry "
                                 "clearly better (signature error 0.95 against 1.00)")

