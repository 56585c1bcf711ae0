"""Feature-space matches for non-rigid ICP (**beyond** the thesis, opt-in with
`matching="features"` of `CorrespondenceSettings.data_term`).

The thesis's data term (§4.2.2, 4.11) matches every template point to its closest
(normal-compatible) target point. Along a smooth wall every nearby point is equally close,
so landmarks slide for free and the stiffness term slides them to the smoothest map, which
does not put the template's belly on the target's belly. Here a match is the nearest
target point in a joint space of position and surface features (ICP with invariant
features, Sharp, Lucas & Hebert 2002):

    v_n(i) = argmin_y ‖x_i − y‖² + ‖f_i − f(y)‖²,
    f(n) = [w_n · (n_x, n_y, 0),  w_u · tanh(n_z / h)],

x_i the template point, n its unit normal; n_z = n · up (+z after Prepare). The first part
keeps a point on the side of a wall that faces its way by the normal's horizontal direction
(it replaces the compatibility test of `normal_max_angle`; the normal's slope would pull
matches towards equal slope, a different height on every flaring lip); the second, the
saturated up-component, marks where the surface turns from facing down to facing up: a
belly or a neck (n_z = 0 between the two) is a level set of it whatever the shape's
proportions, so matching it lines such features up (the constants below say why each
value; docs/history.md, Correspondence: feature matches, what they measured).

The template point's features are its normals as the first (stiffest, nearly affine) α of
the schedule left them (`register`): a taller target tilts every normal less, and the
near-affine fit carries that over before features are compared (a warm start's
`initial_normals` instead, when given). The target is represented
by its landmarks and area-uniform surface samples (their face normals),
SAMPLES_PER_POINT per template point, in one KD-tree over the joint space; a match is the
closest point on the face of the nearest sample (the samples only choose the face), and
the final placement is the exact closest surface point as before (registration.py).
An iteration drops the matches farther than TRIM × the median match distance
(`kept_matches`): a part of the template with no counterpart on the target follows its
neighbours instead of being dragged to the nearest surface facing its way.
From the groupwise round on, template regions facing opposite ways whose first-round
matches land in one region of a shape (`merged_regions`, turning.facing_regions) are
compared on that shape by position and normal only (`FeatureMatcher.forward` /
`backward` with `plain`): there up and down, and the positions between turning lines, name
different parts on the two (a vase whose lip is narrower than its neck).

With `feature_between` > 0 a fifth feature, w_b · g, compares where a point lies between
the turning lines of its region (turning.py), from the groupwise round on. The first round
compares sides only and reports every shape's g at its placed points; the template then
keeps the g of the shape it was made from, at that shape's own landmarks (its own belly
and neck, not the population's mean at matches the first round biased), and every shape
compares it with the weight its agreement earned (`agreement_weights`): a shape whose
turning lines are not the template's (a vase without a neck; an airplane, whose lines run
round a fuselage or a wing however Prepare stood it) is matched without it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import TargetSurface, closest_points_on_triangles, nearest_facing_alike
from ..meshes.mesh import Mesh
from .settings import CorrespondenceSettings
from .turning import MAX_ANGLE, NO_LINE, facing_regions, position_between_turning_lines, positions_and_regions

__all__ = ["point_features", "uses_between", "carry_positions", "uses_features", "agreement_weights",
           "checks_fit", "worse_fits", "keeps_features", "kept_matches", "checks_regions", "merged_regions",
           "FeatureMatcher"]

#: seed of the target's surface samples (fixed: a registration is deterministic)
SAMPLE_SEED = 0
#: w_n, weight of the normal's horizontal direction: two points whose normals differ by
#: 60° are as far apart as points w_n apart on a wall
NORMAL_WEIGHT = 0.5
#: w_u, weight of the saturated up-component tanh(n_z / h) (+z is up after Prepare)
UP_WEIGHT = 1.0
#: h: n_z well below it counts as facing sideways, well above as up; small, so the feature
#: is nearly the side of the turning line a point lies on and a belly's gentle slopes do not
#: pull matches towards equal slope
UP_WIDTH = 0.01
#: an iteration drops the matches farther than this many times the median match distance
#: (trimmed ICP, **beyond** the thesis): a template part with no counterpart on the target
#: (a neck on a vase without one, a handle) follows its neighbours through the stiffness
#: term instead of being dragged to the nearest surface facing its way
TRIM = 10.0
#: area-uniform target surface samples per template point; they choose the face a match
#: lies on (the match is that face's closest point)
SAMPLES_PER_POINT = 20
#: the fit check (`worse_fits`, `keeps_features`): above this share of shapes fitted worse,
#: the collection is matched by closest points; one collapse in 10 or more shapes is left
#: to the outlier flags, more say the class's walls contradict the features
FALLBACK_SHARE = 0.1
#: a shape whose positions between turning lines differ from the template's by at most
#: this on average (at the first round's matches) compares them with the full weight w_b,
#: by `NO_AGREEMENT` or more not at all, linearly between. Positions of unrelated structures
#: differ by 1/3 on average (two independent uniform values); after the first round shapes
#: of one turned class stay below 0.15, most real-class shapes are above 0.2
#: (docs/history.md, Correspondence: feature matches).
FULL_AGREEMENT = 0.1
NO_AGREEMENT = 0.2
#: feature matches fit a shape worse when their residual exceeds the closest-point fit's by
#: more than this fraction (`worse_fits`). Lining features up costs some distance (about a
#: fifth at most on the procedural vases); a template collapsed onto part of a shape costs
#: more, from 1.4 × up (Blender mugs, PSB cups; docs/history.md, Correspondence: feature matches)
FIT_TOLERANCE = 0.25
#: a template region counts in `merged_regions` when it holds at least this share of the
#: template's points (smaller ones are noise of a near-vertical wall or a rim's edge)
MIN_REGION_SHARE = 0.02
#: the joint-space columns a plain match compares: the normal's (features.point_features)
NORMAL_COLUMNS = 3
#: label of a point whose region is unknown (no sample facing alike near it)
NO_REGION = -1


def uses_features(settings: CorrespondenceSettings) -> bool:
    """Whether the data term compares features (`matching="features"`)."""
    return settings.data_term.matching == "features"


def point_features(normals: np.ndarray, settings: CorrespondenceSettings, between: np.ndarray | None = None) -> np.ndarray:
    """f of the module docstring for (n, 3) normals (normalised here; a zero normal gives
    zero features): (n, 4) = [w_n · (n_x, n_y, 0), w_u · tanh(n_z / h)], and when
    `between` (n,) is given a fifth column w_b · g: the points' positions between turning
    lines (turning.py; w_b = `feature_between`)."""
    normals = np.asarray(normals, dtype=np.float64)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    unit = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    up = np.tanh(unit[:, 2] / UP_WIDTH)
    columns = [NORMAL_WEIGHT * unit * np.array([1.0, 1.0, 0.0]), UP_WEIGHT * up[:, None]]
    if between is not None:
        if np.shape(between) != (len(normals),):
            raise ValueError(f"between must hold one position per normal ({len(normals)}), got {np.shape(between)}")
        columns.append(settings.data_term.feature_between * np.asarray(between, dtype=np.float64)[:, None])
    return np.hstack(columns)


def agreement_weights(template_between: np.ndarray, shape_between: list[np.ndarray]) -> np.ndarray:
    """Per shape, the share in [0, 1] of w_b it compares positions between turning lines
    with: 1 when its positions g at its matches (n,) differ from the template's (n,) by at
    most `FULL_AGREEMENT` on average, 0 from `NO_AGREEMENT` on, linear between."""
    template_between = np.asarray(template_between, dtype=np.float64)
    difference = np.array([np.abs(np.asarray(g, dtype=np.float64) - template_between).mean() for g in shape_between])
    return np.clip((NO_AGREEMENT - difference) / (NO_AGREEMENT - FULL_AGREEMENT), 0.0, 1.0)


def checks_fit(settings: CorrespondenceSettings) -> bool:
    """Whether the first round checks feature matches against closest points: whenever
    they run (groupwise.py `_checked_feature_fits`)."""
    return uses_features(settings)


def worse_fits(feature_residuals: np.ndarray, closest_residuals: np.ndarray) -> np.ndarray:
    """(M,) bool: the shapes that feature matches fit worse than closest points do, i.e.
    whose data-term residual (registration.py `fit_residual`, the same template and frame)
    is larger by more than FIT_TOLERANCE (residuals within 1e-9, a shape on itself, are
    equal). Where the features contradict the geometry (walls leaning out on the template
    and in on the shape: Blender mugs, PSB cups) the template collapses onto part of the
    surface and the residual grows; where they line features up, the fit is usually closer
    than by closest points (procedural vases and PSB Airplane, Fish and Vase after the first
    round: 0.6-1.0 ×)."""
    feature_residuals = np.asarray(feature_residuals, dtype=np.float64)
    closest_residuals = np.asarray(closest_residuals, dtype=np.float64)
    if feature_residuals.shape != closest_residuals.shape:
        raise ValueError(f"one residual per shape from each data term, got {feature_residuals.shape} and "
                         f"{closest_residuals.shape}")
    return feature_residuals > (1.0 + FIT_TOLERANCE) * closest_residuals + 1e-9  # a shape on itself: both 0


def keeps_features(worse: np.ndarray, fallback_share: float = FALLBACK_SHARE) -> bool:
    """Whether a collection stays with feature matches after the fit check: unless more than
    `fallback_share` of its shapes are fitted worse (`worse`, from `worse_fits`), when the
    whole collection is matched by closest points. Empty `worse` (not checked: files
    written before the check) keeps them."""
    worse = np.asarray(worse, dtype=bool)
    return not (len(worse) and worse.mean() > fallback_share)


def kept_matches(distance: np.ndarray, trim: float = TRIM) -> np.ndarray:
    """1.0 for every match at most `trim` × the median match distance away, 0.0 beyond
    (TRIM; trimmed ICP); all 1 when trim is 0. Distances are in the registration
    frame (unit scale), so a median of 0 (a shape on itself) still keeps matches within 1e-9."""
    distance = np.asarray(distance, dtype=np.float64)
    if trim <= 0 or len(distance) == 0:
        return np.ones(len(distance))
    finite = distance[np.isfinite(distance)]
    limit = trim * max(float(np.median(finite)) if len(finite) else 0.0, 1e-9)
    return (distance <= limit).astype(np.float64)


def checks_regions(settings: CorrespondenceSettings) -> bool:
    """Whether template regions that merge on a shape are looked for (`merged_regions`):
    whenever feature matches run."""
    return uses_features(settings)


def merged_regions(template_regions: np.ndarray, template_normals: np.ndarray,
                   shape_regions: np.ndarray) -> np.ndarray:
    """(L,) bool: the template points whose region merges with a region facing the other way
    on a shape, so feature matches compare them plainly there (position and normal
    direction).

    `template_regions` (L,): each template point's region on the template's own surface
    (turning.facing_regions); `template_normals` (L, 3) its normals; `shape_regions` (L,):
    the region of the shape at the template point's first-round match (NO_REGION unknown).
    Each template region holding at least MIN_REGION_SHARE of the points goes where most of
    its matches lie; when two of them facing opposite ways land in the same region of the
    shape, the shape has one region where the template has two (a vase whose lip is
    narrower than its neck: belly to rim faces up in one piece, where the template's neck
    splits it into a wall facing up and one facing down). Up and down, and the positions
    between turning lines, then mean different parts on the two, and matching them drags
    the template's lines onto whatever line the shape has."""
    template_regions = np.asarray(template_regions)
    shape_regions = np.asarray(shape_regions)
    faces_up = np.asarray(template_normals, dtype=np.float64)[:, 2] > 0
    if template_regions.shape != shape_regions.shape or faces_up.shape != template_regions.shape:
        raise ValueError(f"one region per template point on both, and one normal each, got {template_regions.shape}, "
                         f"{shape_regions.shape} and {np.shape(template_normals)}")
    labels, counts = np.unique(template_regions, return_counts=True)
    landing: dict[int, list[tuple[int, bool]]] = {}
    for label in labels[counts >= MIN_REGION_SHARE * len(template_regions)]:
        members = template_regions == label
        found, votes = np.unique(shape_regions[members], return_counts=True)
        target = found[np.argmax(votes)]
        if target != NO_REGION:
            landing.setdefault(int(target), []).append((int(label), bool(faces_up[members].mean() > 0.5)))
    plain = np.zeros(len(template_regions), dtype=bool)
    for sources in landing.values():
        if len({up for _, up in sources}) > 1:
            plain |= np.isin(template_regions, [label for label, _ in sources])
    return plain


