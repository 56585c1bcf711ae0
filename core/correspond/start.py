"""Where each shape's registration starts (**beyond** the thesis;
`CorrespondenceSettings.data_term.initialisation`).

"closest" (the thesis): the template as it is; non-rigid ICP finds closest points from
there. "spectral": the template's landmarks carried to every shape by an intrinsic map
(functional_map.py) and non-rigid ICP run from there, its affines acting on those start
points so the stiffness keeps the start's layout (a limb that moved stays matched to the
limb). A shape whose spectrum is not trusted, whose spectral fit is clearly worse than the
closest-point fit, or whose spectral landmarks do not match the template's wave-kernel
signatures clearly better than the closest-point ones, is registered from the
closest-point start instead, and the per-shape message says so. A shape for which no map
from the template passes the tests of orientation and facing is reached through shapes
that were (`relayed_starts`: consistency over the collection; a pose the template's map
cannot bridge is often bridged in two steps). "auto": one of the two
for the whole collection, from how its shapes differ (`pose_evidence`, `chosen_start`):
the intrinsic start where they differ in pose, closest points where they differ in
proportion."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import chamfer_distance
from ..geometry.spectral import SpectrumError, laplace_beltrami_spectrum
from ..base.progress import Progress, sub_range
from .functional_map import MIN_PART_SHARE, SpectralShape, SpectralStart, landmark_signatures, spectral_shape, spectral_start
from .pool import RegistrationRunner, RegistrationTask
from .registration import Registration

__all__ = ["relayed_starts", "RELAY_TRIES", "RELAY_ROUNDS", "pose_evidence", "PoseEvidence", "chosen_start", "POSE_RATIO", "EVIDENCE_FUNCTIONS", "spectral_starts", "checked_spectral_fits", "signature_error", "SPECTRAL_FIT_MARGIN",
           "SPECTRAL_SIGNATURE_MARGIN"]

#: a spectral start whose registration's residual is more than this times the closest-point
#: registration's is not trusted (the intrinsic map put part of the template on the wrong part)
SPECTRAL_FIT_MARGIN = 1.5
#: nor one whose landmarks' signatures differ from the template's by more than this times
#: the closest-point registration's: the intrinsic map must match the intrinsic geometry
#: clearly better to overrule the closest points (a body of revolution fits its signatures
#: alike at every turn about its axis, so the spectrum cannot say which turn is right)
SPECTRAL_SIGNATURE_MARGIN = 0.9


#: a shape tries at most RELAY_TRIES shapes with a start per round (the most alike by
#: their spectra first), for at most RELAY_ROUNDS rounds (a shape reached in one round can
#: relay in the next)
RELAY_TRIES = 2
RELAY_ROUNDS = 3


@dataclass(frozen=True)
class _StartItem:
    """One shape's share of `spectral_starts` (picklable, for a worker)."""

    name: str
    template: SpectralShape | None  # None: the template's own spectrum was not trusted
    template_points: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    template_problem: str = ""
    shared_frame: bool = True  # the shape lies in the template's frame as the collection does (its facing is evidence)


def _start_on_shape(item: _StartItem) -> SpectralStart:
    if item.template is None:
        return SpectralStart(None, f"closest-point start: the template's {item.template_problem}")
    try:
        shape = spectral_shape(item.vertices, item.faces)
    except SpectrumError as exc:
        return SpectralStart(None, f"closest-point start: spectrum not trusted ({exc})")
    return spectral_start(item.template, item.template_points, shape, shared_frame=item.shared_frame)


@dataclass(frozen=True)
class _RelayItem:
    """One try of `relayed_starts` (picklable, for a worker): the map to shape `index`
    through the shape named `via_name`."""

    name: str
    index: int
    template: SpectralShape
    template_points: np.ndarray
    via_name: str
    via: SpectralShape
    via_map: np.ndarray
    shape: SpectralShape
    shared_frame: bool


@dataclass(frozen=True)
class _LastItem:
    """One shape's last resort (picklable, for a worker)."""

    name: str
    template: SpectralShape
    template_points: np.ndarray
    shape: SpectralShape


def _last_resort(item: _LastItem) -> SpectralStart:
    return spectral_start(item.template, item.template_points, item.shape, by_triangles=True)


def _relay_on_shape(item: _RelayItem) -> SpectralStart:
    return spectral_start(item.template, item.template_points, item.shape, shared_frame=item.shared_frame,
                          via=(item.via_name, item.via, item.via_map))


