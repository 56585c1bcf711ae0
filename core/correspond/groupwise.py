"""Groupwise correspondence over a prepared collection (thesis §4.2.7): choose a template
(the Chamfer medoid), register it to every shape, replace it by the mean landmark cloud
of the shapes that fit, register again; flag shapes that fit badly."""

from __future__ import annotations

import os
from dataclasses import replace
from typing import Sequence

import numpy as np

from ..errors import CollectionError, MeshError
from ..geometry import SurfacePoints, chamfer_matrix, knn_graph, registration_frame
from ..progress import Progress, no_progress, sub_range
from .pool import RegistrationRunner, RegistrationTask
from .registration import Registration
from .result import Correspondence
from .settings import CorrespondenceSettings

__all__ = ["chamfer_medoid", "correspond", "flag_outliers"]


def chamfer_medoid(point_sets: Sequence[np.ndarray], max_points: int = 300) -> int:
    """Index of the set with the smallest summed symmetric Chamfer distance
    (geometry.chamfer) to all others. Each set is thinned to its first `max_points` points
    (landmarks come in random order, so these are spread)."""
    sets = [np.asarray(s, dtype=np.float64)[:max_points] for s in point_sets]
    return int(np.argmin(chamfer_matrix(sets).sum(axis=1)))


def flag_outliers(residuals: np.ndarray, scale_ratios: np.ndarray,
                  settings: CorrespondenceSettings = CorrespondenceSettings()) -> list[str]:
    """A reason string per shape ("" = fits). Rules (any one flags):
    robust: residual > median + f · 1.4826 · MAD and > `outlier_min_ratio` × median
    (needs 3+ shapes); absolute: residual > `max_residual`; scale: bounding-box diagonal
    differs from the template's by more than `max_scale_ratio` (either way)."""
    residuals = np.asarray(residuals, dtype=np.float64)
    median = float(np.median(residuals))
    mad = 1.4826 * float(np.median(np.abs(residuals - median)))
    reasons = []
    for residual, ratio in zip(residuals, scale_ratios):
        why = []
        if len(residuals) >= 3 and residual > median + settings.outlier_mad_factor * mad \
                and residual > settings.outlier_min_ratio * median:
            why.append(f"residual {residual:.4f} of the diagonal is far above the collection's median {median:.4f}")
        elif residual > settings.max_residual:
            why.append(f"residual {residual:.4f} of the diagonal exceeds {settings.max_residual}")
        if ratio > settings.max_scale_ratio or ratio < 1.0 / settings.max_scale_ratio:
            why.append(f"size is {ratio:.3g}× the template's (alignment or scaling failed or is off)")
        reasons.append("; ".join(why))
    return reasons


def _template_index(names: list[str], template: str | None, landmark_sets) -> int:
    if template is None:
        return chamfer_medoid(landmark_sets)
    if template not in names:
        shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
        raise CollectionError(f"template {template!r} is not a shape of the collection ({shown})")
    return names.index(template)