def uses_between(settings: CorrespondenceSettings) -> bool:
    """Whether feature matches compare positions between turning lines (`feature_between` > 0)."""
    return uses_features(settings) and settings.data_term.feature_between > 0


def carry_positions(between: np.ndarray, points: np.ndarray, normals: np.ndarray, to_points: np.ndarray,
                    to_normals: np.ndarray) -> np.ndarray:
    """g at `to_points` (unit normals `to_normals`): that of the nearest of `points` (unit
    `normals`) facing alike as turning.py's graph joins points (`geometry.nearest_facing_alike`),
    so a point on one face of a thin wall never takes the other face's; NO_LINE when none
    of its nearest does."""
    index, distance = nearest_facing_alike(points, normals, to_points, to_normals, np.cos(np.radians(MAX_ANGLE)))
    return np.where(np.isfinite(distance), np.asarray(between)[index], NO_LINE)


def _turning_structure(points: np.ndarray, normals: np.ndarray, between: bool, regions: bool):
    """(positions between turning lines or None, facing regions or None) of the points, as
    asked, from one graph when both are (turning.py)."""
    if between and regions:
        return positions_and_regions(points, normals)
    return (position_between_turning_lines(points, normals) if between else None,
            facing_regions(points, normals) if regions else None)


class FeatureMatcher:
    """One target's side of the feature-aware data term: its surface samples and
    landmarks in the joint space of position and features (module docstring).

    With `feature_between` > 0 the target's positions between turning lines (turning.py)
    are computed on all of these points (`self.between`); they enter the joint space only
    `with_between` (when the template has positions of its own to compare)."""

    def __init__(self, target: TargetSurface, target_landmarks: np.ndarray, target_landmark_normals: np.ndarray | None,
                 n_template_points: int, settings: CorrespondenceSettings, with_between: bool = False):
        count = max(1, SAMPLES_PER_POINT * n_template_points)
        samples = Mesh(target.vertices, target.faces).sample_surface(count, np.random.default_rng(SAMPLE_SEED))
        self.landmarks = np.asarray(target_landmarks, dtype=np.float64)
        self.triangles = target.triangles
        sample_normals = target.face_normals[samples.face_index]
        if target_landmark_normals is not None:  # the landmarks are surface points too: a shape matches itself exactly
            self.sample_points = np.vstack([self.landmarks, samples.points])
            self.sample_faces = np.r_[target.closest(self.landmarks).face_index, samples.face_index]
            self.sample_normals = np.vstack([np.asarray(target_landmark_normals, dtype=np.float64), sample_normals])
        else:  # landmarks without normals: zero normal features, the nearest sample's position between lines
            self.sample_points, self.sample_faces, self.sample_normals = samples.points, samples.face_index, sample_normals
        self.between, self.regions = _turning_structure(self.sample_points, self.sample_normals,
                                                        uses_between(settings), checks_regions(settings))
        self._plain_tree = None
        compared = self.between if with_between else None
        self.sample_features = point_features(self.sample_normals, settings, compared)
        if target_landmark_normals is not None:
            self.landmark_features = self.sample_features[:len(self.landmarks)]
        else:
            landmark_between = None if compared is None else compared[cKDTree(samples.points).query(self.landmarks)[1]]
            self.landmark_features = point_features(np.zeros_like(self.landmarks), settings, landmark_between)
        self.tree = cKDTree(np.hstack([self.sample_points, self.sample_features]))

    def positions_at(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray | None:
        """The target's positions between turning lines at its surface points `points`
        (with their normals); None when not computed."""
        if self.between is None:
            return None
        return carry_positions(self.between, self.sample_points, self.sample_normals, points, normals)

    def regions_at(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray | None:
        """The target's region (turning.facing_regions) at its surface points `points` (with
        their normals), that of the nearest sample facing alike (NO_REGION when none of its
        nearest does); None when not computed."""
        if self.regions is None:
            return None
        index, distance = nearest_facing_alike(self.sample_points, self.sample_normals, points, normals,
                                               np.cos(np.radians(MAX_ANGLE)))
        return np.where(np.isfinite(distance), self.regions[index], NO_REGION)

    def _plain(self) -> cKDTree:
        """The samples in the plain joint space (position and the normal's columns), built
        on first use."""
        if self._plain_tree is None:
            self._plain_tree = cKDTree(np.hstack([self.sample_points, self.sample_features[:, :NORMAL_COLUMNS]]))
        return self._plain_tree

    def forward(self, points: np.ndarray, features: np.ndarray,
                plain: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """v_n(i): the closest point to every template point (`points`, its `features`)
        on the face of the target sample nearest to it in the joint space (the samples
        choose the face, the face gives the exact point), and the distance to it. The
        points marked `plain` (L,) bool (`merged_regions`) are compared by position and
        normal only."""
        _, nearest = self.tree.query(np.hstack([points, features]))
        if plain is not None and plain.any():
            _, nearest[plain] = self._plain().query(np.hstack([points[plain], features[plain, :NORMAL_COLUMNS]]))
        goals, _ = closest_points_on_triangles(points, self.triangles[self.sample_faces[nearest]])
        return goals, np.linalg.norm(goals - points, axis=1)

    def backward(self, points: np.ndarray, features: np.ndarray,
                 plain: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """m(j): the template point nearest to every target landmark in the joint space,
        and the positional distance between them. With `plain` (L,) bool, the nearest of the
        other template points in the joint space and the nearest plain one by position and
        normal compete by position and normal."""
        query = np.hstack([self.landmarks, self.landmark_features])
        if plain is not None and plain.any():
            return self._backward_with_plain(points, features, plain, query)
        _, nearest = cKDTree(np.hstack([points, features])).query(query)
        return nearest, np.linalg.norm(points[nearest] - self.landmarks, axis=1)

    def _backward_with_plain(self, points, features, plain, query):
        """`backward` when some template points are compared plainly."""
        columns = 3 + NORMAL_COLUMNS  # position and normal
        candidates = []
        for members, width in ((np.flatnonzero(~plain), None), (np.flatnonzero(plain), columns)):
            if len(members):
                space = np.hstack([points[members], features[members]])[:, :width]
                candidates.append(members[cKDTree(space).query(query[:, :width])[1]])
        plain_space = np.hstack([points, features[:, :NORMAL_COLUMNS]])
        gaps = [np.linalg.norm(plain_space[c] - query[:, :columns], axis=1) for c in candidates]
        nearest = candidates[0] if len(candidates) == 1 else np.where(gaps[1] < gaps[0], candidates[1], candidates[0])
        return nearest, np.linalg.norm(points[nearest] - self.landmarks, axis=1)