def _spectral_distance(a: SpectralShape, b: SpectralShape) -> float:
    """Mean |log ratio| of the two shapes' first non-zero eigenvalues (unit area; shape DNA,
    as `pose_evidence`): small for the same body in a similar pose."""
    k = min(EVIDENCE_FUNCTIONS + 1, len(a.spectrum.values), len(b.spectrum.values))
    ratio = np.maximum(a.spectrum.values[1:k], 1e-12) / np.maximum(b.spectrum.values[1:k], 1e-12)
    return float(np.mean(np.abs(np.log(ratio))))


def relayed_starts(names: Sequence[str], template: SpectralShape, template_points: np.ndarray,
                   starts: list[SpectralStart | None], runner: RegistrationRunner, report: Progress,
                   in_frame: Sequence[bool]) -> list[SpectralStart | None]:
    """`starts` (per shape, as `spectral_starts`) with shapes reached through shapes that
    have a start (`functional_map.relayed_map`): every shape without a start, and every
    shape whose facing is no evidence (`in_frame` False: its direct map may be the half
    turn of the right one, which keeps the orientation). Each tries the next RELAY_TRIES
    shapes with a start it has not tried, the most alike by their spectra first (reached
    in the frame before those reached without it); rounds repeat while a shape without a
    start is reached, at most RELAY_ROUNDS. Of a shape's direct and relayed maps that pass,
    the one with the highest orientation score is kept (the right map's operators commute
    best: a half turn is no exact isometry of a body). A shape still without a start gets
    the last resort (`functional_map.MIN_TRIANGLE_SHARE`: the triangles' orientation,
    without the facing) or keeps its message, with the relays tried."""
    starts, tried = list(starts), [[] for _ in names]
    has_start = lambda i: starts[i] is not None and starts[i].points is not None and starts[i].c is not None  # noqa: E731
    for round_index in range(RELAY_ROUNDS):
        reached = [i for i in range(len(names)) if has_start(i)]
        waiting = [i for i, s in enumerate(starts) if s is not None and s.spectral is not None
                   and (not has_start(i) or (not in_frame[i] and round_index == 0))]
        items = []
        for index in waiting:
            order = sorted((u for u in reached if u != index and names[u] not in tried[index]),
                           key=lambda u: (not in_frame[u], _spectral_distance(starts[u].spectral,
                                                                               starts[index].spectral)))
            for via in order[:RELAY_TRIES]:
                tried[index].append(names[via])
                items.append(_RelayItem(names[index], index, template, template_points, names[via], starts[via].spectral,
                                        starts[via].c, starts[index].spectral, bool(in_frame[index])))
        if not items:
            break
        outcomes = runner.map(_relay_on_shape, items, report, lambda i: f"intrinsic map to {items[i].name} through "
                                                                          f"{items[i].via_name}")
        newly = 0
        for item, outcome in zip(items, outcomes):
            current = starts[item.index]
            if outcome.points is not None and (current.points is None or outcome.orientation > current.orientation):
                newly += current.points is None
                starts[item.index] = replace(outcome, spectral=current.spectral)
        if not newly:
            break
    last = [i for i, start in enumerate(starts) if start is not None and start.points is None
            and start.spectral is not None]
    if last:  # the test used before the operator's, where no map passes the operator's
        items = [_LastItem(names[i], template, template_points, starts[i].spectral) for i in last]
        for index, outcome in zip(last, runner.map(_last_resort, items, report,
                                                   lambda i: f"intrinsic map to {items[i].name}, last resort")):
            if outcome.points is not None:
                starts[index] = replace(outcome, message=f"{outcome.message}: {starts[index].message}",
                                        spectral=starts[index].spectral)
    for index, start in enumerate(starts):
        if start is not None and start.points is None:
            relays = f"; no relay through {', '.join(tried[index])} passed either" if tried[index] else ""
            said = start.message if start.message.startswith("closest-point start") else \
                f"closest-point start: {start.message}"
            starts[index] = replace(start, message=said + relays)
    return starts


