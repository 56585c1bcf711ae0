"""Orientation from the correspondence (core/correspond/posing.py): a shape registered from
the intrinsic start gets its pose in the model frame from its landmarks; Keep Pose shapes
and closest-point starts do not; the poses are recorded in the correspondence and model
files and compose with Prepare's transforms back to the inputs."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from shapegen_core.preprocess.collection import (PREPARED_FORMAT, PREPARED_VERSION, PreparedCollection, PrepareSettings,
                                                 prepare_meshes)
from shapegen_core.correspond import Correspondence, CorrespondenceSettings, correspond
from shapegen_core.correspond.posing import apply_pose, landmark_poses, pose_angle, rigid_fit
from shapegen_core.correspond.settings import DataTermSettings, IterationSettings, StiffnessSettings
from shapegen_core.meshes.mesh import Mesh
from shapegen_core.base.npzfile import save_npz
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.app.pipeline import fit_meshes
from shapegen_core.preprocess import ShapeTransform
from shapegen_core.app.stages import same_shapes

#: the copy Prepare leaves lying: a quarter turn about x (its long z axis ends along −y)
QUARTER_TURN = Rotation.from_euler("x", 90, degrees=True).as_matrix()
TURNED = "blob3"


def _blob(k: int) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere with low-frequency bumps, long along z, without symmetry (the spectral
    map onto it is unique); `k` varies the bumps a little, as shapes of one class vary."""
    sphere = trimesh.creation.icosphere(3)
    x, y, z = sphere.vertices.T
    radius = 1.0 + (0.3 + 0.04 * k) * y + 0.2 * z**2 + (0.25 - 0.03 * k) * y * z + 0.3 * x * (1 + y)
    return sphere.vertices * radius[:, None] * np.array([0.8, 1.0, 1.6]), np.asarray(sphere.faces)


@pytest.fixture(scope="module")
def blobs() -> list[Mesh]:
    """Four blobs standing on their long axis, the last given lying (a quarter turn about x)."""
    meshes = []
    for k in range(4):
        vertices, faces = _blob(k)
        if k == 3:
            vertices = vertices @ QUARTER_TURN.T
        meshes.append(Mesh(vertices, faces, name=f"blob{k}"))
    return meshes


def _prepared(blobs, keep_pose=None) -> PreparedCollection:
    """Prepared without turns (align "none"): the lying blob stays lying, as Prepare leaves
    a shape it only flags."""
    return prepare_meshes(blobs, PrepareSettings(n_landmarks=60, seed=0, align="none"), keep_pose=keep_pose)


def _settings(initialisation: str) -> CorrespondenceSettings:
    return CorrespondenceSettings(stiffness=StiffnessSettings(alpha_steps=2),
                                  data_term=DataTermSettings(initialisation=initialisation),
                                  iterations=IterationSettings(max_iterations=4))


@pytest.fixture(scope="module")
def prepared(blobs) -> PreparedCollection:
    return _prepared(blobs)


@pytest.fixture(scope="module")
def spectral(prepared):
    messages = []
    result = correspond(prepared, _settings("spectral"), template="blob1", jobs=1,
                        progress=lambda fraction, message: messages.append(message))
    return result, messages


def _turn_from_template(points: np.ndarray, template: np.ndarray) -> float:
    """Degrees by which a landmark set lies turned from the template's (its rigid fit)."""
    return pose_angle(rigid_fit(points, template)[0])


def test_rigid_fit_recovers_a_motion_and_the_mirror_fit_a_reflection():
    rng = np.random.default_rng(0)
    reference = rng.normal(size=(50, 3)) * [1.0, 2.0, 5.0]
    points = reference @ QUARTER_TURN.T + [1.0, 2.0, 3.0]
    motion, residual = rigid_fit(points, reference)
    assert residual < 1e-12 and pose_angle(motion) == pytest.approx(90.0)
    np.testing.assert_allclose(apply_pose(motion, points), reference, atol=1e-12)
    mirrored = reference * [-1.0, 1.0, 1.0]
    proper, proper_residual = rigid_fit(mirrored, reference)
    reflection, mirror_residual = rigid_fit(mirrored, reference, proper=False)
    assert np.linalg.det(proper[:3, :3]) == pytest.approx(1.0)
    assert np.linalg.det(reflection[:3, :3]) == pytest.approx(-1.0)
    assert mirror_residual < 1e-12 < proper_residual


