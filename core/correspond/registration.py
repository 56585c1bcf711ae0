"""One registration: the template's landmarks deformed onto one target surface by
non-rigid ICP with stiffness relaxation (thesis §4.2, Alg. 3; Amberg et al. 2007).

`register` takes one `RegistrationProblem` (its fixed inputs) and runs:

- `_relax`: the stiffness schedule, α from stiff to soft (Alg. 3's outer loop);
- `_iterate_at`: the iterations at one α until the energy settles (the inner loop);
- `_solve_step`: one affine-graph solve (4.31, core/geometry/affine_graph.py) of the
  data terms' pulls and the stiffness, and the move of the points.

The data terms (data_terms.py) each say what they pull where: forward matches v_n(i)
(closest, normal-compatible target point of every template point), backward matches m(j)
(closest template point of every target landmark, weighted by λ), optional known pairs
(`Anchors`). At the end every point is placed on the target surface (or snapped to a
vertex). With `matching="features"` (beyond the thesis, features.py) both kinds of match
are nearest points in a joint space of position and surface features instead.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import (AffineSolver, SurfacePoints, TargetSurface, apply_affines, data_blocks, stiffness_energy,
                        transform_normals)
from ..base.progress import CancelCheck
from .data_terms import (AnchorTerm, Anchors, BidirectionalTerm, ClosestMatches, DataTerm, FeatureMatches, ForwardTerm,
                         Pulls, closest_target_points)
from .features import FeatureMatcher, point_features, uses_between, uses_features
from .settings import CorrespondenceSettings, DataTermSettings

__all__ = ["Anchors", "Registration", "RegistrationProblem", "fit_residual", "register"]


@dataclass(frozen=True)
class Registration:
    """One template → target registration (Alg. 3), in the frame of the given points."""

    placed: SurfacePoints  # final template points on the target (surface or vertex)
    normals: np.ndarray  # (L, 3) target normals at the placed points
    deformed: np.ndarray  # (L, 3) template points after the last ICP step, before placement
    residual: float  # √(E_D / Σ weights) of the final matches, in the frame's units
    iterations: int
    energies: np.ndarray  # objective after every iteration
    deformed_normals: np.ndarray | None = None  # (L, 3) template normals after the last step (None: no normals)
    between: np.ndarray | None = None  # (L,) the target's positions between turning lines at the placed points (features.py)
    regions: np.ndarray | None = None  # (L,) the target's region at the placed points (features.merged_regions)


@dataclass(frozen=True)
class RegistrationProblem:
    """The fixed inputs of one registration, all in one frame (see `correspond` for the
    frame used). Arrays are checked and held as float64 (`__post_init__`).

    `template` (L, 3): the points the affines act on; `edges`: their landmark graph (the
    stiffness term); `target`: the surface registered to, and `target_landmarks` (T, 3) on
    it (the bidirectional term). `template_normals` / `target_landmark_normals` (L, 3) /
    (T, 3): normals of both (None: matches ignore normals). `anchors`: known pairs.
    `initial_points` (L, 3): a warm start, where the template points begin (e.g. an earlier
    registration's `deformed`); the affines still act on `template`. `initial_normals`
    (L, 3): the template's normals at that start (the earlier registration's `normals`),
    which feature-space matches compare from the first iteration on. `template_between`
    (L,): the template points' positions between turning lines (turning.py; groupwise: the
    template shape's own), compared by feature matches when `feature_between` > 0.
    `plain_points` (L,) bool: template points feature matches compare by position and
    normal only (features.merged_regions). The last two are checked, and used, only when
    feature matches run (`matching="features"` and template normals given)."""

    template: np.ndarray
    edges: np.ndarray
    target: TargetSurface
    target_landmarks: np.ndarray
    settings: CorrespondenceSettings = CorrespondenceSettings()
    template_normals: np.ndarray | None = None
    target_landmark_normals: np.ndarray | None = None
    anchors: Anchors | None = None
    initial_points: np.ndarray | None = None
    initial_normals: np.ndarray | None = None
    template_between: np.ndarray | None = None
    plain_points: np.ndarray | None = None

    def __post_init__(self):
        template = np.asarray(self.template, dtype=np.float64)
        self._hold("template", template)
        if self.anchors is not None and (np.asarray(self.anchors.indices) >= len(template)).any():
            raise ValueError(f"anchor indices must be < {len(template)} (the template's point count)")
        if self.template_normals is not None:
            self._hold("template_normals", np.asarray(self.template_normals, dtype=np.float64))
        if self.initial_points is not None:
            self._hold("initial_points", _checked_start(self.initial_points, template.shape, "initial_points"))
        if self.initial_normals is not None:
            self._hold("initial_normals", _checked_start(self.initial_normals, template.shape, "initial_normals",
                                                         beside_normals=self.template_normals is not None))
        if self.uses_features:
            self._check_feature_inputs(len(template))

    def _hold(self, name: str, value) -> None:
        """Set a field of this frozen instance (its checked, converted value)."""
        object.__setattr__(self, name, value)

    def _check_feature_inputs(self, n_points: int) -> None:
        """Check (and hold as arrays) `template_between` when it is compared and `plain_points`."""
        if self.template_between is not None and uses_between(self.settings):
            between = np.asarray(self.template_between, dtype=np.float64)
            if between.shape != (n_points,) or not np.isfinite(between).all():
                raise ValueError(f"template_between must be finite with one value per template point ({n_points}), "
                                 f"got {between.shape}")
            self._hold("template_between", between)
        if self.plain_points is not None:
            plain = np.asarray(self.plain_points)
            if plain.shape != (n_points,) or plain.dtype != bool:
                raise ValueError(f"plain_points must be one bool per template point ({n_points}), got "
                                 f"{plain.shape} {plain.dtype}")
            self._hold("plain_points", plain)

    @property
    def uses_features(self) -> bool:
        """Whether matches are feature-space matches (`matching="features"` and template normals given)."""
        return uses_features(self.settings) and self.template_normals is not None

    @property
    def compared_between(self) -> np.ndarray | None:
        """The template's positions between turning lines when feature matches compare them, else None."""
        if not self.uses_features or self.template_between is None or not uses_between(self.settings):
            return None
        return self.template_between