def spectral_starts(names: Sequence[str], surfaces: Sequence, template_index: int, template_points: np.ndarray,
                    runner: RegistrationRunner, report: Progress, in_frame: Sequence[bool] | None = None
                    ) -> tuple[list[SpectralStart | None], np.ndarray | None]:
    """Per shape (None for the template's own shape, which starts as itself): where its
    landmarks start by the intrinsic map from the template shape (functional_map.py), or
    why not; and the signatures of the template's landmarks (None: its spectrum is not
    trusted). `surfaces`: per shape, the mesh registered against (a dense shape's proxy).
    `in_frame`: per shape, whether it lies in the frame as the collection does, so that a
    map's facing is evidence (default all; none when the template's own is not)."""
    template_mesh = surfaces[template_index].mesh
    try:
        template, problem = spectral_shape(template_mesh.vertices, template_mesh.faces), ""
    except SpectrumError as exc:
        template, problem = None, f"spectrum is not trusted ({exc})"
    in_frame = [True] * len(names) if in_frame is None else [bool(f) and bool(in_frame[template_index]) for f in in_frame]
    items = [_StartItem(name, template, template_points, surface.mesh.vertices, surface.mesh.faces, problem,
                        in_frame[index])
             for index, (name, surface) in enumerate(zip(names, surfaces)) if index != template_index]
    others = [index for index in range(len(names)) if index != template_index]
    mapped = runner.map(_start_on_shape, items, sub_range(report, 0.0, 0.6),
                        lambda i: f"intrinsic map to {items[i].name}")
    starts: list[SpectralStart | None] = [None] * len(names)
    for index, outcome in zip(others, mapped):
        starts[index] = outcome
    if template is not None:
        starts = relayed_starts(names, template, template_points, starts, runner, sub_range(report, 0.6, 1.0),
                                in_frame)
    return starts, None if template is None else landmark_signatures(template, template_points)


def signature_error(template_signatures: np.ndarray, start: SpectralStart, points: np.ndarray, to_frame) -> float:
    """Mean squared difference between the template landmarks' signatures and the shape's
    at `points` (its landmarks in the registration frame; the shape's signature read at
    the nearest of its vertices, which `to_frame` takes to that frame)."""
    _, nearest = cKDTree(to_frame(start.signature_vertices)).query(points)
    return float(((template_signatures - start.signature[nearest]) ** 2).sum(axis=1).mean())


def checked_spectral_fits(spectral: list[RegistrationTask], closest: list[RegistrationTask], runner: RegistrationRunner,
                          report: Progress, label: str, signature_errors=None) -> tuple[list[Registration], list[str]]:
    """Register every shape from its spectral start and from the closest-point start side
    by side (`spectral[i]` and `closest[i]` are the same shape; a shape without a spectral
    start has its closest task in both places and runs once). A spectral fit whose
    residual is more than SPECTRAL_FIT_MARGIN times the closest-point fit's, or (with
    `signature_errors(i, registration)`: the signature error of shape i's landmarks) whose
    signatures do not match at least 1 / SPECTRAL_SIGNATURE_MARGIN times better, is
    replaced by it. Returns the registrations and, per shape, "" or why it fell back."""
    differs = [s is not c for s, c in zip(spectral, closest)]
    extra = [replace(task, index=len(spectral) + k, name=f"{task.name} (closest-point start)")
             for k, task in enumerate(t for t, d in zip(closest, differs) if d)]
    both = runner.run(list(spectral) + extra, report, f"{label}, spectral starts checked against closest points")
    registrations, reasons = list(both[:len(spectral)]), [""] * len(spectral)
    by_closest = iter(both[len(spectral):])
    for index, checked in enumerate(differs):
        if not checked:
            continue
        alternative = next(by_closest)
        if registrations[index].residual > SPECTRAL_FIT_MARGIN * alternative.residual:
            ratio = registrations[index].residual / alternative.residual
            reasons[index] = f"closest-point start: the spectral start fit {ratio:.1f}× worse"
        elif signature_errors is not None:
            by_spectrum, by_closest_points = (signature_errors(index, r) for r in (registrations[index], alternative))
            if by_spectrum > SPECTRAL_SIGNATURE_MARGIN * by_closest_points:
                reasons[index] = (f"closest-point start: the spectral start does not match the intrinsic geometry "
                                  f"clearly better (signature error {by_spectrum:.2f} against {by_closest_points:.2f})")
        if reasons[index]:
            registrations[index] = alternative
    return registrations, reasons


#: eigenvalues (after the constant one) compared by `pose_evidence`
EVIDENCE_FUNCTIONS = 12


