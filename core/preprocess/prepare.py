"""`prepare_collection`: align and scale a collection of meshes, every transform recorded
(thesis §3.4; the steps are in the package docstring)."""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..base.errors import CollectionError, MeshError
from ..meshes.mesh import FACE_CHUNK, Mesh
from ..meshes.simplify import DENSE_FACES, POSE_PROXY_FACES
from ..meshes.spill import loaded, proxy_of
from .consensus import ConsensusSettings, PoseDecision, ShapeEvidence, consensus_rotations
from .moments import SCALE_MODES, scale_measure, surface_moments
from .rotations import describe_rotation, horizontal_pca_rotation, up_rotation
from .transform import PreparedShape, ShapeTransform

__all__ = ["ALIGN_MODES", "CENTRE_MODES", "prepare_collection", "turn_as_flagged"]

ALIGN_MODES = ("consensus", "pca", "none")
CENTRE_MODES = ("centroid", "highest", "none")


def prepare_collection(
    meshes: Sequence[Mesh],
    up_axis: str = "z",
    align: str = "consensus",
    centre: str = "centroid",
    scale: str = "variance",
    seed: int = 0,
    progress: Callable[[float, str], None] | None = None,
    keep_pose: Sequence[bool] | None = None,
    consensus: ConsensusSettings = ConsensusSettings(),
    dense_faces: int = DENSE_FACES,
) -> list[PreparedShape]:
    """Align and scale a collection of meshes (see the package docstring for the steps).

    keep_pose: per shape, True to never turn it beyond the up axis (any align mode); its
    pose is still checked and flagged (`PreparedShape.pose_outlier`).
    dense_faces: the pose search and signatures see a mesh with more faces through its
    proxy of about POSE_PROXY_FACES faces (core/meshes/simplify.py), so their cost does
    not grow with the density of the mesh.
    meshes may be `spill.StoredMesh`es (dense meshes kept on disk for the run): the pose
    search uses their proxies built when they were read, each per-shape step at full
    density loads one at a time, and their prepared shapes are stored beside them."""
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown align mode {align!r}; choose from {ALIGN_MODES}")
    if centre not in CENTRE_MODES:
        raise ValueError(f"unknown centre mode {centre!r}; choose from {CENTRE_MODES}")
    if scale not in SCALE_MODES:
        raise ValueError(f"unknown scale mode {scale!r}; choose from {SCALE_MODES}")
    meshes = list(meshes)
    if not meshes:
        raise CollectionError("the collection is empty: nothing to prepare")
    keep = [False] * len(meshes) if keep_pose is None else [bool(k) for k in keep_pose]
    if len(keep) != len(meshes):
        raise ValueError(f"keep_pose has {len(keep)} entries for {len(meshes)} shapes")
    report = progress or (lambda fraction, message: None)

    up = up_rotation(up_axis)
    evidence = None
    if len(meshes) > 2 or (align == "consensus" and len(meshes) > 1):
        posed = [proxy_of(mesh, POSE_PROXY_FACES, dense_faces).mesh for mesh in meshes]
        evidence = ShapeEvidence.of(posed, up, consensus, seed, report)
        del posed
    report(0.2, "surface samples")
    names = [m.name for m in meshes]
    if align == "consensus" and evidence is not None:
        decisions = consensus_rotations(evidence, names, keep, consensus, report, up_axis)
    else:
        decisions = [_own_decision(mesh, up, align, k) for mesh, k in zip(meshes, keep)]
        if len(meshes) > 2:  # nobody is turned by the consensus, but a pose it doubts is flagged
            checks = consensus_rotations(evidence, names, keep, consensus, report, up_axis, may_turn=False)
            decisions = [PoseDecision(d.rotation, d.reason, d.steps, c.flag,
                                      None if c.flag_rotation is None else c.flag_rotation @ d.rotation)
                         for d, c in zip(decisions, checks)]
    report(0.9, "floor, centre and scale")

    transforms, measures = [], []
    for mesh, d in zip(meshes, decisions):  # one mesh at full density at a time (a stored one loaded)
        with loaded(mesh) as full:
            transforms.append(_floor_and_centre(full, d.rotation @ up, centre))
            if scale != "none":
                measures.append(_measure(full, transforms[-1], scale))
    if scale != "none":
        transforms = _equal_size(transforms, measures, scale)
    prepared = [PreparedShape(_normalised(mesh, t), t, d.changed, d.rotation, d.reason, d.flag, _flag_turn(d), k)
                for mesh, t, d, k in zip(meshes, transforms, decisions, keep)]
    report(1.0, "prepared")
    return prepared