def test_poses_only_intrinsic_starts_never_kept_ones():
    rng = np.random.default_rng(1)
    template = rng.normal(size=(40, 3)) * [1.0, 2.0, 5.0]
    lying = template @ QUARTER_TURN.T + [0.5, 0.0, -2.0]
    points = np.stack([template, lying, lying, lying])
    poses, notes = landmark_poses(points, 0, ["template", "spectral", "closest", "spectral"],
                                  [False, False, False, True])
    assert pose_angle(poses[1]) == pytest.approx(90.0)
    assert notes[1] == "posed by its landmarks: turned 90° onto the template"
    np.testing.assert_allclose(apply_pose(poses[1], lying), template, atol=1e-9)
    for index in (0, 2, 3):  # the template, a closest-point start, a kept pose
        assert np.array_equal(poses[index], np.eye(4))
    assert notes[0] == notes[2] == ""
    assert notes[3].startswith("pose kept by request (Keep Pose)")


def test_a_shape_left_lying_enters_the_model_upright_with_the_intrinsic_start(spectral, prepared):
    result, messages = spectral
    turned, template = result.names.index(TURNED), result.names.index(result.template_name)
    starts = result.diagnostics.shape_starts
    assert starts[turned] == "spectral" and starts[template] == "template"
    # as corresponded (the prepared frame) it lies a quarter turn from the template; in the model frame it stands
    assert _turn_from_template(result.points[turned], result.points[template]) > 80
    model_points = result.model_points()
    assert _turn_from_template(model_points[turned], model_points[template]) < 1.0
    angle = pose_angle(result.poses[turned])
    assert 80 < angle < 100
    assert result.diagnostics.pose_notes[turned] == f"posed by its landmarks: turned {angle:.0f}° onto the template"
    assert f"{TURNED}: {result.diagnostics.pose_notes[turned]}" in messages
    np.testing.assert_array_equal(result.landmark_matrix(), model_points.reshape(len(result), -1))
    # the standing shapes hardly turn; the template is the reference
    assert np.array_equal(result.poses[template], np.eye(4))
    for index in range(len(result)):
        if index not in (turned, template):
            assert pose_angle(result.poses[index]) < 10
    # Prepare's frame is kept where the correspondence was made: the points still lie on the prepared meshes
    for index, shape in enumerate(prepared.shapes):
        on_mesh = np.einsum("lk,lkd->ld", result.barycentric[index],
                            shape.mesh.vertices[shape.mesh.faces[result.face_index[index]]])
        np.testing.assert_allclose(on_mesh, result.points[index], atol=1e-9)
    # and the model frame maps back to the inputs: the pose after Prepare's transform
    for index in range(len(result)):
        to_model = ShapeTransform.from_matrix(result.model_transforms()[index])
        np.testing.assert_allclose(to_model.to_input(model_points[index]), result.points_input[index], atol=1e-9)


def test_a_shape_marked_keep_pose_keeps_its_pose(blobs):
    result = correspond(_prepared(blobs, keep_pose=[TURNED]), _settings("spectral"), template="blob1", jobs=1)
    turned = result.names.index(TURNED)
    assert result.diagnostics.shape_starts[turned] == "spectral"
    assert np.array_equal(result.poses[turned], np.eye(4))
    assert result.diagnostics.pose_notes[turned].startswith("pose kept by request (Keep Pose)")
    np.testing.assert_array_equal(result.model_points()[turned], result.points[turned])
    assert _turn_from_template(result.model_points()[turned], result.points[result.names.index("blob1")]) > 80


def test_keep_pose_is_recorded_in_the_prepared_file_and_older_files_read_as_not_kept(blobs, tmp_path):
    kept = _prepared(blobs, keep_pose=[TURNED])
    assert [s.pose_kept for s in kept.shapes] == [False, False, False, True]
    loaded = PreparedCollection.load(kept.save(tmp_path / "kept.npz"))
    assert [s.pose_kept for s in loaded.shapes] == [False, False, False, True]
    old = {k: v for k, v in kept.to_arrays().items() if k != "pose_kept"}
    save_npz(tmp_path / "old.npz", PREPARED_FORMAT, PREPARED_VERSION, old)
    assert not any(s.pose_kept for s in PreparedCollection.load(tmp_path / "old.npz").shapes)


def test_a_closest_point_start_is_not_posed(prepared):
    result = correspond(prepared, _settings("closest"), template="blob1", jobs=1)
    assert result.diagnostics.shape_starts == ["closest", "template", "closest", "closest"]
    assert not result.posed.any() and result.diagnostics.pose_notes == ["", "", "", ""]
    np.testing.assert_array_equal(result.model_points(), result.points)  # bit for bit
    np.testing.assert_array_equal(result.model_transforms(), result.transforms)
    np.testing.assert_array_equal(result.landmark_matrix(), result.points.reshape(len(result), -1))


