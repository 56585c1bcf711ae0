"""Evaluation of shape models: the thesis's §5.5 experiments plus the field's standard
generative-shape metrics (docs/method.md §5).

Everything works on corresponding landmark sets: a shape is a row y ∈ R^{3L} of the landmark
matrix Y (N × 3L, docs/method.md §4), i.e. L points p_1..p_L ∈ R^3 in the normalised frame
(z up, x the first horizontal principal axis, collection-wide scale).

Modules: `metrics` (distances d and d_P; novelty, specificity, MMD, coverage, 1-NNA),
`completion` (hidden regions and the completion error), `baselines` (training-set
memoriser, mean shape), `curves` (PPCA generalisation, specificity and held-out NLL
against the number of modes), `latent` (2-D latent map, outlier scores, morph),
`protocol` (random streams, k-fold split) and `run` (`run_evaluation`, its settings and
result; `report.py` writes the files).

Which metric uses which distance: novelty / specificity (sample → nearest training shape)
use d_P, as the thesis compared samples with their nearest data example after alignment;
MMD, coverage and 1-NNA use d, the plain Euclidean metric in R^{3L} scaled by 1/√L (all
shapes already share one frame), because a Gaussian kernel of a Euclidean distance is
positive definite, so MMD is a true metric between distributions; generalisation and
completion compare a reconstruction with its own ground truth in the model frame (no
alignment, as ShapeWorks and Scalismo do). For the latent variable models (whose refits are
expensive) generalisation is the k-fold held-out reconstruction at their latent dimension:
ŷ = decode(encode(y)) by a model fitted without y.

References: Styner et al., "Evaluation of 3D correspondence methods for model building",
IPMI 2003; Gretton et al., "A kernel two-sample test", JMLR 2012; Achlioptas et al.,
"Learning representations and generative models for 3D point clouds", ICML 2018; Lopez-Paz
& Oquab, "Revisiting classifier two-sample tests", ICLR 2017; Yang et al., "PointFlow",
ICCV 2019; Umeyama, IEEE PAMI 1991.
"""

from .baselines import MeanShapeModel, TrainingSetModel
from .completion import REGIONS, completion_errors, hidden_coordinates, region_mask
from .curves import generalisation_curve, ppca_nll_curve, specificity_curve
from .latent import choose_morph_endpoints, latent_morph, latent_outlier_scores
from .metrics import (EvaluationError, as_point_sets, coverage, landmark_rms_matrix, mmd, novelty, one_nna,
                      one_nna_chance_level, procrustes_align, procrustes_rms_matrix, specificity)
from .protocol import heldout_folds, kfold_indices, random_stream
from .run import EvaluationResult, EvaluationSettings, parse_model_names, run_evaluation

__all__ = [
    "EvaluationError",
    "EvaluationSettings",
    "EvaluationResult",
    "REGIONS",
    "as_point_sets",
    "landmark_rms_matrix",
    "procrustes_rms_matrix",
    "procrustes_align",
    "novelty",
    "specificity",
    "mmd",
    "coverage",
    "one_nna",
    "one_nna_chance_level",
    "region_mask",
    "hidden_coordinates",
    "completion_errors",
    "random_stream",
    "kfold_indices",
    "heldout_folds",
    "generalisation_curve",
    "specificity_curve",
    "ppca_nll_curve",
    "latent_outlier_scores",
    "choose_morph_endpoints",
    "latent_morph",
    "TrainingSetModel",
    "MeanShapeModel",
    "parse_model_names",
    "run_evaluation",
]
