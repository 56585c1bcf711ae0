"""Every tunable parameter of the correspondence engine, in one frozen settings dataclass
(core/settings.py: checks itself, travels as one JSON string)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..settings import Settings, SettingsError, option
from ..simplify import REGISTRATION_PROXY_FACES

__all__ = ["CorrespondenceSettings", "MATCHING_METHODS", "REFINE_METHODS", "REFINE_ALIGNMENTS"]

#: `matching`: the data term's matches (registration.py, features.py)
MATCHING_METHODS = ("closest", "features")

#: `refine`: "population" slides the landmarks on their surfaces after NICP (refine.py)
REFINE_METHODS = ("population", "none")
#: `refine_alignment`: what is removed from every shape before the compactness term
REFINE_ALIGNMENTS = ("similarity", "scale", "none")


@dataclass(frozen=True)
class CorrespondenceSettings(Settings):
    """Every parameter of the correspondence engine, with the thesis defaults (§4.2.8)
    except where a measurement said otherwise (`normal_max_angle`, `update_template`).

    Stiffness (§4.2.4):
      gamma: γ in G = diag(1, 1, 1, γ); weight of the translation part of neighbouring
        affine differences against the linear part (thesis 2).
      k_neighbours: k of the symmetrised k-NN landmark graph of the stiffness term
        (thesis 6).
      alpha_start, alpha_end, alpha_steps: the stiffness schedule of Alg. 3, `alpha_steps`
        values evenly spaced from `alpha_start` down to `alpha_end` (thesis 100 → 5 for
        vases and teapots, 100 → 10 for cars). `alpha_steps = 1` uses `alpha_end` only
        (no relaxation).
    Data term (§4.2.2):
      bidirectional_weight: λ, weight of target landmarks pulling their closest template
        point (thesis 1 vases, 0.5 teapots, 0.1 cars: small when meshes have interior
        parts). 0 switches the bidirectional term off.
      normal_max_angle: normal compatibility (degrees): a match only counts between
        points whose normals differ by at most this; the closest *compatible* target point
        is used (and a template point with none nearby gets weight 0). None: off, plain
        closest points (the thesis's setting). Default 60: on thin-walled shapes (vases)
        plain closest points put ~1/3 of the outer-wall landmarks on the inner wall;
        this cuts that to a few % (bench/correspondence.py). Needs consistently oriented
        meshes.
      distance_weights: weight matches by s = 1 / (1 + d), normalised by the largest s
        (4.12–4.13; d in the registration frame, unit RMS template radius).
      snap_to_vertices: closest points and final placement on target *vertices* (the
        thesis's choice) instead of the closest point on the surface (default).
    Feature-space matches (**beyond** the thesis, opt-in; features.py, issue 13):
      matching: "closest": the thesis's data term, every template point matched to the
        closest (normal-compatible) target point. "features": to the nearest target point
        in a joint space of position and features [w_n · n, w_u · tanh(n_z / h)] (frame
        units: unit RMS template radius), so matches keep to the side of a thin wall that
        faces their way (`normal_max_angle` is not used) and turning regions — a belly, a
        neck, a shoulder — are pulled onto each other. Measured (docs/results.md "Fourth
        round", second and fourth parts; `bench/correspondence_seeds.py`): true error of
        procedural vases 2.025 → 1.424 % (6 shapes, mean of five seeds, lower on every
        seed; 1.763 % with the first defaults, h 0.1 and α ending at 5), 1.4× faster; PSB
        label transfer higher on Airplane, Cup and Fish, 0.2 points lower on Vase; but PPCA
        models of its landmarks are less compact (held-out log-likelihood lower and
        completion error higher on all four PSB classes; completion measured on the
        held-out surface worse on Airplane, Cup and Vase too), so it is not the default.
        Without `feature_fit_check`, on mugs modelled in Blender whose walls lean in on
        some and out on others it fitted 5 of 14 badly (flagged as outliers: the
        up-component of a leaning wall is the sign of its lean; docs/results.md "Fourth
        round, eleventh part"); the check now matches such collections by closest points.
      feature_normals: w_n: two points whose normals differ by 60° are as far apart as
        points w_n apart on a wall. 0.5 (measured with the first defaults, h 0.1 and α
        ending at 5): lower procedural error than 1 (1.763 against
        1.810 %) and a remeshed copy within 0.22 edge lengths (1: 0.27); 1 transfers PSB
        labels better (Vase 70.3 against 67.7 %).
      feature_tilt: c: the normal feature is w_n · (n_x, n_y, c · n_z). The up feature
        below already says which side of a turning line a point lies on; the normal's
        own up-component also pulls matches towards points of equal slope, which on a
        flaring lip or a belly is a different height on every shape. 0 (default; files
        written before it record 1): the normal keeps a match on the side of a thin wall
        facing its way by its horizontal direction, and facing up or down by the up
        feature. Measured at 0 against 1 (docs/results.md "Fourth round, thirteenth
        part"): procedural true error 1.135 → 1.082 % (6 vases, lower on all five
        seeds; seeds 5–9 1.770 → 1.728, 20 vases 1.768 → 1.749 %), PSB Vase models
        more compact (held-out log-likelihood 1447 → 1524, completion on the surface 3.02
        → 2.79 %), completion on the surface 1.35 → 1.33 % on Airplane and 1.49 → 1.51 %
        on Fish, label transfer within 0.3 points (Airplane 95.2 → 94.9, Fish 87.0 → 87.1,
        Vase 66.9 → 66.7 %); 0.3 gave the same procedural error and Vase 65.9 %.
      feature_up: w_u: weight of the saturated up-component of the normal (+z is up after
        Prepare): where the surface turns from facing down to facing up.
      feature_up_width: h: n_z well below h counts as "facing sideways", well above as up.
        0.01 (was 0.1): the feature is then nearly the side of the turning line a point
        lies on, and a belly's gentle slopes stop pulling matches towards equal slope
        (true error 1.635 → 1.424 % with the softer schedule below; docs/results.md
        "Fourth round, fourth part").
      feature_stiffness: with feature matches the schedule ends at this fraction of
        `alpha_end` (0.4: 5 → 2 at the default). The features pull only the points
        between the template's turning line and the target's; a softer last α lets the
        wall around them follow. Measured (6 vases, five seeds): true error 1.632 % at 1
        with h 0.01, 1.424 % at 0.4; scratch, template excluded: 1.739 % at 0.6, 1.719 %
        at 0.2. With closest points a softer end does not help (α 1: 2.431 against
        2.401 %, template excluded). The price: a remeshed copy of one vase is matched
        within 0.31 edge lengths instead of 0.22 (tests/core/test_features.py).
      feature_between: w_b > 0 adds a fifth feature, w_b · g: where a point lies between
        the turning lines of its region (turning.py: 0 on the lower line, 1 on the upper,
        by the height a path within the region climbs), so the points on both sides of a
        line are pulled in proportion, not only those between the template's line and the
        target's. The first round compares sides only and every shape reports its own g at
        its placed points; from the groupwise round on the template keeps the g of the
        shape it was made from, and every shape compares it with a share of w_b that falls
        from 1 to 0 as its first-round g disagrees with the template's by 0.1 to 0.2 on
        average (features.agreement_weights; groupwise.py). 1 (default; it acts only
        with feature matches); 0: off (files written before it record 0). Measured at 1
        against 0 (docs/results.md "Fourth round", fifth, seventh, eighth and tenth
        parts): procedural true error 1.424 → 1.175 % (lower on every seed; seeds 5–9
        2.056 → 1.885); with `feature_trim` 1.395 → 1.135 % (seeds 5–9 2.024 → 1.852),
        PSB label transfer equal or higher on every class (most PSB shapes disagree and are
        matched without it; Airplane 95.3, Cup 94.6, Fish 87.1 → 87.4, Vase 66.6 → 66.9 %),
        PSB held-out log-likelihood and completion within 0.2 % and 1.5 %; 1.2× the
        registration time. It became the default with feature matches when the trimmed
        matches and the agreement weights made it no worse on any PSB class.
      feature_trim: with feature matches, an iteration drops the template points whose
        match lies more than this many times the median match distance away (trimmed ICP,
        **beyond** the thesis, which keeps every compatible match): a part of the template
        with no counterpart on the target (a neck on a vase without one, a handle) then
        follows its neighbours through the stiffness term instead of being dragged to
        the nearest surface facing its way. 0: none dropped (files written before it
        record 0). Measured (docs/results.md "Fourth round, ninth part"; 6 vases, five
        seeds): features + between 1.175 → 1.135 %, features 1.424 → 1.395 %, seeds 5–9
        1.885 → 1.852 and 2.056 → 2.024; PPCA held-out log-likelihood higher and completion
        lower on all four; PSB label transfer within 0.3 points. 10 of 3 / 4.5 / 6 / 10 /
        15 / 25 (procedural 1.194 / 1.170 / 1.149 / 1.135 / 1.137 / 1.150 %).
      feature_merged_regions: with feature matches, after the first round, the template
        points of two regions facing opposite ways (turning.facing_regions) whose matches
        land in one region of a shape are matched on that shape by position and normal
        only, without the up feature and the positions between turning lines
        (features.merged_regions): a vase whose lip is narrower than its neck faces up
        from belly to rim, where the template's neck splits that wall into one facing up
        and one facing down, and matching sides there drags the template's neck onto the
        shape's rim. Files written before it record False. Measured (docs/results.md
        "Fourth round, fourteenth part"): procedural true error 1.082 → 0.994 % (6 vases,
        five seeds; it acts on the three vases without a neck, 2.97 → 2.09 %, and on no
        other), seeds 5–9 1.728 → 1.672, 20 vases 1.749 → 1.639 %; PSB label transfer
        within 0.1 point with fewer shapes below the naive baseline (Airplane 3 → 1, Vase
        4 → 3); models less compact on the procedural class and PSB Vase, more on
        Airplane.
      feature_samples: area-uniform surface samples of the target per template point;
        they choose the face a match lies on (the match is the closest point of that
        face, and the final placement is the exact closest surface point as always).
      feature_fit_check: True (default; files written before it record False): the first
        round registers every shape by feature matches and by closest points from the same
        template, and a shape counts as fitted worse by feature matches when its residual
        exceeds the closest-point fit's by more than 25 % (features.worse_fits: a template
        collapsed onto part of the shape, as where its wall leans in and the shape's out).
        When more than `feature_fallback_share` of the shapes are, the collection is
        matched by closest points (exactly the "closest" result); otherwise by feature
        matches, exactly as without the check. The file records every shape's outcome
        (`Correspondence.feature_fit_worse`; `matching_summary` says which data term ran).
        Costs one closest-point round (1.6× the time of feature matches alone, 1.3× of
        closest points). Measured (docs/results.md "Fourth round, twelfth part"): 14
        Blender mugs 5 outliers → 0 (5 fitted worse: closest points), PSB Cup closest
        points (held-out log-likelihood 1634.8 → 1676.4, label transfer 94.6 → 93.7 %),
        procedural vases (seeds 1-4, 11) and PSB Airplane, Fish and Vase unchanged.
      feature_fallback_share: 0.1: one collapse in a collection of 10 or more is left to the
        outlier flags; more say the class's walls contradict the features (in a smaller
        collection one is enough: seed 7 of the procedural vases, 3.686 → 3.280 %).
    Iteration (Alg. 3):
      update_template: True: every solve starts from the moved points, so the stiffness
        regularises each step only (the thesis's modification of Alg. 3). False
        (default): the affines map the original template and the stiffness regularises the
        whole deformation (Amberg et al.); measured: converges in fewer iterations and
        drifts less (remeshed copy 0.37 % vs 0.55 % of the diagonal).
      tolerance: ε; iterate at one α until |E_t − E_(t−1)| <= ε · E_(t−1).
      max_iterations_per_alpha: cap of ICP iterations at one α (default 4; was 10).
      max_iterations: cap of ICP iterations over the whole schedule (thesis ~20–30;
        default 20, was 30). Measured (pairwise, 5 procedural vase pairs + 4 PSB classes ×
        8 pairs): caps 10/30 used 20–28 iterations, caps 4/20 use 16–20 at the same
        accuracy (vase true error 2.92 % vs 2.92 %, PSB label transfer 87.3 % vs 87.2 %):
        the later iterations at one α barely move the points. Caps 3/15 were as accurate
        there and faster still, but on the groupwise test collection
        (tests/core/test_correspond.py) pairwise then edged out groupwise (1.78 % vs
        1.80 %); at 4/20 groupwise wins (1.83 % vs 1.86 %), as with the old caps.
      ridge: tiny Tikhonov weight pulling each affine towards "no change" (relative to the
        mean diagonal of the data term's blocks); keeps BᵀB invertible when weights switch
        matches off.
    Dense shapes (issue 15):
      proxy_faces: a shape with more than 2.5 times this many faces (100k at the default)
        is registered against its vertex-clustering proxy of about this many faces
        (core/simplify.py, built once per shape) and its final landmarks are placed
        exactly on the full surface (proxy.py); unused with snap_to_vertices.
    Groupwise (§4.2.7):
      groupwise_rounds: times the template is replaced by the mean landmark cloud and all
        shapes registered again (thesis 1; 0 = pairwise registration only).
    Outliers (outliers.py `flag_outliers`; any rule flags):
      outlier_mad_factor: flag a residual above median + factor · 1.4826 · MAD ...
      outlier_min_ratio: ... and above this multiple of the median (both must hold), or
      max_residual: above this fraction of the shape's bounding-box diagonal, or
      max_scale_ratio: when the shape's and the template's bounding-box diagonals differ by
        more than this factor (alignment/scaling failed or was switched off), or
      loo_mad_factor, loo_min_ratio: when the shape's leave-one-out reconstruction error
        (its landmarks against the PPCA model of the other shapes) is above median +
        factor · 1.4826 · MAD and above this multiple of the median (upside down, turned,
        mirrored, another class). Measured on 12 procedural vases (300 landmarks),
        seeds 0-19: shapes of clean collections reach at most 2.0× the median (2.6×
        beside an upside-down shape), a shape turned upside down after Prepare at
        least 6.4×; 4× flags none of the clean and every upside-down one.
      loo_variance: the leave-one-out model keeps the fewest principal directions that
        explain this fraction of the other shapes' variance.
    Groupwise refinement (**beyond** the thesis; refine.py, objective.py):
      refine: "population": after NICP every landmark slides on its own surface to lower
        E = w_c · compactness + w_s · spread (Cates et al. 2007; Davies et al. 2002);
        "none" (default): NICP's landmarks as they are (the thesis). The default stays
        "none" because the benchmark (bench/correspondence.py) measured the refinement
        lowering the objective but not the true error on the procedural vases.
      refine_iterations: accepted descent steps at most.
      refine_compactness: w_c, weight of ½ log det(I + K/δ) (K: the N × N dual Gram matrix
        of the aligned, centred landmark vectors). 0: spread term only.
      refine_spread: w_s, weight of the mean over shapes of the spread term (a Parzen
        estimate of each shape's landmark density, lowest when they are spread out).
        0: compactness only (landmarks may bunch up).
      refine_regulariser: ρ / RMS landmark radius, δ = L ρ²: modes of variation that move
        the landmarks by less than ρ count as squared size, larger ones by their log
        (see objective.py). Small values reward few dimensions; large ones make the
        term a plain sum of squares.
      refine_normals: κ: the compactness term sees every landmark's smooth surface normal
        beside its position, scaled by κ × the population's RMS landmark radius
        (ShapeWorks' "use normals"): features where the surface turns (belly, neck, rim)
        then cost variance when they are not lined up. 0: positions only.
      refine_smooth_fields: K > 0: every step is a combination of the K smoothest fields
        on the landmark graph (Laplacian eigenvectors) per coordinate, so whole regions
        slide together instead of the gradient's noisy, landmark-by-landmark pattern;
        0: the plain (projected) gradient.
      refine_sigma: width of the spread kernel in landmark spacings √(area / L).
      refine_step: the first step moves the landmarks by this many spacings (RMS); it
        then grows by 1.5 after an accepted step and halves after a rejected one.
      refine_max_move: no landmark moves by more than this many spacings in one step
        (the step must stay local for the closest point to follow the surface).
      refine_alignment: "similarity": compactness after removing every shape's scale and
        rotation (generalised Procrustes, estimated again every 10 steps when that lowers
        the objective) and centroid; "scale": its centroid and size only (the rotation
        Prepare gave it stays); "none": on the prepared shapes as they are.
      refine_tolerance: stop when an accepted step lowers E by less than this (relative).
    """

    #: files written before these fields existed ran with these values (settings.Settings);
    #: not annotated: a class attribute, not a field
    FIELDS_ADDED_LATER = {"feature_stiffness": 1.0, "feature_between": 0.0, "feature_trim": 0.0,
                          "feature_fit_check": False, "feature_tilt": 1.0, "feature_merged_regions": False}

    gamma: float = option(2.0, "γ: weight of the translation part in the stiffness", above=0)
    k_neighbours: int = option(6, "k of the landmark graph of the stiffness term", minimum=1)
    alpha_start: float = option(100.0, "first stiffness α of the schedule (at least alpha_end)")
    alpha_end: float = option(5.0, "last stiffness α of the schedule", above=0)
    alpha_steps: int = option(5, "α values of the schedule", minimum=1)
    bidirectional_weight: float = option(1.0, "λ: weight of target landmarks pulling the template", minimum=0)
    normal_max_angle: float | None = option(60.0, "largest angle (degrees) between matched normals; None: off")
    matching: str = option("closest", "data term matches: closest (compatible) points, the thesis; features: "
                           "nearest in position and surface normal (beyond the thesis)", flag="--matching",
                           choices=MATCHING_METHODS)
    feature_normals: float = option(0.5, "features: weight of the surface normal beside the position", minimum=0)
    feature_tilt: float = option(0.0, "features: weight of the normal's up-component within the normal feature, "
                                      "relative to its horizontal part", minimum=0)
    feature_up: float = option(1.0, "features: weight of the saturated up-component of the normal", minimum=0)
    feature_up_width: float = option(0.01, "features: up-components well below this count as facing sideways",
                                     above=0)
    feature_stiffness: float = option(0.4, "features: the stiffness schedule ends at this fraction of alpha_end",
                                      above=0)
    feature_between: float = option(1.0, "features: weight of a point's position between the turning lines of its "
                                    "region, from the groupwise round on (0: off)", flag="--feature-between", minimum=0)
    feature_trim: float = option(10.0, "features: matches farther than this many times the median match distance "
                                 "are dropped in that iteration (0: none)", minimum=0)
    feature_merged_regions: bool = option(True, "features: template points whose region merges with one facing "
                                                "the other way on a shape are matched there by position and normal "
                                                "only, from the groupwise round on")
    feature_samples: int = option(20, "features: target surface samples per template point", minimum=1)
    feature_fit_check: bool = option(True, "features: the first round also registers every shape by closest points; "
                                     "a collection feature matches fit badly is matched by closest points")
    feature_fallback_share: float = option(0.1, "features: above this share of shapes fitted over 25 % worse, the "
                                           "whole collection is matched by closest points", minimum=0)
    distance_weights: bool = option(False, "weight matches by 1 / (1 + d)")
    snap_to_vertices: bool = option(False, "closest points on target vertices instead of the surface")
    update_template: bool = option(False, "every solve starts from the moved points (the thesis's Alg. 3)")
    tolerance: float = option(1e-3, "ε: relative energy change that ends the iterations at one α", minimum=0)
    max_iterations_per_alpha: int = option(4, "ICP iterations at one α at most", minimum=1)
    max_iterations: int = option(20, "ICP iterations over the whole schedule at most", minimum=1)
    ridge: float = option(1e-9, "Tikhonov weight pulling each affine towards no change", minimum=0)
    proxy_faces: int = option(REGISTRATION_PROXY_FACES, "faces of the proxy a shape with more than 2.5 times as many "
                              "is registered against", minimum=100)
    groupwise_rounds: int = option(1, "rounds with the mean landmark cloud as template", minimum=0)
    outlier_mad_factor: float = option(3.0, "outlier: residual above median + factor · MAD ...")
    outlier_min_ratio: float = option(1.5, "... and above this multiple of the median")
    max_residual: float = option(0.05, "outlier: residual above this fraction of the diagonal")
    max_scale_ratio: float = option(3.0, "outlier: size differs from the template's by more than this factor")
    loo_mad_factor: float = option(3.0, "outlier: leave-one-out error above median + factor · MAD ...")
    loo_min_ratio: float = option(4.0, "... and above this multiple of the median", above=1)
    loo_variance: float = option(0.9, "fraction of variance the leave-one-out PPCA model keeps", above=0)
    refine: str = option("none", "groupwise refinement after non-rigid ICP (population: landmarks slide on their "
                         "surfaces to make the population compact; none: the thesis)", flag="--refine",
                         choices=REFINE_METHODS)
    refine_iterations: int = option(30, "refinement: accepted descent steps at most", minimum=0)
    refine_compactness: float = option(1.0, "refinement: weight of the compactness term", minimum=0)
    refine_spread: float = option(1.0, "refinement: weight of the spread term", minimum=0)
    refine_regulariser: float = option(0.001, "refinement: ρ of the covariance regulariser δ = L ρ², relative to "
                                       "the RMS landmark radius", above=0)
    refine_normals: float = option(1.0, "refinement: weight of the surface normals beside the positions in the "
                                   "compactness term (× the RMS landmark radius)", minimum=0)
    refine_smooth_fields: int = option(30, "refinement: steps restricted to this many smoothest displacement fields "
                                       "of the landmark graph (0: plain gradient)", minimum=0)
    refine_sigma: float = option(1.0, "refinement: spread kernel width in landmark spacings", above=0)
    refine_step: float = option(0.3, "refinement: RMS move of the first step in landmark spacings", above=0)
    refine_max_move: float = option(0.5, "refinement: largest move of a landmark in one step, in spacings", above=0)
    refine_alignment: str = option("similarity", "refinement: similarity removed before the compactness term",
                                   choices=REFINE_ALIGNMENTS)
    refine_tolerance: float = option(1e-6, "refinement: stop below this relative decrease of the objective",
                                     minimum=0)

    def __post_init__(self):
        super().__post_init__()
        if self.loo_variance > 1:
            raise SettingsError("loo_variance", f"must be at most 1, got {self.loo_variance!r}")
        if self.feature_fallback_share > 1:
            raise SettingsError("feature_fallback_share", f"must be at most 1, got {self.feature_fallback_share!r}")
        if self.feature_stiffness > 1:
            raise SettingsError("feature_stiffness", f"must be at most 1, got {self.feature_stiffness!r}")
        if self.alpha_start < self.alpha_end:
            raise SettingsError("alpha_start", f"must be at least alpha_end ({self.alpha_end!r}), got "
                                f"{self.alpha_start!r}")

    @property
    def alphas(self) -> np.ndarray:
        """The stiffness schedule α_1 > α_2 > ... of Alg. 3: `alpha_steps` values from
        `alpha_start` down to `alpha_end` (× `feature_stiffness` with feature matches)."""
        end = self.alpha_end * (self.feature_stiffness if self.matching == "features" else 1.0)
        if self.alpha_steps == 1:
            return np.array([end], dtype=float)
        return np.linspace(self.alpha_start, end, self.alpha_steps)
