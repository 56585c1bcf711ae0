"""Groupwise correspondence over a prepared collection (thesis §4.2.7): choose a template
(the Chamfer medoid), register it to every shape, flag shapes that fit badly
(outliers.py), replace the template by the mean landmark cloud of the shapes that fit,
register again. A medoid the first round flags gives way to the medoid of the rest.
Last, the shapes registered from the intrinsic start are posed in the model frame by their
landmarks (posing.py), and each shape's start and pose are recorded."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..base.errors import CollectionError, MeshError
from ..geometry import SurfacePoints, chamfer_distance, chamfer_matrix, knn_graph, registration_frame
from ..base.progress import Progress, no_progress, sub_range
from .engine import make_runner
from .pool import RegistrationRunner, RegistrationTask
from .proxy import dense_shapes, face_normals_at, place_dense, proxies_of
from .outliers import flag_outliers
from .posing import landmark_poses
from .diagnostics import CorrespondenceDiagnostics
from .matching import DataTerm, data_term_for
from .registration import Registration
from .result import Correspondence
from .settings import CorrespondenceSettings
from .starting import RoundsSetup, Start, start_for

__all__ = ["chamfer_medoid", "correspond"]

#: the medoid sums over every pair up to this many shapes; beyond, it screens against
#: MEDOID_REFERENCES shapes and sums over all only for the MEDOID_SHORTLIST best
MEDOID_EXACT_SHAPES, MEDOID_REFERENCES, MEDOID_SHORTLIST = 200, 32, 16


def chamfer_medoid(point_sets: Sequence[np.ndarray], max_points: int = 300) -> int:
    """Index of the point set with the smallest summed symmetric Chamfer distance
    (geometry.chamfer) to all others. Each set is thinned to its first `max_points` points
    (landmarks are farthest-point ordered, so a prefix covers the surface). Above
    MEDOID_EXACT_SHAPES sets (every pair is O(N²), 1000 shapes about 200 s) the
    sums are screened against MEDOID_REFERENCES sets spread over the collection and only
    the MEDOID_SHORTLIST best are summed over all sets."""
    sets = [np.asarray(s, dtype=np.float64)[:max_points] for s in point_sets]
    if len(sets) <= MEDOID_EXACT_SHAPES:
        return int(np.argmin(chamfer_matrix(sets).sum(axis=1)))
    trees = [cKDTree(s) for s in sets]

    def summed(j: int, others) -> float:
        return sum(chamfer_distance(sets[j], sets[i], None, trees[j], trees[i]) for i in others if i != j)

    references = np.unique(np.linspace(0, len(sets) - 1, MEDOID_REFERENCES).round().astype(int))
    screened = np.argsort([summed(j, references) for j in range(len(sets))], kind="stable")[:MEDOID_SHORTLIST]
    return int(min(screened, key=lambda j: summed(int(j), range(len(sets)))))


def _template_index(names: list[str], template: str | None, landmark_sets, candidates: Sequence[int]) -> int:
    """The named template, else the Chamfer medoid of the `candidates` (shape indices)."""
    if template is None:
        candidates = list(candidates)
        return candidates[chamfer_medoid([landmark_sets[i] for i in candidates])]
    if template not in names:
        shown = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "")
        raise CollectionError(f"template {template!r} is not a shape of the collection ({shown})")
    return names.index(template)


@dataclass
class _Rounds:
    """The outcome of the groupwise rounds from one template (`_run_rounds`)."""

    start: int  # index of the shape the first template came from
    edges: np.ndarray
    template: np.ndarray  # the template of the last round
    registrations: list  # of the last round, in the registration frame
    results: list  # the same in the normalised frame
    residuals: np.ndarray
    reasons: list[str]
    rounds_run: int
    centre: np.ndarray | None = None  # the registration frame of these rounds
    scale: float = 1.0
    shape_starts: list[str] | None = None  # per shape, its start: "spectral", "closest" or "template"
    matching: dict = field(default_factory=dict)  # what the data term decided (matching.py `RoundMatches.record`)

    @property
    def keep(self) -> np.ndarray:
        return np.array([not r for r in self.reasons])


def correspond(
    collection,
    settings: CorrespondenceSettings = CorrespondenceSettings(),
    template: str | None = None,
    jobs: int | None = None,
    progress: Progress | None = None,
    should_cancel=None,
    scheduler: str | None = None,
) -> Correspondence:
    """Groupwise non-rigid ICP over a `PreparedCollection` (thesis §4.2, docs/method.md §3).

    template: a shape name, or None for the medoid by symmetric Chamfer distance. An
    outlier is never the medoid template: when a round flags the medoid (outliers.py;
    a shape turned upside down fits itself as the first template, the mean template
    of the next round shows it), the medoid of the shapes that round did not flag
    becomes the template and the rounds start again from it (a template given by name
    is kept). Outliers cannot be left out of the first medoid choice: they are known
    only after a round of registrations. Last, each shape registered from the intrinsic
    start gets its pose in the model frame from its landmarks (`_posed`, posing.py).
    jobs: worker processes (None: all cores; 1: in this process).
    progress: fractions over the R = groupwise_rounds + 1 rounds of registrations, each
    round an equal share filled as its shapes' ICP iterations run (core/progress.py);
    after a change of template the new rounds share what is left;
    messages name the template, the shape being registered and the round.
    should_cancel: None, a callable or an Event, checked between ICP iterations; raises
    errors.Cancelled.
    scheduler: run the registrations on a Dask cluster instead of local processes
    (tcp://host:port or local:N; engine.py, core/cluster.py); same results.
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
    # shapes whose pose Prepare flagged (PreparedShape.pose_outlier) are no medoid candidates
    posed_well = [i for i, shape in enumerate(collection.shapes) if not shape.pose_outlier]
    start = _template_index(names, template, landmark_sets, posed_well or range(len(names)))
    report(0.0, f"template {names[start]}")

    jobs = (os.cpu_count() or 1) if jobs is None else int(jobs)
    jobs = max(1, min(jobs, len(names)))
    rounds = settings.groupwise_rounds + 1
    runner = make_runner(jobs, scheduler, should_cancel)
    dense = dense_shapes(collection.shapes, settings)
    try:
        # dense shapes: proxies first (0-5 % of NICP), exact placement on their full surfaces last (95-100 %)
        surfaces = proxies_of(collection.shapes, dense, settings, runner, sub_range(report, 0.0, 0.05))
        rounds_report = sub_range(report, 0.05, 0.95) if dense else report
        chosen, rounds_report = start_for(settings).chosen([s.mesh for s in surfaces], landmark_sets, start, runner,
                                                           rounds_report)
        data_term = data_term_for(settings)
        outcome = _run_rounds(collection, start, settings, runner, rounds_report, template is None, surfaces, chosen,
                              data_term)
        if template is None and outcome.reasons[start]:
            fits = np.flatnonzero(outcome.keep)
            if len(fits):
                start = _template_index(names, None, landmark_sets, fits)
                done = outcome.rounds_run / rounds
                rounds_report(done, f"template {names[start]} ({names[outcome.start]} is an outlier: "
                                    f"{outcome.reasons[outcome.start]})")
                outcome = _run_rounds(collection, start, settings, runner, sub_range(rounds_report, done, 1.0),
                                      False, surfaces, chosen, data_term)
        if dense:
            registrations = place_dense(outcome.registrations, collection, surfaces, dense, settings, outcome.centre,
                                       outcome.scale, runner, sub_range(report, 0.95, 1.0))
            outcome = replace(outcome, registrations=registrations,
                              results=[_to_normalised(r, outcome.centre, outcome.scale) for r in registrations],
                              residuals=_relative_residuals(registrations, outcome.scale, collection.shapes))
    finally:
        runner.close()
    template_name = names[outcome.start]

    results, registrations = outcome.results, outcome.registrations
    points = np.stack([r.placed.points for r in results])
    face_index = np.stack([r.placed.face_index for r in results])
    barycentric = np.stack([r.placed.barycentric for r in results])
    poses, pose_notes = _posed(collection, names, points, outcome, report)
    report(1.0, f"corresponded {len(names)} shapes (template {template_name})")
    transforms = [shape.transform for shape in collection.shapes]
    return Correspondence(
        names=names,
        points=points,
        points_input=np.stack([t.to_input(p) for t, p in zip(transforms, points)]),
        face_index=face_index,
        barycentric=barycentric,
        edges=outcome.edges,
        template_points=np.asarray(outcome.template, dtype=np.float64),
        template_name=template_name,
        transforms=np.stack([t.matrix for t in transforms]),
        residuals=outcome.residuals,
        outliers=~outcome.keep,
        outlier_reasons=outcome.reasons,
        settings=settings,
        prepare=collection.settings,
        unreadable=dict(collection.unreadable),
        poses=poses,
        diagnostics=CorrespondenceDiagnostics(
            iterations=np.array([r.iterations for r in registrations]), start=chosen.kind, start_reason=chosen.reason,
            shape_starts=list(outcome.shape_starts), pose_notes=pose_notes, **outcome.matching),
    )


def _posed(collection, names: list[str], points: np.ndarray, outcome: _Rounds, report: Progress
           ) -> tuple[np.ndarray, list[str]]:
    """The step from corresponded landmarks to the model frame (posing.py): each shape
    registered from the intrinsic start, not kept by request, is posed by the rigid fit of
    its landmarks onto the template shape's; the others stay as Prepare left them. Each
    shape posed or kept says so in one line."""
    poses, notes = landmark_poses(points, outcome.start, outcome.shape_starts,
                                  [shape.pose_kept for shape in collection.shapes])
    for name, note in zip(names, notes):
        if note:
            report(1.0, f"{name}: {note}")
    return poses, notes


def _run_rounds(collection, start: int, settings: CorrespondenceSettings, runner: RegistrationRunner,
                report: Progress, stop_if_template_flagged: bool, surfaces: Sequence, chosen: Start,
                data_term: DataTerm) -> _Rounds:
    """The R = groupwise_rounds + 1 rounds from the landmarks of shape `start` (§4.2.7):
    register the template to every shape, flag outliers, replace the template by the mean
    landmark cloud of the shapes that fit, again. With `stop_if_template_flagged`, stops
    after the first round that flags shape `start`. `surfaces`: per shape, the mesh to
    register against (a dense shape's proxy). Where each shape starts is the `chosen`
    start's (starting.py), what the registrations match and how each round runs is the
    `data_term`'s (matching.py)."""
    names = list(collection.names)
    template_points = np.asarray(collection.landmarks[start].points, dtype=np.float64)
    centre, scale = registration_frame(template_points, names[start])
    to_frame = lambda p: (np.asarray(p) - centre) / scale  # noqa: E731
    template_normals = face_normals_at(collection.shapes[start].mesh, collection.landmarks[start].face_index)
    landmark_normals = [face_normals_at(s.mesh, l.face_index) for s, l in zip(collection.shapes, collection.landmarks)]
    edges = knn_graph(template_points, settings.stiffness.k_neighbours)
    template_diagonal = collection.shapes[start].mesh.bbox_diagonal()
    ratios = np.array([s.mesh.bbox_diagonal() / template_diagonal for s in collection.shapes])
    rounds = settings.groupwise_rounds + 1
    in_frame = [not shape.pose_outlier for shape in collection.shapes]
    starter, report = chosen.begin(RoundsSetup(names, surfaces, start, template_points, in_frame, to_frame, runner),
                                   report)
    matches = data_term.begin(start, template_normals)
    outcome = None
    shape_starts = ["template" if index == start else "closest" for index in range(len(names))]
    current_template, current_normals = template_points, template_normals
    for round_index in range(rounds):
        label = f"round {round_index + 1} of {rounds}"
        round_report = sub_range(report, round_index / rounds, (round_index + 1) / rounds)
        if outcome is not None:
            current_template, current_normals = _mean_template(outcome.results, outcome.keep)
        template_in_frame = to_frame(current_template)
        tasks, message = matches.tasks([
            RegistrationTask(i, names[i], surface.mesh.vertices, surface.mesh.faces, landmarks.points,
                             landmark_normals[i], template_in_frame, current_normals, edges, settings, centre, scale)
            for i, (surface, landmarks) in enumerate(zip(surfaces, collection.landmarks))
        ], outcome)
        if outcome is not None:
            report(round_index / rounds, f"mean template ({label}){message}")

        def run(tasks, report, label, round_index=round_index):
            return matches.run(round_index, tasks, runner, report, label)

        registrations, taken = starter.registrations(round_index, tasks, outcome, run, round_report, label)
        shape_starts = taken or shape_starts
        results = [_to_normalised(r, centre, scale) for r in registrations]
        residuals = _relative_residuals(registrations, scale, collection.shapes)
        reasons = _with_pose_flags(flag_outliers(residuals, ratios, settings,
                                                 np.stack([r.placed.points for r in results])), collection.shapes)
        outcome = _Rounds(start, edges, current_template, registrations, results, residuals, reasons,
                          round_index + 1, centre, scale, list(shape_starts), matches.record())
        if stop_if_template_flagged and reasons[start]:
            break
    return outcome


def _relative_residuals(registrations: Sequence[Registration], scale: float, shapes) -> np.ndarray:
    """Each registration's residual (registration frame) as a fraction of its shape's
    bounding-box diagonal."""
    return np.array([r.residual * scale / s.mesh.bbox_diagonal() for r, s in zip(registrations, shapes)])


def _with_pose_flags(reasons: list[str], shapes) -> list[str]:
    """Each shape's correspondence reasons, followed by the pose flag Prepare raised for it
    (`PreparedShape.pose_outlier`), so a wrong pose is an outlier with its reason."""
    return ["; ".join(part for part in (reason, shape.pose_outlier and f"Prepare: {shape.pose_outlier}") if part)
            for reason, shape in zip(reasons, shapes)]


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
    use = _fitting(results, keep)
    points = np.mean([r.placed.points for r in use], axis=0)
    normals = np.sum([r.normals for r in use], axis=0)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return points, normals


def _fitting(results: Sequence[Registration], keep: np.ndarray) -> list[Registration]:
    """The registrations of the shapes that fit (all, if none does)."""
    return [r for r, k in zip(results, keep) if k] or list(results)