def _checked_start(values, shape: tuple, name: str, beside_normals: bool | None = None) -> np.ndarray:
    """A warm start's `values` as float64: finite, with the template's `shape`; warm-start
    normals only beside the template's normals (`beside_normals`: whether those are given)."""
    values = np.asarray(values, dtype=np.float64)
    if beside_normals is False or values.shape != shape or not np.isfinite(values).all():
        also = "" if beside_normals is None else ", beside template_normals"
        raise ValueError(f"{name} must be finite with the template's shape {shape}{also}, got {values.shape}")
    return values


@dataclass
class _Relaxation:
    """Where a registration is: the template's current points and normals, the features
    feature matches compare (None: closest matches), the points and normals the next
    solve's affines act on (`base`: the template, or the current points with
    `update_template`), and the iterations so far with their energies."""

    points: np.ndarray
    normals: np.ndarray | None
    features: np.ndarray | None
    base: np.ndarray
    base_normals: np.ndarray | None
    energies: list[float] = field(default_factory=list)
    iteration: int = 0
    previous: float = np.inf  # the last iteration's energy


def register(problem: RegistrationProblem, on_iteration: Callable[[int], None] | None = None,
             should_cancel=None) -> Registration:
    """Iterative stiffness relaxation (Alg. 3) of the problem's template onto its target.

    Per iteration: every data term's pulls (data_terms.py: closest target points v_n(i) of
    the current template points, closest current template point m(j) of each target
    landmark u_j, known pairs from `anchors`), one sparse solve (4.31), move the points.
    With `update_template` the next solve starts from the moved points (the thesis's Alg.
    3); otherwise from the original template (Amberg et al.). With feature matches and
    `feature_between` > 0 the result reports the target's positions between turning lines
    at its placed points (`Registration.between`), given a template's or not; with feature
    matches it reports the target's regions there (`Registration.regions`).
    `on_iteration(n)` is called after every iteration. Raises Cancelled between iterations
    once `should_cancel` (None, a callable or an Event-like object; core/progress.py) says
    so."""
    finder = problem.target.tracker()  # closest points with candidate faces kept between iterations
    matcher = None
    if problem.uses_features:
        matcher = FeatureMatcher(problem.target, problem.target_landmarks, problem.target_landmark_normals,
                                 len(problem.template), problem.settings,
                                 with_between=problem.compared_between is not None)
    state = _start(problem)
    _relax(problem, _data_terms(problem, finder, matcher), state, on_iteration,
           CancelCheck(should_cancel, "correspondence"))
    placed = _place(problem.target, state.points, state.normals, problem.settings.data_term, finder)
    residual = fit_residual(placed, problem.target_landmarks)
    placed_normals = problem.target.face_normals[placed.face_index]
    target_between = None if matcher is None else matcher.positions_at(placed.points, placed_normals)
    target_regions = None if matcher is None else matcher.regions_at(placed.points, placed_normals)
    return Registration(placed, placed_normals, state.points, residual, state.iteration, np.asarray(state.energies),
                        state.normals, target_between, target_regions)


def _start(problem: RegistrationProblem) -> _Relaxation:
    """The template where the registration begins (at `initial_points`, with
    `initial_normals`, when given) and, with feature matches, its features."""
    base, base_normals = problem.template, problem.template_normals
    points = (base if problem.initial_points is None else problem.initial_points).copy()
    normals = base_normals if problem.initial_normals is None else problem.initial_normals
    features = None
    if problem.uses_features:
        features = point_features(normals, problem.settings, problem.compared_between)
    return _Relaxation(points, normals, features, base, base_normals)