def _flag_turn(decision: PoseDecision) -> np.ndarray | None:
    """The turn (after the shape's pose) that its flag suggests, None: no suggestion."""
    if decision.flag_rotation is None:
        return None
    return decision.flag_rotation @ decision.rotation.T


def _normalised(mesh, transform: ShapeTransform):
    """The mesh in the normalised frame; a stored mesh (core/meshes/spill.py) stays stored."""
    with loaded(mesh) as full:
        vertices = transform.to_normalised(full.vertices)
    return mesh.with_vertices(vertices)


def _own_decision(mesh, up: np.ndarray, align: str, keep: bool) -> PoseDecision:
    """The turn after the up rotation without consensus: the horizontal PCA (align "pca",
    unless the pose is kept), else none."""
    if align == "none" or keep:
        return PoseDecision(np.eye(3))
    with loaded(mesh) as full:
        yaw = horizontal_pca_rotation(full.with_vertices(full.vertices @ up.T))
    return PoseDecision(yaw, f"{describe_rotation(yaw)}: its principal horizontal axis to x (align pca)")


def _floor_and_centre(mesh: Mesh, rotation: np.ndarray, centre: str) -> ShapeTransform:
    """Step 4: the rotation, then the lowest surface vertex to z = 0 and the horizontal
    centre (surface centroid, highest vertex, or none) to x = y = 0."""
    # only vertices that belong to a face count (an unused stray vertex is no surface)
    rotated = mesh.vertices[mesh.used_vertices()] @ rotation.T
    shift = np.zeros(3)
    shift[2] = -rotated[:, 2].min()
    if centre == "centroid":
        _, mean, _ = surface_moments(mesh)
        shift[:2] = -(rotation @ mean)[:2]
    elif centre == "highest":
        shift[:2] = -rotated[int(np.argmax(rotated[:, 2])), :2]
    return ShapeTransform(rotation, 1.0, shift)


def _measure(mesh: Mesh, transform: ShapeTransform, scale: str) -> float:
    """Step 5's measure (`scale_measure`) of one shape after `transform`. The surface
    variance of a mesh above FACE_CHUNK faces comes from its own moments (a similarity's
    rotation and shift leave it, its scale multiplies it by scale²), not from a transformed
    copy."""
    if scale == "variance" and mesh.n_faces > FACE_CHUNK:
        value = transform.scale ** 2 * scale_measure(mesh, scale)
    else:
        value = scale_measure(mesh.with_vertices(transform.to_normalised(mesh.vertices)), scale)
    if not np.isfinite(value) or value <= 0:
        raise MeshError(
            f"{mesh.name or 'mesh'}: cannot scale by {scale}: the measure is {value} "
            "(a flat or degenerate shape)"
        )
    return value


def _equal_size(transforms: Sequence[ShapeTransform], measures: Sequence[float], scale: str) -> list[ShapeTransform]:
    """Step 5: scale every shape so its measure (`_measure`) equals the geometric mean of
    the collection's measures."""
    measures = np.asarray(measures)
    target = float(np.exp(np.mean(np.log(measures))))
    power = 0.5 if scale == "variance" else 1.0 / 3.0
    return [t.then(scale=(target / m) ** power) for t, m in zip(transforms, measures)]


def turn_as_flagged(shape: PreparedShape, centre: str = "centroid") -> tuple[PreparedShape, ShapeTransform]:
    """Shape turned by the turn its flag suggests (`PreparedShape.flag_turn`), at the
    user's request (Turn Flagged), floored and centred again (`centre`; the scale is
    unchanged, a turn leaves the surface variance as it is), and the step from its
    normalised frame to the new one (to carry its landmarks). Its pose report says so and
    the flag is cleared. A shape without a suggested turn is returned as it is."""
    if shape.flag_turn is None:
        return shape, ShapeTransform.identity()
    step = _floor_and_centre(shape.mesh, shape.flag_turn, centre)
    transform = shape.transform.then(step.rotation, step.scale, step.translation)
    rotation = shape.flag_turn @ shape.pose_rotation
    reason = f"{describe_rotation(shape.flag_turn)} at the user's request (flagged: {shape.pose_outlier})"
    if shape.pose_change:
        reason = f"{describe_rotation(rotation)} in all ({shape.pose_change}; then {reason})"
    turned = PreparedShape(shape.mesh.with_vertices(step.to_normalised(shape.mesh.vertices)), transform, True,
                           rotation, reason, "", None, shape.pose_kept)
    return turned, step
