"""Groupwise correspondence over a prepared collection (thesis §4.2.7): choose a template
(the Chamfer medoid), register it to every shape, flag shapes that fit badly
(outliers.py), replace the template by the mean landmark cloud of the shapes that fit,
register again. A medoid the first round flags gives way to the medoid of the rest.
Last, the shapes registered from the intrinsic start are posed in the model frame by their
landmarks (posing.py), and each shape's start and pose are recorded."""

from __future__ import annotations

import os
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..errors import CollectionError, MeshError
from ..geometry import SurfacePoints, chamfer_distance, chamfer_matrix, knn_graph, registration_frame
from ..progress import Progress, no_progress, sub_range
from ..simplify import Proxy
from ..spill import full_mesh
from .engine import make_runner
from .pool import RegistrationRunner, RegistrationTask
from .proxy import dense_shapes, face_normals_at, place_dense, proxies_of
from .outliers import flag_outliers
from .posing import landmark_poses
from .refine import refine_population
from .features import agreement_weights, checks_fit, checks_regions, keeps_features, merged_regions, uses_between, \
    worse_fits
from .registration import Registration
from .result import Correspondence
from .settings import CorrespondenceSettings
from .start import checked_spectral_fits, chosen_start, pose_evidence, signature_error, spectral_starts

__all__ = ["chamfer_medoid", "correspond"]

#: the medoid sums over every pair up to this many shapes; beyond, it screens against
#: MEDOID_REFERENCES shapes and sums over all only for the MEDOID_SHORTLIST best
MEDOID_EXACT_SHAPES, MEDOID_REFERENCES, MEDOID_SHORTLIST = 200, 32, 16