def test_the_poses_round_trip_through_the_correspondence_file_and_older_files_load_unposed(spectral, tmp_path):
    result, _ = spectral
    loaded = Correspondence.load(result.save(tmp_path / "corr.npz"))
    np.testing.assert_array_equal(loaded.poses, result.poses)
    assert (loaded.diagnostics.pose_notes, loaded.diagnostics.shape_starts) == \
        (result.diagnostics.pose_notes, result.diagnostics.shape_starts)
    np.testing.assert_array_equal(loaded.model_points(), result.model_points())
    old = Correspondence.from_arrays({k: v for k, v in result.to_arrays().items()
                                      if k not in ("poses", "pose_notes", "shape_starts")})
    assert not old.posed.any() and old.diagnostics.pose_notes == [] and old.diagnostics.shape_starts == []
    np.testing.assert_array_equal(old.model_points(), result.points)
    bad = dict(result.to_arrays())
    bad["poses"] = bad["poses"].copy()
    bad["poses"][0, :3, :3] *= 2.0
    with pytest.raises(Exception, match="not a rigid motion"):
        Correspondence.from_arrays(bad)


def test_the_model_learns_and_meshes_in_the_model_frame_and_its_file_keeps_the_poses(prepared, tmp_path):
    settings = FitSettings(model="ppca", latent_dim=1, template="blob1", correspondence=_settings("spectral"))
    model = fit_meshes(prepared, settings, jobs=1)
    corr = model.correspondence
    turned = model.names.index(TURNED)
    assert corr.posed[turned]
    # the training mesh moved with its landmarks: the landmarks lie on it, and meshing them gives it back
    mesh = model.meshes[turned]
    np.testing.assert_allclose(mesh.vertices, apply_pose(corr.poses[turned], prepared.shapes[turned].mesh.vertices))
    on_mesh = np.einsum("lk,lkd->ld", corr.barycentric[turned], mesh.vertices[mesh.faces[corr.face_index[turned]]])
    np.testing.assert_allclose(on_mesh, model.training_points[turned], atol=1e-9)
    again = model.mesh_from_landmarks(model.training_points[turned], template=TURNED)
    assert np.abs(again.vertices - mesh.vertices).max() < 1e-3 * mesh.bbox_diagonal()
    assert same_shapes(model, prepared)
    loaded = GenerativeShapeModel.load(model.save(tmp_path / "model.npz"))
    np.testing.assert_array_equal(loaded.correspondence.poses, corr.poses)
    np.testing.assert_allclose(loaded.meshes[turned].vertices, mesh.vertices)
    np.testing.assert_array_equal(loaded.training_matrix(), model.training_matrix())
    assert same_shapes(loaded, prepared)


def test_the_command_line_says_who_was_posed_and_a_fit_from_the_file_meshes_in_the_model_frame(blobs, tmp_path):
    """`shapegen correspond` records and reports the poses; `shapegen fit CORR --meshes DIR`
    reads the inputs again and puts each in the model frame by Prepare's transform and then
    its pose (`Correspondence.model_transforms`)."""
    import subprocess
    import sys
    from pathlib import Path

    from shapegen_core.meshes.reading import read_mesh
    from shapegen_core.meshes.writing import write_mesh

    shapegen = str(Path(sys.executable).with_name("shapegen"))
    folder = tmp_path / "blobs"
    folder.mkdir()
    for mesh in blobs:
        write_mesh(mesh, folder / f"{mesh.name}.ply")
    corr_file, model_file = tmp_path / "corr.npz", tmp_path / "model.npz"
    done = subprocess.run([shapegen, "correspond", str(folder), "-o", str(corr_file), "--align", "none", "--landmarks",
                           "60", "--initialisation", "spectral", "--template", "blob1", "--jobs", "1"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    corr = Correspondence.load(corr_file)
    turned = corr.names.index(TURNED)
    assert corr.posed[turned] and f"{corr.pose_summary()};" in done.stdout
    assert f"{TURNED}: posed by its landmarks: turned" in done.stderr
    done = subprocess.run([shapegen, "fit", str(corr_file), "--meshes", str(folder), "-o", str(model_file), "--model",
                           "ppca", "--latent-dim", "1"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    model = GenerativeShapeModel.load(model_file)
    to_model = ShapeTransform.from_matrix(corr.model_transforms()[turned])
    as_read = read_mesh(folder / f"{TURNED}.ply")
    np.testing.assert_allclose(model.meshes[turned].vertices, to_model.to_normalised(as_read.vertices), atol=1e-9)
    on_mesh = np.einsum("lk,lkd->ld", corr.barycentric[turned],
                        model.meshes[turned].vertices[model.meshes[turned].faces[corr.face_index[turned]]])
    np.testing.assert_allclose(on_mesh, model.training_points[turned], atol=1e-6)