def _data_terms(problem: RegistrationProblem, finder, matcher: FeatureMatcher | None) -> list[DataTerm]:
    """The problem's data terms, in the order their pulls are stacked: forward matches,
    the bidirectional term (unless λ = 0), the known pairs (if any)."""
    data_term = problem.settings.data_term
    if matcher is None:
        matches = ClosestMatches(problem.target, finder, problem.target_landmarks, problem.target_landmark_normals,
                                 data_term)
    else:
        matches = FeatureMatches(matcher, problem.plain_points, data_term)
    terms: list[DataTerm] = [ForwardTerm(matches)]
    if data_term.bidirectional_weight > 0:
        terms.append(BidirectionalTerm(matches, problem.target_landmarks, data_term.bidirectional_weight))
    if problem.anchors is not None:
        terms.append(AnchorTerm(problem.anchors))
    return terms


def _relax(problem: RegistrationProblem, terms: list[DataTerm], state: _Relaxation,
           on_iteration: Callable[[int], None] | None, cancel: CancelCheck) -> None:
    """Alg. 3's stiffness schedule: iterate at every α from stiff to soft (`_iterate_at`)
    until the schedule or the iteration cap (`max_iterations`) ends. With feature matches
    and no warm-start normals, the template's features are taken again after the stiffest
    α, as that α fitted them."""
    settings = problem.settings
    solver = AffineSolver(problem.edges, len(state.points), settings.stiffness.gamma)
    for alpha_index, alpha in enumerate(settings.alphas):
        if state.features is not None and alpha_index == 1 and problem.initial_normals is None:
            state.features = point_features(state.normals, settings, problem.compared_between)
        _iterate_at(alpha, problem, terms, state, solver, on_iteration, cancel)
        if state.iteration >= settings.iterations.max_iterations:
            break


def _iterate_at(alpha: float, problem: RegistrationProblem, terms: list[DataTerm], state: _Relaxation,
                solver: AffineSolver, on_iteration: Callable[[int], None] | None, cancel: CancelCheck) -> None:
    """ICP iterations at one α (Alg. 3's inner loop): pulls of every data term, one solve,
    until the energy changes by at most `tolerance` (relative), `max_iterations_per_alpha`
    iterations, or the cap over the whole schedule."""
    limits = problem.settings.iterations
    for _ in range(limits.max_iterations_per_alpha):
        cancel()
        pulls = Pulls.stacked([term.pulls(state.points, state.normals, state.features) for term in terms])
        energy = _solve_step(alpha, pulls, problem, state, solver)
        state.iteration += 1
        if on_iteration is not None:
            on_iteration(state.iteration)
        # relative change, with a floor far below any real fit (frame units: unit RMS radius)
        converged = np.isfinite(state.previous) and (
            abs(state.previous - energy) <= limits.tolerance * state.previous + 1e-12 * len(pulls.rows))
        state.previous = energy
        if state.iteration >= limits.max_iterations or converged:
            break


def _solve_step(alpha: float, pulls: Pulls, problem: RegistrationProblem, state: _Relaxation,
                solver: AffineSolver) -> float:
    """One solve of (4.31): the affines that best meet the pulls at stiffness α; the points
    (and normals) move by them. Returns the energy E = E_D + α² E_s at the new points."""
    settings = problem.settings
    if settings.iterations.update_template:  # Alg. 3: affines act on the current points
        state.base, state.base_normals = state.points, state.normals
    blocks, rhs = data_blocks(state.base, pulls.rows, pulls.goals, pulls.weights, len(state.points))
    affines = solver.solve(alpha, blocks, rhs, settings.iterations.ridge)
    moved = apply_affines(affines, state.base)
    data = float((pulls.weights * ((moved[pulls.rows] - pulls.goals) ** 2).sum(axis=1)).sum())
    energy = data + alpha**2 * stiffness_energy(affines, problem.edges, settings.stiffness.gamma)
    state.energies.append(energy)
    if state.normals is not None:
        state.normals = transform_normals(affines, state.base_normals)
    state.points = moved
    return energy


def _place(target: TargetSurface, points: np.ndarray, normals: np.ndarray | None,
           settings: DataTermSettings, finder=None) -> SurfacePoints:
    """Final placement of the template points on the target (Alg. 3, line 11): the closest
    surface point (compatible, if normals are used and one exists), or the nearest vertex."""
    matches, _ = closest_target_points(target, points, normals, settings, finder)
    missing = ~np.isfinite(matches.distance)
    if missing.any():
        plain = target.closest_vertices(points[missing]) if settings.snap_to_vertices else target.closest(points[missing])
        for array, value in zip((matches.points, matches.face_index, matches.barycentric, matches.distance),
                                (plain.points, plain.face_index, plain.barycentric, plain.distance)):
            array[missing] = value
    return matches


def fit_residual(placed: SurfacePoints, target_landmarks: np.ndarray) -> float:
    """RMS of the bidirectional data term at the end (unit weights): template points to the
    surface before placement, and target landmarks to the nearest placed point (coverage;
    counted even when λ = 0 so a template covering half the target is never hidden)."""
    coverage, _ = cKDTree(placed.points).query(target_landmarks)
    squares = np.r_[placed.distance**2, coverage**2]
    return float(np.sqrt(squares.mean()))