def chamfer_medoid(point_sets: Sequence[np.ndarray], max_points: int = 300) -> int:
    """Index of the point set with the smallest summed symmetric Chamfer distance
    (geometry.chamfer) to all others. Each set is thinned to its first `max_points` points
    (landmarks are farthest-point ordered, so a prefix covers the surface). Above
    MEDOID_EXACT_SHAPES sets (issue 15: every pair is O(N²), 1000 shapes about 200 s) the
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
    between_shares: np.ndarray | None = None  # (M,) each shape's share of feature_between (None: not compared)
    feature_fit_worse: np.ndarray | None = None  # (M,) bool: feature matches fitted worse (None: not checked)
    plain_shares: np.ndarray | None = None  # (M,) share of template points matched plainly (None: not checked)
    shape_starts: list[str] | None = None  # per shape, its start: "spectral", "closest" or "template"

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
    refining = settings.refinement.method == "population"
    nicp_report = sub_range(report, 0.0, REFINE_START) if refining else report
    runner = make_runner(jobs, scheduler, should_cancel)
    dense = dense_shapes(collection.shapes, settings)
    try:
        # dense shapes: proxies first (0-5 % of NICP), exact placement on their full surfaces last (95-100 %)
        surfaces = proxies_of(collection.shapes, dense, settings, runner, sub_range(nicp_report, 0.0, 0.05))
        rounds_report = sub_range(nicp_report, 0.05, 0.95) if dense else nicp_report
        initialisation, start_reason = settings.data_term.initialisation, "asked for"
        if initialisation == "auto":
            evidence = pose_evidence([s.mesh for s in surfaces], landmark_sets, start, runner,
                                     sub_range(rounds_report, 0.0, EVIDENCE_SHARE))
            initialisation, start_reason = chosen_start(evidence)
            rounds_report(EVIDENCE_SHARE, f"{'intrinsic (spectral)' if initialisation == 'spectral' else 'closest-point'}"
                                          f" start chosen for the collection: {start_reason}")
            rounds_report = sub_range(rounds_report, EVIDENCE_SHARE, 1.0)
        settings_run = replace(settings, data_term=replace(settings.data_term, initialisation=initialisation))
        outcome = _run_rounds(collection, start, settings_run, runner, rounds_report,
                              stop_if_template_flagged=template is None, surfaces=surfaces, start_reason=start_reason)
        if template is None and outcome.reasons[start]:
            fits = np.flatnonzero(outcome.keep)
            if len(fits):
                start = _template_index(names, None, landmark_sets, fits)
                done = outcome.rounds_run / rounds
                rounds_report(done, f"template {names[start]} ({names[outcome.start]} is an outlier: "
                                    f"{outcome.reasons[outcome.start]})")
                outcome = _run_rounds(collection, start, settings_run, runner, sub_range(rounds_report, done, 1.0),
                                      stop_if_template_flagged=False, surfaces=surfaces, start_reason=start_reason)
        if dense:
            registrations = place_dense(outcome.registrations, collection, surfaces, dense, settings, outcome.centre,
                                       outcome.scale, runner, sub_range(nicp_report, 0.95, 1.0))
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
    trace = np.zeros((0, 3))
    if refining:
        points, face_index, barycentric, trace = _refined(collection, outcome.keep, points, face_index, barycentric,
                                                          outcome.edges, settings,
                                                          sub_range(report, REFINE_START, 1.0), should_cancel, jobs)
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
        iterations=np.array([r.iterations for r in registrations]),
        outliers=~outcome.keep,
        outlier_reasons=outcome.reasons,
        settings=settings,
        prepare=collection.settings,
        refinement=settings.refinement.method if len(trace) else "none",
        refinement_trace=trace,
        between_shares=np.zeros(0) if outcome.between_shares is None else outcome.between_shares,
        feature_fit_worse=np.zeros(0, dtype=bool) if outcome.feature_fit_worse is None else outcome.feature_fit_worse,
        plain_shares=np.zeros(0) if outcome.plain_shares is None else outcome.plain_shares,
        unreadable=dict(collection.unreadable),
        start=initialisation,
        start_reason=start_reason,
        shape_starts=list(outcome.shape_starts),
        poses=poses,
        pose_notes=pose_notes,
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


#: with refinement, NICP's progress fills [0, REFINE_START] and the refinement the rest
REFINE_START = 0.8
#: with the spectral start, the intrinsic maps fill this share of the rounds' progress
SPECTRAL_SHARE = 0.2
#: with the automatic start, the evidence (the shapes' spectra) fills this share of it
EVIDENCE_SHARE = 0.05


def _refined(collection, keep, points, face_index, barycentric, edges, settings, report, should_cancel, jobs):
    """The landmarks of the shapes that fit (`keep`) refined together (refine.py); outliers
    keep theirs. Returns points, face_index, barycentric and the objective trace."""
    active = np.flatnonzero(keep)
    if len(active) < 3:  # no population to speak of: the objective's covariance is degenerate
        report(1.0, f"refinement skipped: {len(active)} shapes fit")
        return points, face_index, barycentric, np.zeros((0, 3))
    meshes = [full_mesh(collection.shapes[i].mesh) for i in active]  # a stored dense mesh loaded (core/spill.py)
    result = refine_population(meshes, points[active], face_index[active], barycentric[active], settings, report,
                               should_cancel, edges, jobs)
    points, face_index, barycentric = points.copy(), face_index.copy(), barycentric.copy()
    points[active], face_index[active], barycentric[active] = result.points, result.face_index, result.barycentric
    return points, face_index, barycentric, result.trace


def _run_rounds(collection, start: int, settings: CorrespondenceSettings, runner: RegistrationRunner,
                report: Progress, stop_if_template_flagged: bool, surfaces: Sequence | None = None,
                start_reason: str = "asked for") -> _Rounds:
    """The R = groupwise_rounds + 1 rounds from the landmarks of shape `start` (§4.2.7):
    register the template to every shape, flag outliers, replace the template by the mean
    landmark cloud of the shapes that fit, again. With `stop_if_template_flagged`, stops
    after the first round that flags shape `start`. `surfaces`: per shape, the mesh to
    register against (a dense shape's proxy; default each shape's own mesh). `settings`
    name the start ("closest" or "spectral", "auto" resolved by the caller); `start_reason`
    says why, in each shape's message."""
    surfaces = [Proxy(s.mesh) for s in collection.shapes] if surfaces is None else surfaces
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
    starts = None
    if settings.data_term.initialisation == "spectral":
        # a shape Prepare flagged (on its side, upside down, unusual) may not face as the others do
        in_frame = [not shape.pose_outlier for shape in collection.shapes]
        starts, template_signatures = spectral_starts(names, surfaces, start, template_points, runner,
                                                      sub_range(report, 0.0, SPECTRAL_SHARE), in_frame)
        chosen = "" if start_reason == "asked for" else f"; chosen for the collection: {start_reason}"
        for name, spectral in zip(names, starts):
            if spectral is not None:
                report(SPECTRAL_SHARE, f"{name}: {spectral.message}{chosen}")
        report = sub_range(report, SPECTRAL_SHARE, 1.0)
    else:
        for index, name in enumerate(names):
            if index != start:
                report(0.0, f"{name}: closest-point start ({start_reason})")
    outcome = None
    shape_starts = ["template" if index == start else "closest" for index in range(len(names))]
    current_template, current_normals, current_between = template_points, template_normals, None
    round_settings, shares, worse = settings, None, None  # round_settings: closest points after a failed fit check
    plain = None  # per shape, the template points matched plainly (features.merged_regions), from round 2 on
    for round_index in range(rounds):
        label = f"round {round_index + 1} of {rounds}"
        round_report = sub_range(report, round_index / rounds, (round_index + 1) / rounds)
        if outcome is not None:
            current_template, current_normals = _mean_template(outcome.results, outcome.keep)
            message = f"mean template ({label})"
            if current_between is None and uses_between(round_settings):
                current_between = _template_between(outcome, start)
                shares = agreement_weights(current_between, [r.between for r in outcome.results])
                message += f"; turning lines compared on {int(np.count_nonzero(shares))} of {len(names)} shapes"
            if plain is None and checks_regions(round_settings):
                template_regions = outcome.results[start].regions
                plain = [merged_regions(template_regions, template_normals, r.regions) for r in outcome.results]
                message += f"; regions merged on {sum(int(p.any()) for p in plain)} of {len(names)} shapes"
            report(round_index / rounds, message)
        template_in_frame = to_frame(current_template)
        shape_settings = ([round_settings] * len(names) if shares is None else
                          [_with_between_share(round_settings, share) for share in shares])
        tasks = [
            RegistrationTask(i, names[i], surface.mesh.vertices, surface.mesh.faces, landmarks.points,
                             landmark_normals[i], template_in_frame, current_normals, edges, shape_settings[i], centre,
                             scale, current_between, None if plain is None else plain[i])
            for i, (surface, landmarks) in enumerate(zip(surfaces, collection.landmarks))
        ]
        if starts is not None:
            registrations, taken = _from_spectral_starts(tasks, starts, template_signatures, outcome, to_frame,
                                                         runner, round_report, label)
            shape_starts = taken or shape_starts
        elif round_index == 0 and checks_fit(settings):
            registrations, round_settings, worse = _checked_feature_fits(tasks, start, runner, round_report, label)
        else:
            registrations = runner.run(tasks, round_report, label)
        results = [_to_normalised(r, centre, scale) for r in registrations]
        residuals = _relative_residuals(registrations, scale, collection.shapes)
        reasons = _with_pose_flags(flag_outliers(residuals, ratios, settings,
                                                 np.stack([r.placed.points for r in results])), collection.shapes)
        outcome = _Rounds(start, edges, current_template, registrations, results, residuals, reasons,
                          round_index + 1, centre, scale, shares, worse,
                          None if plain is None else np.array([p.mean() for p in plain]), list(shape_starts))
        if stop_if_template_flagged and reasons[start]:
            break
    return outcome