def correspond(
    collection,
    settings: CorrespondenceSettings = CorrespondenceSettings(),
    template: str | None = None,
    jobs: int | None = None,
    progress: Progress | None = None,
    should_cancel=None,
) -> Correspondence:
    """Groupwise non-rigid ICP over a `PreparedCollection` (thesis §4.2, method.md §3).

    template: a shape name, or None for the medoid by symmetric Chamfer distance.
    jobs: worker processes (None: all cores; 1: in this process).
    progress: fractions over the R = groupwise_rounds + 1 rounds of registrations, each
    round an equal share filled as its shapes' ICP iterations run (core/progress.py);
    messages name the template, the shape being registered and the round.
    should_cancel: None, a callable or an Event, checked between ICP iterations; raises
    errors.Cancelled.
    """
    report = progress or no_progress
    names = list(collection.names)
    if len(names) < 2:
        raise CollectionError(
            f"correspondence needs a collection of at least 2 shapes, got {len(names)}"
            + (f" ({names[0]})" if names else ""))
    for shape in collection.shapes:
        if not shape.mesh.area() > 0:
            raise MeshError(f"{shape.name}: surface area is zero (degenerate mesh); cannot register to it")
    landmark_sets = [l.points for l in collection.landmarks]
    start = _template_index(names, template, landmark_sets)
    template_name = names[start]
    report(0.0, f"template {template_name}")

    template_points = np.asarray(landmark_sets[start], dtype=np.float64)
    centre, scale = registration_frame(template_points, template_name)
    to_frame = lambda p: (np.asarray(p) - centre) / scale  # noqa: E731
    template_normals = collection.shapes[start].mesh.face_normals()[collection.landmarks[start].face_index]
    edges = knn_graph(template_points, settings.k_neighbours)

    jobs = (os.cpu_count() or 1) if jobs is None else int(jobs)
    jobs = max(1, min(jobs, len(names)))
    rounds = settings.groupwise_rounds + 1
    runner = RegistrationRunner(jobs, should_cancel)
    try:
        current_template, current_normals = template_points, template_normals
        for round_index in range(rounds):
            label = f"round {round_index + 1} of {rounds}"
            if round_index > 0:
                current_template, current_normals = _mean_template(results, keep)
                report(round_index / rounds, f"mean template ({label})")
            tasks = [
                RegistrationTask(i, names[i], to_frame(shape.mesh.vertices), shape.mesh.faces,
                      to_frame(landmarks.points), shape.mesh.face_normals()[landmarks.face_index],
                      to_frame(current_template), current_normals, edges, settings)
                for i, (shape, landmarks) in enumerate(zip(collection.shapes, collection.landmarks))
            ]
            registrations = runner.run(tasks, sub_range(report, round_index / rounds, (round_index + 1) / rounds),
                                       label)
            results = [_to_normalised(r, centre, scale) for r in registrations]
            residuals = np.array([r.residual * scale / s.mesh.bbox_diagonal()
                                  for r, s in zip(registrations, collection.shapes)])
            template_diagonal = collection.shapes[start].mesh.bbox_diagonal()
            ratios = np.array([s.mesh.bbox_diagonal() / template_diagonal for s in collection.shapes])
            reasons = flag_outliers(residuals, ratios, settings)
            keep = np.array([not r for r in reasons])
    finally:
        runner.close()
    report(1.0, f"corresponded {len(names)} shapes (template {template_name})")

    points = np.stack([r.placed.points for r in results])
    transforms = [shape.transform for shape in collection.shapes]
    return Correspondence(
        names=names,
        points=points,
        points_input=np.stack([t.to_input(p) for t, p in zip(transforms, points)]),
        face_index=np.stack([r.placed.face_index for r in results]),
        barycentric=np.stack([r.placed.barycentric for r in results]),
        edges=edges,
        template_points=np.asarray(current_template, dtype=np.float64),
        template_name=template_name,
        transforms=np.stack([t.matrix for t in transforms]),
        residuals=residuals,
        iterations=np.array([r.iterations for r in registrations]),
        outliers=~keep,
        outlier_reasons=reasons,
        settings=settings,
        prepare=collection.settings,
    )


def _to_normalised(registration: Registration, centre: np.ndarray, scale: float) -> Registration:
    """Map a registration's points from the registration frame back to the normalised frame."""
    placed = registration.placed
    return replace(
        registration,
        placed=SurfacePoints(placed.points * scale + centre, placed.face_index, placed.barycentric,
                             placed.distance * scale),
        deformed=registration.deformed * scale + centre,
        residual=registration.residual * scale,
    )


def _mean_template(results: Sequence[Registration], keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """§4.2.7: the mean landmark cloud over the shapes that fit (all, if none does), with
    the normalised mean of the target normals at the placed points."""
    use = [r for r, k in zip(results, keep) if k] or list(results)
    points = np.mean([r.placed.points for r in use], axis=0)
    normals = np.sum([r.normals for r in use], axis=0)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return points, normals
