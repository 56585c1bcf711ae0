"""Every tunable parameter of the correspondence engine: `CorrespondenceSettings`, one
frozen settings dataclass (core/settings.py: checks itself, travels as one JSON string)
nesting one group per subsystem — stiffness, data term, iterations, outliers.
Files written before the grouping record the options flat; `FIELDS_MOVED` (its table in
core/base/compat.py) reads them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..base.compat import CORRESPONDENCE_MOVED, CORRESPONDENCE_REMOVED, DATA_TERM_ADDED_LATER
from ..base.settings import Settings, SettingsError, group, option
from ..meshes.simplify import REGISTRATION_PROXY_FACES

__all__ = ["CorrespondenceSettings", "StiffnessSettings", "DataTermSettings", "IterationSettings", "OutlierSettings",
           "FEATURE_STIFFNESS", "MATCHING_METHODS", "INITIALISATIONS"]

#: `data_term.matching`: the data term's matches (registration.py, features.py)
MATCHING_METHODS = ("closest", "features")

#: with feature matches the stiffness schedule ends at this fraction of `stiffness.alpha_end`: the
#: features pull only the points between the template's turning line and the target's, and
#: a softer last α lets the wall around them follow (with closest points a softer end does
#: not help, so the schedule changes only there; docs/history.md, Correspondence: feature matches)
FEATURE_STIFFNESS = 0.4

#: `data_term.initialisation`: where each shape's registration starts (start.py)
INITIALISATIONS = ("auto", "closest", "spectral")


@dataclass(frozen=True)
class StiffnessSettings(Settings):
    """The stiffness term and its schedule (§4.2.4, §4.2.6), thesis defaults (§4.2.8).

    gamma: γ in G = diag(1, 1, 1, γ); weight of the translation part of neighbouring affine
      differences against the linear part (thesis 2).
    k_neighbours: k of the symmetrised k-NN landmark graph of the stiffness term (thesis 6).
    alpha_start, alpha_end, alpha_steps: the stiffness schedule of Alg. 3 (§4.2.6),
      `alpha_steps` values evenly spaced from `alpha_start` down to `alpha_end` (thesis
      100 → 5 for vases and teapots, 100 → 10 for cars). `alpha_steps = 1` uses `alpha_end`
      only (no relaxation). With feature matches the schedule ends lower
      (`CorrespondenceSettings.alphas`, FEATURE_STIFFNESS).
    """

    gamma: float = option(2.0, "γ: weight of the translation part in the stiffness", above=0)
    k_neighbours: int = option(6, "k of the landmark graph of the stiffness term", minimum=1)
    alpha_start: float = option(100.0, "first stiffness α of the schedule (at least alpha_end)")
    alpha_end: float = option(5.0, "last stiffness α of the schedule", above=0)
    alpha_steps: int = option(5, "α values of the schedule", minimum=1)

    def __post_init__(self):
        super().__post_init__()
        if self.alpha_start < self.alpha_end:
            raise SettingsError("alpha_start", f"must be at least alpha_end ({self.alpha_end!r}), got "
                                f"{self.alpha_start!r}")


@dataclass(frozen=True)
class DataTermSettings(Settings):
    """The data term (§4.2.2): which target point each template point is pulled to, which
    template point each target landmark pulls, how matches are weighted, and where the
    registration starts.

    bidirectional_weight: λ, weight of target landmarks pulling their closest template
      point (thesis 1 vases, 0.5 teapots, 0.1 cars: small when meshes have interior parts).
      0 switches the bidirectional term off.
    normal_max_angle: a match only counts between points whose normals differ by at most
      this many degrees; the closest *compatible* target point is used, and a template
      point with none nearby gets weight 0. None: plain closest points (the thesis). Why 60:
      on thin-walled shapes plain closest points put many outer-wall landmarks on the inner
      wall. Needs consistently oriented meshes (intake.py ensures it).
    distance_weights: weight matches by s = 1 / (1 + d), normalised by the largest s (eqs.
      4.12–4.13; d in the registration frame, unit RMS template radius).
    snap_to_vertices: closest points and final placement on target *vertices* (the thesis's
      choice) instead of the closest point on the surface (default: snapping costs accuracy
      on coarse meshes).
    Feature-space matches (**beyond** the thesis, opt-in; features.py, turning.py):
    matching: "closest": the thesis's data term, every template point matched to the
      closest (normal-compatible) target point. "features": to the nearest target point in
      a joint space of position and features (ICP with invariant features, Sharp et al.
      2002; frame units: unit RMS template radius), so matches keep to the side of a thin
      wall that faces their way (`normal_max_angle` is not used) and turning regions — a
      belly, a neck, a shoulder — are pulled onto each other. Closer to the true
      correspondence on turned shapes, but the landmark models it gives are less compact on
      real classes, so it is not the default.
    feature_between: w_b > 0 adds a fifth feature, w_b · g: where a point lies between the
      turning lines of its region (turning.py: 0 on the lower line, 1 on the upper, by
      height), so points on both sides of a line are pulled in proportion. The first round
      compares sides only; from the groupwise round on the template keeps the g of the
      shape it was made from, and each shape compares it with a share of w_b that falls from
      1 to 0 as its first-round g disagrees with the template's by 0.1 to 0.2
      (features.agreement_weights): real classes whose turning lines differ are matched
      without it. 0: off (files written before it record 0).
    The other weights and rules of feature matches are constants of features.py (the
    normal's and the up-component's weights, the up-width, trimmed matches, merged regions,
    surface samples, the fit check against closest points and its fallback share) and
    FEATURE_STIFFNESS: they were research knobs, removed as options
    (`CorrespondenceSettings.FIELDS_REMOVED`; their measurements are in docs/history.md).
    Start (**beyond** the thesis; start.py, functional_map.py):
    initialisation: "auto" (default): the collection chooses one of the two starts below
      from how its shapes differ (start.py `chosen_start`: far more in space than in their
      Laplace–Beltrami spectra is pose, so spectral; else closest), says so for every shape
      and records it in the correspondence (`Correspondence.diagnostics.start`). It took the
      better start on every measured class but PSB cups, where it keeps closest points and
      the intrinsic start wins through one cup Prepare left facing away (docs/results.md).
      "closest" (files written before the option record it, and read so): every shape's
      registration starts from the template as it is (the thesis). "spectral": from the
      template's landmarks carried to the shape by an intrinsic map (Laplace–Beltrami
      eigenfunctions, sign search, orientation, ZoomOut), which bending does not change: for
      classes whose shapes differ in pose (an animal's limbs). Each shape is also registered
      from the closest-point start in the first round; where the spectrum is not trusted
      (parts, a failed solve, no orientation-preserving map), the spectral fit is clearly
      worse or its landmarks match the template's wave-kernel signatures no clearly better
      (start.py), the closest-point start is used and the shape's message says so. Rounds
      after the first start every shape from its previous landmarks (a mean template of
      shapes in different poses is no start).
    """

    #: files written before these fields existed ran with other values (core/base/compat.py)
    FIELDS_ADDED_LATER = DATA_TERM_ADDED_LATER

    bidirectional_weight: float = option(1.0, "λ: weight of target landmarks pulling the template", minimum=0)
    normal_max_angle: float | None = option(60.0, "largest angle (degrees) between matched normals; None: off")
    matching: str = option("closest", "data term matches: closest (compatible) points, the thesis; features: "
                           "nearest in position and surface normal (beyond the thesis)", flag="--matching",
                           choices=MATCHING_METHODS)
    feature_between: float = option(1.0, "features: weight of a point's position between the turning lines of its "
                                    "region, from the groupwise round on (0: off)", flag="--feature-between", minimum=0)
    initialisation: str = option("auto", "where registration starts: auto (chosen from how the collection's shapes "
                                 "differ: spectral where they differ in pose, else closest); closest (the template as "
                                 "it is, the thesis); spectral (an intrinsic map, for shapes that differ in pose)",
                                 flag="--initialisation", choices=INITIALISATIONS)
    distance_weights: bool = option(False, "weight matches by 1 / (1 + d)")
    snap_to_vertices: bool = option(False, "closest points on target vertices instead of the surface")


@dataclass(frozen=True)
class IterationSettings(Settings):
    """The iterations of Alg. 3 (§4.2.6) and the solve of each.

    update_template: True: every solve starts from the moved points, so the stiffness
      regularises each step only (the thesis's modification of Alg. 3). False (default):
      the affines map the original template and the stiffness regularises the whole
      deformation (Amberg et al.): fewer iterations and less drift.
    tolerance: ε; iterate at one α until |E_t − E_(t−1)| <= ε · E_(t−1).
    max_iterations_per_alpha, max_iterations: caps of ICP iterations at one α and over the
      whole schedule (thesis ~20–30 in all). Later iterations at one α barely move the
      points, so lower caps keep the accuracy at less cost; too low and pairwise
      registration overtakes groupwise.
    ridge: tiny Tikhonov weight pulling each affine towards "no change" (relative to the
      mean diagonal of the data term's blocks); keeps BᵀB invertible when weights switch
      matches off.
    """

    update_template: bool = option(False, "every solve starts from the moved points (the thesis's Alg. 3)")
    tolerance: float = option(1e-3, "ε: relative energy change that ends the iterations at one α", minimum=0)
    max_iterations_per_alpha: int = option(4, "ICP iterations at one α at most", minimum=1)
    max_iterations: int = option(20, "ICP iterations over the whole schedule at most", minimum=1)
    ridge: float = option(1e-9, "Tikhonov weight pulling each affine towards no change", minimum=0)


@dataclass(frozen=True)
class OutlierSettings(Settings):
    """When a registered shape is flagged an outlier (outliers.py `flag_outliers`; any rule
    flags).

    residual_mad_factor: flag a residual above median + factor · 1.4826 · MAD ...
    residual_min_ratio: ... and above this multiple of the median (both must hold), or
    max_residual: above this fraction of the shape's bounding-box diagonal, or
    max_scale_ratio: when the shape's and the template's bounding-box diagonals differ by
      more than this factor (alignment or scaling failed or was switched off), or
    loo_mad_factor, loo_min_ratio: when the shape's leave-one-out reconstruction error (its
      landmarks against the PPCA model, §5.3.1, of the other shapes) is above median +
      factor · 1.4826 · MAD and above this multiple of the median (upside down, turned,
      mirrored, another class). The ratio sits between what clean collections reach and
      what a shape turned upside down after Prepare reaches.
    loo_variance: the leave-one-out model keeps the fewest principal directions that
      explain this fraction of the other shapes' variance.
    """

    residual_mad_factor: float = option(3.0, "outlier: residual above median + factor · MAD ...")
    residual_min_ratio: float = option(1.5, "... and above this multiple of the median")
    max_residual: float = option(0.05, "outlier: residual above this fraction of the diagonal")
    max_scale_ratio: float = option(3.0, "outlier: size differs from the template's by more than this factor")
    loo_mad_factor: float = option(3.0, "outlier: leave-one-out error above median + factor · MAD ...")
    loo_min_ratio: float = option(4.0, "... and above this multiple of the median", above=1)
    loo_variance: float = option(0.9, "fraction of variance the leave-one-out PPCA model keeps", above=0)

    def __post_init__(self):
        super().__post_init__()
        if self.loo_variance > 1:
            raise SettingsError("loo_variance", f"must be at most 1, got {self.loo_variance!r}")




@dataclass(frozen=True)
class CorrespondenceSettings(Settings):
    """Every parameter of the correspondence engine, with the thesis defaults (§4.2.8)
    except where a measurement said otherwise, one group per subsystem (each group's
    docstring says what its options do). The figures behind each non-thesis value are in
    docs/history.md ("Measurements behind the correspondence settings").

    proxy_faces (dense shapes): a shape with more than 2.5 times this many faces is
      registered against its vertex-clustering proxy of about this many faces
      (core/simplify.py, built once per shape) and its final landmarks are placed exactly
      on the full surface (proxy.py), so a dense sculpt costs about what a sparse mesh
      does; unused with snap_to_vertices.
    groupwise_rounds (§4.2.7): times the template is replaced by the mean landmark cloud and
      all shapes registered again (thesis 1; 0 = pairwise registration only).
    """

    #: flat names of before and fields taken out (core/base/compat.py); not annotated: class
    #: attributes, not fields
    FIELDS_MOVED = CORRESPONDENCE_MOVED
    FIELDS_REMOVED = CORRESPONDENCE_REMOVED

    stiffness: StiffnessSettings = group(StiffnessSettings, "the stiffness term and its schedule (§4.2.4, §4.2.6)")
    data_term: DataTermSettings = group(DataTermSettings, "matches, their weights and the start (§4.2.2)")
    iterations: IterationSettings = group(IterationSettings, "iterations of Alg. 3 and the solve (§4.2.6)")
    proxy_faces: int = option(REGISTRATION_PROXY_FACES, "faces of the proxy a shape with more than 2.5 times as many "
                              "is registered against", minimum=100)
    groupwise_rounds: int = option(1, "rounds with the mean landmark cloud as template", minimum=0)
    outliers: OutlierSettings = group(OutlierSettings, "when a shape is flagged an outlier (outliers.py)")

    @property
    def alphas(self) -> np.ndarray:
        """The stiffness schedule α_1 > α_2 > ... of Alg. 3: `alpha_steps` values from
        `alpha_start` down to `alpha_end` (× FEATURE_STIFFNESS with feature matches)."""
        stiffness = self.stiffness
        end = stiffness.alpha_end * (FEATURE_STIFFNESS if self.data_term.matching == "features" else 1.0)
        if stiffness.alpha_steps == 1:
            return np.array([end], dtype=float)
        return np.linspace(stiffness.alpha_start, end, stiffness.alpha_steps)