def _from_spectral_starts(tasks: list[RegistrationTask], starts: list, template_signatures, previous: _Rounds | None,
                          to_frame, runner: RegistrationRunner, report: Progress, label: str
                          ) -> tuple[list[Registration], list[str] | None]:
    """(the spectral start, **beyond** the thesis; start.py) the round's registrations. The
    first round registers every shape from its spectral start (`starts[i]`, None for the
    template's own shape) beside the closest-point start, which replaces it where the
    spectrum was not trusted, the spectral fit is clearly worse or its landmarks do not
    match the template's signatures clearly better (start.py; said per shape). Later
    rounds start every shape from its previous round's landmarks: the mean template of
    shapes in different poses is no start, and the affines then act on those landmarks.
    Returns the registrations and, from the first round, the start each shape kept
    ("spectral", "closest", "template" for the template's own shape; None in later rounds,
    which keep the first's)."""
    if previous is not None:
        return runner.run([replace(task, template=r.placed.points, template_normals=r.normals)
                           for task, r in zip(tasks, previous.registrations)], report, label), None
    spectral = [task if s is None or s.points is None else
                replace(task, template=to_frame(s.points), template_normals=s.normals)
                for task, s in zip(tasks, starts)]

    def signature_errors(index: int, registration: Registration) -> float:
        return signature_error(template_signatures, starts[index], registration.placed.points, to_frame)

    registrations, reasons = checked_spectral_fits(spectral, tasks, runner, report, label,
                                                   None if template_signatures is None else signature_errors)
    for task, reason in zip(tasks, reasons):
        if reason:
            report(1.0, f"{task.name}: {reason}")
    taken = ["template" if s is None else "spectral" if s.points is not None and not reason else "closest"
             for s, reason in zip(starts, reasons)]
    return registrations, taken