@dataclass(frozen=True)
class PoseEvidence:
    """What a collection says about how its shapes differ, each against the template shape.

    intrinsic: (M,) mean |log ratio| of the first EVIDENCE_FUNCTIONS non-zero
      Laplace–Beltrami eigenvalues of the unit-area surfaces (shape DNA, Reuter et al.
      2006): bending without stretching leaves it near 0, a change of proportion does not;
      NaN where the spectrum is not trusted (0 for the template).
    extrinsic: (M,) RMS symmetric Chamfer distance of the prepared landmark clouds over the
      template cloud's RMS radius: how far apart the shapes lie in space after Prepare.
    degenerate: share of the template's consecutive eigenvalue pairs within 5 % of each
      other (a body of revolution has pairs: its spectrum cannot say which turn is right).
    """

    template: int
    intrinsic: np.ndarray
    extrinsic: np.ndarray
    degenerate: float

    def summary(self) -> dict:
        others = np.arange(len(self.intrinsic)) != self.template
        intrinsic, extrinsic = self.intrinsic[others], self.extrinsic[others]
        trusted = np.isfinite(intrinsic)
        median_int = float(np.median(intrinsic[trusted])) if trusted.any() else float("nan")
        median_ext = float(np.median(extrinsic))
        return {"intrinsic_median": median_int, "extrinsic_median": median_ext,
                "ratio": median_ext / median_int if median_int > 0 else float("inf"),
                "trusted": int(trusted.sum()), "shapes": int(others.sum()), "degenerate": self.degenerate}

    def describe(self) -> str:
        s = self.summary()
        return (f"intrinsic {s['intrinsic_median']:.3f}, extrinsic {s['extrinsic_median']:.3f}, ratio "
                f"{s['ratio']:.2f}, spectra trusted {s['trusted']} of {s['shapes']}, degenerate {s['degenerate']:.2f}")


def _eigenvalues(mesh) -> np.ndarray | None:
    """The first EVIDENCE_FUNCTIONS non-zero eigenvalues of a mesh (unit area), or None."""
    try:
        spectrum = laplace_beltrami_spectrum(mesh.vertices, mesh.faces, EVIDENCE_FUNCTIONS + 1)
    except SpectrumError:
        return None
    if spectrum.largest_part_share < MIN_PART_SHARE:
        return None
    return spectrum.values[1:]


def pose_evidence(meshes: Sequence, landmark_sets: Sequence[np.ndarray], template_index: int, runner=None,
                  report: Progress | None = None) -> PoseEvidence:
    """`PoseEvidence` of a collection: `meshes` (the surfaces registered against, any frame:
    the spectra are of unit-area surfaces), `landmark_sets` (prepared frame)."""
    if runner is None:
        values = [_eigenvalues(mesh) for mesh in meshes]
    else:
        values = runner.map(_eigenvalues, list(meshes), report, lambda i: f"spectrum of {meshes[i].name}")
    reference = values[template_index]
    intrinsic = np.full(len(meshes), np.nan)
    if reference is not None:
        for index, v in enumerate(values):
            if v is not None:
                intrinsic[index] = float(np.mean(np.abs(np.log(np.maximum(v, 1e-12) / np.maximum(reference, 1e-12)))))
    template = np.asarray(landmark_sets[template_index], dtype=np.float64)
    radius = float(np.sqrt(((template - template.mean(axis=0)) ** 2).sum(axis=1).mean()))
    extrinsic = np.array([np.sqrt(chamfer_distance(template, points)) / radius for points in landmark_sets])
    degenerate = float(np.mean(reference[1:] < 1.05 * reference[:-1])) if reference is not None else float("nan")
    return PoseEvidence(template_index, intrinsic, extrinsic, degenerate)


#: the collection differs in pose when its shapes lie this many times farther apart in
#: space than in their spectra (`PoseEvidence.summary` "ratio", medians over the shapes):
#: bending moves a shape in space but hardly changes its spectrum, a change of proportion
#: changes both alike. The value lies between the ratios of classes that differ in
#: proportion and of classes that differ in pose (bench/start_evidence.py; docs/results.md,
#: "How auto chooses")
POSE_RATIO = 5.0


def chosen_start(evidence: PoseEvidence) -> tuple[str, str]:
    """("spectral" or "closest", why) for a collection, from its `PoseEvidence`: the
    intrinsic start where its shapes differ far more in space than in their spectra
    (POSE_RATIO: they differ in pose), closest points where they differ about as much in
    both (in proportion: an intrinsic map then has no better claim than the surfaces'
    positions) or where most spectra are not trusted (several parts: the start would fall
    back anyway)."""
    s = evidence.summary()
    if s["trusted"] < s["shapes"] / 2:
        return "closest", f"the spectra of {s['shapes'] - s['trusted']} of {s['shapes']} shapes are not trusted"
    said = (f"the shapes lie {s['ratio']:.1f}× farther apart in space ({s['extrinsic_median']:.3f}) than in their "
            f"spectra ({s['intrinsic_median']:.3f}), threshold {POSE_RATIO:g}×")
    return ("spectral" if s["ratio"] > POSE_RATIO else "closest"), said