def _checked_feature_fits(tasks: list[RegistrationTask], start: int, runner: RegistrationRunner, report: Progress,
                          label: str) -> tuple[list[Registration], CorrespondenceSettings, np.ndarray]:
    """(feature matches, **beyond** the thesis) the first round by
    feature matches and by closest points side by side, from the same template. When
    feature matches fit more than features.FALLBACK_SHARE of the shapes worse
    (features.worse_fits: the template collapsed onto part of them), the collection is
    matched by closest points, and the result is the closest-point correspondence exactly;
    else by feature matches, as without the check. The template's own shape decides nothing
    (it fits itself either way). Returns the round's registrations, the settings of the
    rounds to come and (M,) bool: the shapes feature matches fitted worse."""
    settings = tasks[0].settings
    closest_settings = replace(settings, data_term=replace(settings.data_term, matching="closest"))
    closest_tasks = [replace(task, index=len(tasks) + task.index, name=f"{task.name} (closest points)",
                             settings=closest_settings, template_between=None) for task in tasks]
    both = runner.run(tasks + closest_tasks, report, f"{label}, feature matches checked against closest points")
    by_features, by_closest = both[:len(tasks)], both[len(tasks):]
    worse = worse_fits([r.residual for r in by_features], [r.residual for r in by_closest])
    worse[start] = False
    if keeps_features(worse):
        return by_features, settings, worse
    report(1.0, f"feature matches fit {int(worse.sum())} of {len(tasks)} shapes worse than closest points "
                f"({', '.join(t.name for t, w in zip(tasks, worse) if w)}): closest points for the collection")
    return by_closest, closest_settings, worse


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


def _with_between_share(settings: CorrespondenceSettings, share: float) -> CorrespondenceSettings:
    """`settings` comparing positions between turning lines with `share` of `feature_between`
    (features.agreement_weights)."""
    data_term = settings.data_term
    return replace(settings, data_term=replace(data_term, feature_between=data_term.feature_between * share))


def _template_between(outcome: _Rounds, start: int) -> np.ndarray:
    """(feature matches, **beyond** the thesis; features.py) the template's positions
    between turning lines from the groupwise round on: those of the shape it was made from,
    at its own landmarks (its registration onto itself in the first round). The population's
    mean at the first round's matches carries that round's bias (it compares sides only),
    and measured worse (docs/results.md, Correspondence)."""
    return outcome.results[start].between
