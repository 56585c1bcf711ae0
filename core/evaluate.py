"""Evaluation of shape models: the thesis's §5.5 experiments plus the field's standard
generative-shape metrics (issue 7; method.md §5).

Everything works on corresponding landmark sets: a shape is a row y ∈ R^{3L} of the landmark
matrix Y (N × 3L, method.md §4), i.e. L points p_1..p_L ∈ R^3 in the normalised frame
(z up, x the first horizontal principal axis, collection-wide scale).

Distances between two shapes a, b (L points each)
-------------------------------------------------
* per-landmark RMS            d(a, b)   = sqrt( (1/L) Σ_l ‖a_l − b_l‖² )
* Procrustes (similarity) RMS d_P(a→b) = min_{s>0, R∈SO(3), t} sqrt( (1/L) Σ_l ‖s R a_l + t − b_l‖² )
  closed form (Umeyama 1991): with centred ā, b̄ and H = āᵀ b̄ = U Σ Vᵀ,
  d_P² = (‖b̄‖² − (σ_1 + σ_2 + δ σ_3)² / ‖ā‖²) / L,  δ = sign det(V Uᵀ).
  It aligns the first argument onto the second (not symmetric when scales differ).

Which metric uses which distance: novelty / specificity (sample → nearest training shape)
use d_P, as the thesis compared samples with their nearest data example after alignment;
MMD, coverage and 1-NNA use d, the plain Euclidean metric in R^{3L} scaled by 1/√L (all
shapes already share one frame), because a Gaussian kernel of a Euclidean distance is
positive definite, so MMD is a true metric between distributions; generalisation and
completion compare a reconstruction with its own ground truth in the model frame (no
alignment, as ShapeWorks and Scalismo do).

Metrics
-------
* novelty(s) = min_n d_P(s → y_n) per sample s (thesis §5.5.2, Fig. 5.7).
* specificity (Styner et al. 2003) = (1/S) Σ_s min_n d_P(s → y_n): mean distance of S model
  samples to their nearest training shape (ShapeWorks / Scalismo `specificity`); small =
  samples look like data. Reported for the fitted models, and for PPCA against the number
  of modes m.
* generalisation (Styner et al. 2003) G(m) = (1/N) Σ_i d(y_i, ŷ_i^{(m)}): leave-one-out
  reconstruction error, ŷ_i^{(m)} the projection of y_i onto the first m modes of the PCA
  of the other N − 1 shapes (ShapeWorks / Scalismo `generalization`). For the latent
  variable models (whose refits are expensive) it is the k-fold version at their latent
  dimension: ŷ = decode(encode(y)) by a model fitted without y.
* MMD (Gretton et al. 2012), biased estimator with a Gaussian kernel k(a, b) =
  exp(−d(a, b)² / (2 h²)): MMD² = mean k(X, X) + mean k(R, R) − 2 mean k(X, R) ≥ 0, zero for
  identical sets; h = the median pairwise distance among the reference shapes (the
  median heuristic, fixed per reference set so every model is measured with the same h).
* coverage (Achlioptas et al. 2018) = |{argmin_r d(x, r) : x ∈ X}| / |R|: the fraction of
  reference shapes that are the nearest neighbour of at least one sample (1 = all covered).
* 1-NNA (Lopez-Paz & Oquab 2017; Yang et al. 2019) = leave-one-out accuracy of the 1-nearest-
  neighbour classifier telling samples from reference shapes in X ∪ R (|X| = |R|): 0.5 =
  indistinguishable (ideal), 1 = fully separable, 0 = every sample has a reference twin
  (memorisation of the reference set). On small sets the chance level is (n − 1)/(2n − 1),
  not 0.5 (`one_nna_chance_level`); the report states it.
* completion error (thesis §5.5.3, Table 5.1): a region of each held-out shape is hidden,
  the model reconstructs it from the rest; E = Σ_{hidden coordinates c} (ŷ_c − y_c)² per test
  shape, reported as the mean over test shapes. Regions (landmark sets chosen on the mean of
  the *training* shapes, so the same landmarks are hidden on every test shape and nothing
  about the test shape leaks into the mask): "top" third along z (up), "middle" third along
  z (the thesis's vase task), "rear" third along x (lowest x; the thesis's car task).
* held-out NLL against latent dimension (thesis §5.5.4, Fig. 5.10): k-fold mean negative
  log-likelihood per shape of PPCA on training and held-out folds, −(1/n) Σ log N(y | μ,
  WWᵀ + σ²I), for q = 1 .. q_max.
* 2-D latent map (§5.5.5, Fig. 5.11): a GP-LVM with Q = 2; outlier score of shape i = the
  leave-one-out negative log density of its latent under the Gaussian KDE of the others,
  −log[(1/(N−1)) Σ_{j≠i} N(z_i | z_j, h² I)], h the model's KDE bandwidth; robust z-score
  (score − median) / (1.4826 MAD), flagged above 3.
* morph (Fig. 5.12): decode z(t) = (1 − t) z_a + t z_b along a straight latent line between
  the two training latents farthest apart whose line stays where the latent KDE has support
  (`choose_morph_endpoints`).

References: Styner et al., "Evaluation of 3D correspondence methods for model building",
IPMI 2003; Gretton et al., "A kernel two-sample test", JMLR 2012; Achlioptas et al.,
"Learning representations and generative models for 3D point clouds", ICML 2018; Lopez-Paz
& Oquab, "Revisiting classifier two-sample tests", ICLR 2017; Yang et al., "PointFlow",
ICCV 2019; Umeyama, IEEE PAMI 1991.

`run_evaluation` runs all of it on one landmark matrix; `report.py` writes the files.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from .errors import ShapeGenError
from .models import MODEL_TYPES, BayesianGPLVM, GPLVM, ModelInputError, PPCA

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
    "kfold_indices",
    "generalisation_curve",
    "specificity_curve",
    "ppca_nll_curve",
    "latent_outlier_scores",
    "choose_morph_endpoints",
    "latent_morph",
    "TrainingSetModel",
    "MeanShapeModel",
    "make_model",
    "parse_model_names",
    "run_evaluation",
]

#: Regions hidden in the completion task: name -> (axis of the normalised frame, third).
REGIONS: dict[str, tuple[int, str]] = {"top": (2, "high"), "middle": (2, "middle"), "rear": (0, "low")}

Progress = Callable[[float, str], None]


class EvaluationError(ShapeGenError, ValueError):
    """Evaluation settings or data are unusable (the message says which and why)."""


# ============================================================================ distances
def as_point_sets(Y) -> np.ndarray:
    """(n, 3L) landmark rows or (n, L, 3) point sets -> float64 (n, L, 3)."""
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[None, :]
    if Y.ndim == 2:
        if Y.shape[1] % 3:
            raise EvaluationError(f"landmark rows must have 3L coordinates, got {Y.shape[1]}")
        return Y.reshape(Y.shape[0], -1, 3)
    if Y.ndim == 3 and Y.shape[2] == 3:
        return Y
    raise EvaluationError(f"expected landmark rows (n, 3L) or point sets (n, L, 3), got shape {Y.shape}")


def landmark_rms_matrix(A, B) -> np.ndarray:
    """d(a_i, b_j) = sqrt((1/L) Σ_l ‖a_il − b_jl‖²) for all pairs, (m, n); no alignment.

    A, B: sets of shapes as rows (n, 3L) or point sets (n, L, 3); one shape as a (3L,) row."""
    A, B = as_point_sets(A), as_point_sets(B)
    if A.shape[1] != B.shape[1]:
        raise EvaluationError(f"shapes have {A.shape[1]} and {B.shape[1]} landmarks; they must correspond")
    a = A.reshape(len(A), -1)
    b = B.reshape(len(B), -1)
    # explicit differences (no |a|² + |b|² − 2ab cancellation: identical shapes give exactly 0),
    # in row blocks of about 4 million numbers
    out = np.empty((len(a), len(b)))
    block = max(1, 4_000_000 // max(1, b.size))
    for start in range(0, len(a), block):
        diff = a[start:start + block, None, :] - b[None, :, :]
        out[start:start + block] = np.einsum("mnd,mnd->mn", diff, diff)
    return np.sqrt(out / A.shape[1])


def _procrustes_terms(A: np.ndarray, B: np.ndarray):
    """Centred squared norms and the optimal trace term σ1 + σ2 + δσ3 for every pair."""
    Ac = A - A.mean(1, keepdims=True)
    Bc = B - B.mean(1, keepdims=True)
    a2 = np.einsum("mlk,mlk->m", Ac, Ac)
    b2 = np.einsum("nlk,nlk->n", Bc, Bc)
    H = np.einsum("mlk,nlj->mnkj", Ac, Bc)                        # (m, n, 3, 3) = āᵀ b̄
    U, S, Vt = np.linalg.svd(H)
    det = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    det[det == 0] = 1.0
    trace = S[..., 0] + S[..., 1] + det * S[..., 2]
    return Ac, Bc, a2, b2, trace, U, Vt, det


def procrustes_rms_matrix(A, B, scaling: bool = True) -> np.ndarray:
    """d_P(a_i → b_j): RMS per landmark after the best similarity (scaling=True) or rigid
    transform of a_i onto b_j, for all pairs, (m, n). See the module docstring for the
    closed form; a degenerate a_i (all points equal) is only translated. The closed form
    subtracts two nearly equal terms for near-identical shapes: d_P of a shape and its copy is
    0 only to about 1e-8 of the shape's size."""
    A, B = as_point_sets(A), as_point_sets(B)
    if A.shape[1] != B.shape[1]:
        raise EvaluationError(f"shapes have {A.shape[1]} and {B.shape[1]} landmarks; they must correspond")
    _, _, a2, b2, trace, *_ = _procrustes_terms(A, B)
    if scaling:
        safe = np.where(a2 > 0, a2, 1.0)[:, None]
        residual = np.where(a2[:, None] > 0, b2[None, :] - trace**2 / safe, b2[None, :])
    else:
        residual = a2[:, None] + b2[None, :] - 2.0 * trace
    return np.sqrt(np.maximum(residual, 0.0) / A.shape[1])


def procrustes_align(a, b, scaling: bool = True) -> np.ndarray:
    """a moved by the best similarity (or rigid) transform onto b; a, b are one shape each,
    as (L, 3) points or a (3L,) row; returns (L, 3)."""
    A = np.asarray(a, dtype=np.float64).reshape(1, -1, 3)
    B = np.asarray(b, dtype=np.float64).reshape(1, -1, 3)
    Ac, _, a2, _, trace, U, Vt, det = _procrustes_terms(A, B)
    D = np.diag([1.0, 1.0, det[0, 0]])
    R = Vt[0, 0].T @ D @ U[0, 0].T                                # rotation taking ā to b̄
    s = trace[0, 0] / a2[0] if scaling and a2[0] > 0 else 1.0
    return s * Ac[0] @ R.T + B[0].mean(0)


# ============================================================================ sample metrics
def novelty(samples, training) -> dict:
    """Per sample: d_P(sample → nearest training shape) and that shape's index.

    A model that memorises its training set has novelty 0 for every sample."""
    D = procrustes_rms_matrix(samples, training)
    nearest = np.argmin(D, 1)
    return {"distance": D[np.arange(len(D)), nearest], "nearest": nearest}


def specificity(samples, training) -> float:
    """Styner et al. 2003: mean over samples of d_P(sample → nearest training shape)."""
    return float(np.mean(novelty(samples, training)["distance"]))


def _median_bandwidth(reference: np.ndarray) -> float:
    D = landmark_rms_matrix(reference, reference)
    upper = D[np.triu_indices(len(D), 1)]
    positive = upper[upper > 0]
    return float(np.median(positive)) if positive.size else 1.0


def mmd(samples, reference, bandwidth: float | None = None) -> float:
    """Maximum mean discrepancy (biased estimator) with a Gaussian kernel on d:

    MMD²(X, R) = (1/|X|²) Σ k(x, x') + (1/|R|²) Σ k(r, r') − (2/(|X||R|)) Σ k(x, r),
    k(a, b) = exp(−d(a, b)² / (2h²)); returns MMD = sqrt(max(MMD², 0)) (same units-free scale
    for every model). bandwidth h: None = median pairwise distance among the reference set.
    Identical sets give exactly 0."""
    X, R = as_point_sets(samples), as_point_sets(reference)
    h = _median_bandwidth(R) if bandwidth is None else float(bandwidth)
    if not h > 0:
        raise EvaluationError(f"MMD bandwidth must be positive, got {h}")

    def kernel_mean(P, Q):
        return float(np.mean(np.exp(-landmark_rms_matrix(P, Q) ** 2 / (2.0 * h * h))))

    value = kernel_mean(X, X) + kernel_mean(R, R) - 2.0 * kernel_mean(X, R)
    return float(np.sqrt(max(value, 0.0)))


def coverage(samples, reference) -> float:
    """Fraction of reference shapes that are the nearest (by d) reference of some sample."""
    D = landmark_rms_matrix(samples, reference)
    return float(np.unique(np.argmin(D, 1)).size / D.shape[1])


def one_nna(samples, reference) -> float:
    """1-nearest-neighbour accuracy (leave-one-out) of telling samples from reference shapes.

    Over the pooled set P = X ∪ R (|X| = |R| required), each point's nearest other point by d
    predicts its label; returns the fraction predicted correctly. 0.5 is ideal."""
    X, R = as_point_sets(samples), as_point_sets(reference)
    if len(X) != len(R):
        raise EvaluationError(f"1-NNA needs equally many samples and reference shapes, got {len(X)} and {len(R)}")
    pooled = np.concatenate([X, R])
    labels = np.r_[np.zeros(len(X), bool), np.ones(len(R), bool)]
    D = landmark_rms_matrix(pooled, pooled)
    np.fill_diagonal(D, np.inf)
    return float(np.mean(labels[np.argmin(D, 1)] == labels))


def one_nna_chance_level(n: int) -> float:
    """Expected leave-one-out 1-NNA when |X| = |R| = n come from one distribution: a point's
    nearest other point is one of n − 1 same-set or n other-set points, equally likely, so the
    accuracy is (n − 1) / (2n − 1) (→ 0.5 for large n; 3/7 ≈ 0.43 for n = 4)."""
    return (n - 1) / (2 * n - 1)


# ============================================================================ completion
def region_mask(reference_points, region: str) -> np.ndarray:
    """Hidden landmarks (bool, L) of a completion region, chosen on one reference point set
    (L, 3) — in `run_evaluation` the mean training shape — by its extent along an axis:
    "top" z > z_min + 2/3 Δz, "middle" the middle third of z, "rear" x < x_min + 1/3 Δx."""
    if region not in REGIONS:
        raise EvaluationError(f"unknown completion region {region!r} (known: {', '.join(REGIONS)})")
    P = np.asarray(reference_points, dtype=np.float64).reshape(-1, 3)
    axis, third = REGIONS[region]
    v = P[:, axis]
    lo, hi = v.min(), v.max()
    cut1, cut2 = lo + (hi - lo) / 3.0, lo + 2.0 * (hi - lo) / 3.0
    hidden = {"low": v < cut1, "middle": (v >= cut1) & (v <= cut2), "high": v > cut2}[third]
    if hidden.all() or not hidden.any():
        raise EvaluationError(f"completion region {region!r} hides {'all' if hidden.all() else 'no'} landmarks")
    return hidden


def hidden_coordinates(hidden_landmarks: np.ndarray) -> np.ndarray:
    """Landmark mask (L,) -> coordinate mask (3L,) in the row layout [x1 y1 z1 x2 ...]."""
    return np.repeat(np.asarray(hidden_landmarks, bool), 3)


def completion_errors(Y_true, Y_completed, hidden) -> np.ndarray:
    """Thesis Table 5.1: E_i = Σ_{c hidden} (ŷ_ic − y_ic)² per shape (coordinate mask (3L,))."""
    Y_true = np.asarray(Y_true, dtype=np.float64).reshape(len(Y_true), -1)
    Y_completed = np.asarray(Y_completed, dtype=np.float64).reshape(len(Y_completed), -1)
    return np.sum((Y_completed[:, hidden] - Y_true[:, hidden]) ** 2, axis=1)


# ============================================================================ baselines
class TrainingSetModel:
    """Memorisation baseline: samples are training shapes drawn without replacement (with
    replacement when more are asked than exist); completion copies the hidden coordinates of
    the training shape closest on the visible ones (nearest-neighbour completion)."""

    model_type = "training-set"

    def fit(self, Y, progress=None) -> "TrainingSetModel":
        self.training_ = np.asarray(Y, dtype=np.float64).copy()
        return self

    @property
    def latent_dim(self) -> int:
        return 0

    def sample(self, n: int, rng=None) -> np.ndarray:
        rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
        count = len(self.training_)
        return self.training_[rng.choice(count, n, replace=n > count)]

    def complete(self, Y_partial, observed_mask) -> np.ndarray:
        Y = np.asarray(Y_partial, dtype=np.float64)
        mask = np.asarray(observed_mask, bool)
        out = Y.copy()
        for i in range(len(Y)):
            o = mask[i]
            nearest = np.argmin(np.sum((self.training_[:, o] - Y[i, o]) ** 2, 1))
            out[i, ~o] = self.training_[nearest, ~o]
        return out


class MeanShapeModel(TrainingSetModel):
    """Collapsed baseline: every sample is the mean training shape, and completion fills the
    hidden coordinates with it (the reference level of the completion error: relative 1)."""

    model_type = "mean-shape"

    def sample(self, n: int, rng=None) -> np.ndarray:
        return np.repeat(self.training_.mean(0)[None, :], n, axis=0)

    def complete(self, Y_partial, observed_mask) -> np.ndarray:
        mask = np.asarray(observed_mask, bool)
        return np.where(mask, np.asarray(Y_partial, dtype=np.float64), self.training_.mean(0))


# ============================================================================ model set-up
def parse_model_names(text_or_names) -> list[str]:
    """'ppca,gplvm' or a list -> validated, de-duplicated names (order kept)."""
    names = text_or_names.split(",") if isinstance(text_or_names, str) else list(text_or_names)
    names = [n.strip().lower() for n in names if n.strip()]
    unknown = [n for n in names if n not in MODEL_TYPES]
    if unknown:
        raise EvaluationError(f"unknown model name(s) {', '.join(repr(n) for n in unknown)} "
                              f"(known: {', '.join(MODEL_TYPES)})")
    if not names:
        raise EvaluationError(f"no model given (known: {', '.join(MODEL_TYPES)})")
    return list(dict.fromkeys(names))


def make_model(name: str, latent_dim: int | None = None, seed: int = 0):
    """An unfitted model with the project defaults; latent_dim None = each model's 80 % rule."""
    if name == "ppca":
        return PPCA(n_components=latent_dim)
    if name == "gplvm":
        return GPLVM(n_components=latent_dim)
    if name == "bgplvm":
        return BayesianGPLVM(n_components=latent_dim, random_state=seed)
    raise EvaluationError(f"unknown model name {name!r} (known: {', '.join(MODEL_TYPES)})")


def kfold_indices(n: int, folds: int, rng: np.random.Generator) -> list[np.ndarray]:
    """A random partition of range(n) into `folds` test sets of near-equal size (sorted)."""
    if isinstance(folds, bool) or not isinstance(folds, (int, np.integer)) or folds < 2:
        raise EvaluationError(f"folds must be an integer >= 2, got {folds!r}")
    if folds > n:
        raise EvaluationError(f"{folds} folds need at least {folds} shapes, but the collection has {n}")
    return [np.sort(part) for part in np.array_split(rng.permutation(n), folds)]


def _rng(seed: int, *stream: int) -> np.random.Generator:
    """An independent, reproducible random stream per purpose (seed, stream id...)."""
    return np.random.default_rng([int(seed), *stream])


# ============================================================================ curves
def generalisation_curve(Y, max_modes: int | None = None) -> dict:
    """Styner et al. 2003 generalisation G(m), m = 1..max_modes (default N − 2), by
    leave-one-out: ŷ_i = μ_{−i} + V_m V_mᵀ (y_i − μ_{−i}) with V_m the first m principal axes
    of the other N − 1 shapes; G(m) = mean_i d(y_i, ŷ_i), with its standard error."""
    Y = np.asarray(Y, dtype=np.float64)
    n = len(Y)
    top = n - 2 if max_modes is None else min(int(max_modes), n - 2)
    if top < 1:
        raise EvaluationError(f"generalisation needs at least 3 shapes, got {n}")
    errors = np.empty((n, top))
    for i in range(n):
        rest = np.delete(Y, i, axis=0)
        mu = rest.mean(0)
        _, _, Vt = np.linalg.svd(rest - mu, full_matrices=False)
        coefficients = Vt[:top] @ (Y[i] - mu)
        for m in range(1, top + 1):
            recon = mu + coefficients[:m] @ Vt[:m]
            errors[i, m - 1] = landmark_rms_matrix(Y[i], recon)[0, 0]
    return {"modes": list(range(1, top + 1)), "mean": errors.mean(0),
            "stderr": errors.std(0, ddof=1) / np.sqrt(n)}


def specificity_curve(Y, n_samples: int, seed: int, max_modes: int | None = None) -> dict:
    """Styner et al. 2003 specificity S(m) of PPCA with m modes, fitted on all shapes:
    mean over `n_samples` samples of d_P(sample → nearest training shape)."""
    Y = np.asarray(Y, dtype=np.float64)
    top = len(Y) - 2 if max_modes is None else min(int(max_modes), len(Y) - 2)
    modes, values = [], []
    for m in range(1, top + 1):
        model = PPCA(n_components=m).fit(Y)
        values.append(specificity(model.sample(n_samples, _rng(seed, 7, m)), Y))
        modes.append(m)
    return {"modes": modes, "mean": np.asarray(values)}


def ppca_nll_curve(Y, folds: Sequence[np.ndarray], max_latent_dim: int | None = None) -> dict:
    """Thesis Fig. 5.10: k-fold mean NLL per shape of PPCA (Ledoit–Wolf, the project default)
    against q. For each q and fold f: train NLL = −mean_{n∈train} log N(y_n | μ, C),
    test NLL likewise on the held-out fold; averaged over folds (with the standard error of the
    test value over folds). q runs to min(max_latent_dim, smallest training fold − 1)."""
    Y = np.asarray(Y, dtype=np.float64)
    n = len(Y)
    smallest_train = min(n - len(f) for f in folds)
    top = smallest_train - 1 if max_latent_dim is None else min(int(max_latent_dim), smallest_train - 1)
    dims, train, test, test_se = [], [], [], []
    for q in range(1, top + 1):
        tr, te = [], []
        try:
            for test_idx in folds:
                train_idx = np.setdiff1d(np.arange(n), test_idx)
                model = PPCA(n_components=q).fit(Y[train_idx])
                tr.append(-np.mean(model.log_likelihood(Y[train_idx])))
                te.append(-np.mean(model.log_likelihood(Y[test_idx])))
        except ModelInputError:
            break                       # q reached the data's rank: the curve ends here
        dims.append(q)
        train.append(np.mean(tr))
        test.append(np.mean(te))
        test_se.append(np.std(te, ddof=1) / np.sqrt(len(te)))
    test_arr = np.asarray(test)
    return {"latent_dims": dims, "train_nll": np.asarray(train), "test_nll": test_arr,
            "test_nll_stderr": np.asarray(test_se),
            "best_latent_dim": int(dims[int(np.argmin(test_arr))]) if dims else None}


# ============================================================================ latent map, morph
def latent_outlier_scores(Z, bandwidth: float) -> dict:
    """Leave-one-out KDE outlier score of each latent (module docstring) and robust z-scores."""
    Z = np.asarray(Z, dtype=np.float64)
    n, q = Z.shape
    d2 = np.sum((Z[:, None, :] - Z[None, :, :]) ** 2, -1)
    log_k = -0.5 * d2 / bandwidth**2 - q * np.log(bandwidth) - 0.5 * q * np.log(2 * np.pi)
    np.fill_diagonal(log_k, -np.inf)
    top = log_k.max(1, keepdims=True)
    log_density = top[:, 0] + np.log(np.sum(np.exp(log_k - top), 1)) - np.log(n - 1)
    score = -log_density
    median = np.median(score)
    mad = 1.4826 * np.median(np.abs(score - median))
    robust_z = (score - median) / mad if mad > 0 else np.zeros(n)
    return {"score": score, "robust_z": robust_z, "flagged": robust_z > 3.0}


def _kde_log_density(points: np.ndarray, Z: np.ndarray, bandwidth: float) -> np.ndarray:
    """log (1/N) Σ_j N(p | z_j, h² I) at each row of `points`."""
    q = Z.shape[1]
    d2 = np.sum((points[:, None, :] - Z[None, :, :]) ** 2, -1)
    log_k = -0.5 * d2 / bandwidth**2 - q * np.log(bandwidth) - 0.5 * q * np.log(2 * np.pi)
    top = log_k.max(1, keepdims=True)
    return top[:, 0] + np.log(np.sum(np.exp(log_k - top), 1)) - np.log(len(Z))


def choose_morph_endpoints(Z, bandwidth: float, quantile: float = 0.1, checks: int = 25) -> tuple[int, int]:
    """Two training latents to morph between: the pair farthest apart whose straight line stays
    where the latent KDE has support, i.e. the KDE log density at `checks` points along the line
    never drops below its `quantile` over the training latents themselves (a morph through empty
    latent space only shows the GP reverting to the mean shape). Falls back to the farthest pair."""
    Z = np.asarray(Z, dtype=np.float64)
    floor = np.quantile(_kde_log_density(Z, Z, bandwidth), quantile)
    t = np.linspace(0.0, 1.0, checks)[:, None]
    d2 = np.sum((Z[:, None, :] - Z[None, :, :]) ** 2, -1)
    best, best_d2 = None, -1.0
    for a in range(len(Z)):
        for b in range(a + 1, len(Z)):
            if d2[a, b] <= best_d2:
                continue
            line = (1.0 - t) * Z[a] + t * Z[b]
            if _kde_log_density(line, Z, bandwidth).min() >= floor:
                best, best_d2 = (a, b), d2[a, b]
    if best is None:
        a, b = np.unravel_index(int(np.argmax(d2)), d2.shape)
        best = (int(min(a, b)), int(max(a, b)))
    return best


def latent_morph(model, z_start, z_end, steps: int = 7) -> dict:
    """Decode z(t) = (1 − t) z_a + t z_b, t = 0 .. 1 in `steps` equal steps (Fig. 5.12).

    Returns t, the latents, the shapes (steps, 3L) and the step lengths d(frame_k, frame_k+1)
    (a smooth morph has near-equal steps)."""
    t = np.linspace(0.0, 1.0, steps)
    Z = (1.0 - t)[:, None] * np.asarray(z_start)[None, :] + t[:, None] * np.asarray(z_end)[None, :]
    shapes = model.decode(Z)
    step = np.array([landmark_rms_matrix(shapes[k], shapes[k + 1])[0, 0] for k in range(steps - 1)])
    return {"t": t, "latents": Z, "shapes": shapes, "step": step}


# ============================================================================ the whole run
@dataclass
class EvaluationSettings:
    """Settings of one evaluation run (all recorded in the report).

    models: model names (MODEL_TYPES keys). folds: k of the k-fold protocol used by
    completion, held-out reconstruction, held-out likelihood and MMD / coverage / 1-NNA.
    seed: every random choice (fold split, samples, inducing points) derives from it.
    n_samples: samples of the full-data models for novelty / specificity.
    latent_dim: None = each model's 80 % explained-variance rule, else fixed for all models.
    regions: completion regions (REGIONS keys). max_curve_dim: cap of q / m in the PPCA
    curves. latent_map: fit the 2-D GP-LVM map and morph.
    """

    models: list[str] = field(default_factory=lambda: ["ppca", "gplvm", "bgplvm"])
    folds: int = 5
    seed: int = 0
    n_samples: int = 100
    latent_dim: int | None = None
    regions: list[str] = field(default_factory=lambda: ["top", "middle", "rear"])
    max_curve_dim: int = 40
    latent_map: bool = True
    morph_steps: int = 7

    def validate(self, n_shapes: int) -> None:
        self.models = parse_model_names(self.models)
        unknown = [r for r in self.regions if r not in REGIONS]
        if unknown or not self.regions:
            raise EvaluationError(f"unknown completion region(s) {unknown} (known: {', '.join(REGIONS)})")
        if n_shapes < 4:
            raise EvaluationError(f"evaluation needs at least 4 shapes, got {n_shapes}")
        if isinstance(self.folds, bool) or not isinstance(self.folds, (int, np.integer)) or self.folds < 2:
            raise EvaluationError(f"--folds must be an integer >= 2, got {self.folds!r}")
        if self.folds > n_shapes:
            raise EvaluationError(f"--folds {self.folds} is more than the {n_shapes} shapes of the collection")
        smallest_train = n_shapes - -(-n_shapes // self.folds)
        if smallest_train < 3:
            raise EvaluationError(f"with {n_shapes} shapes and {self.folds} folds a training fold has only "
                                  f"{smallest_train} shapes; use fewer folds")
        if self.latent_dim is not None and not 1 <= self.latent_dim < smallest_train:
            raise EvaluationError(f"--latent-dim {self.latent_dim} must be between 1 and {smallest_train - 1} "
                                  f"(the smallest training fold has {smallest_train} shapes)")
        if self.n_samples < 1:
            raise EvaluationError(f"n_samples must be >= 1, got {self.n_samples}")


@dataclass
class EvaluationResult:
    """Numbers (`report`, JSON-ready after report.py's cleaning) and the arrays the figures
    show (`figures`: point sets in the normalised frame)."""

    report: dict
    figures: dict
    timings: dict


def run_evaluation(Y, names: Sequence[str], settings: EvaluationSettings,
                   progress: Progress | None = None, extra: dict | None = None) -> EvaluationResult:
    """Every metric of this module on the landmark matrix Y (N × 3L) for `settings.models`.

    Protocol: one random k-fold split (seed). Per fold and model: fit on the training folds;
    complete each region of the held-out shapes; reconstruct them (decode ∘ encode); score
    them; draw |test| samples for MMD / coverage / 1-NNA against them. Baselines ride along
    (training-set memoriser, mean shape). Per model on all shapes: `n_samples` samples for
    novelty / specificity. PPCA curves: held-out NLL vs q (k-fold), generalisation and
    specificity vs modes. Finally the 2-D GP-LVM latent map with outlier scores and a morph.
    """
    report_progress = progress or (lambda fraction, message: None)
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim != 2 or Y.shape[1] % 3 or not np.all(np.isfinite(Y)):
        raise EvaluationError(f"landmark matrix must be a finite (N, 3L) array, got shape {Y.shape}")
    n, n_coords = Y.shape
    names = list(names)
    settings.validate(n)
    seed = settings.seed
    folds = kfold_indices(n, settings.folds, _rng(seed, 1))
    timings: dict[str, float] = {}
    figures: dict = {"names": names, "data": as_point_sets(Y)}

    baselines = {"training-set": TrainingSetModel, "mean-shape": MeanShapeModel}
    all_models = list(settings.models) + list(baselines)
    per_model = {name: {"completion": {r: np.full(n, np.nan) for r in settings.regions},
                        "completion_relative": {r: np.full(n, np.nan) for r in settings.regions},
                        "reconstruction": np.full(n, np.nan), "heldout_ll": [], "mmd": [], "coverage": [],
                        "one_nna": [], "latent_dims": [], "fit_seconds": []}
                 for name in all_models}
    hidden_counts = {r: [] for r in settings.regions}
    hidden_landmarks_of_shape = {r: np.zeros(n) for r in settings.regions}
    completion_examples = {}
    steps_total = settings.folds * len(all_models) + len(settings.models) + 3
    step = 0

    for f, test_idx in enumerate(folds):
        train_idx = np.setdiff1d(np.arange(n), test_idx)
        Y_train, Y_test = Y[train_idx], Y[test_idx]
        train_mean = Y_train.mean(0)
        masks = {r: hidden_coordinates(region_mask(train_mean, r)) for r in settings.regions}
        for r in settings.regions:
            hidden_counts[r].append(int(masks[r].sum()) // 3)
            hidden_landmarks_of_shape[r][test_idx] = masks[r].sum() // 3
        for name in all_models:
            report_progress(step / steps_total, f"fold {f + 1}/{settings.folds}: {name}")
            step += 1
            start = time.perf_counter()
            model = (baselines[name]() if name in baselines
                     else make_model(name, settings.latent_dim, seed + f))
            model.fit(Y_train)
            stats = per_model[name]
            stats["fit_seconds"].append(time.perf_counter() - start)
            stats["latent_dims"].append(int(model.latent_dim))
            for r, hidden in masks.items():
                observed = np.broadcast_to(~hidden, Y_test.shape).copy()
                completed = model.complete(np.where(observed, Y_test, np.nan), observed)
                err = completion_errors(Y_test, completed, hidden)
                mean_err = np.sum((train_mean[hidden] - Y_test[:, hidden]) ** 2, 1)
                stats["completion"][r][test_idx] = err
                stats["completion_relative"][r][test_idx] = err / mean_err
                if f == 0:
                    completion_examples.setdefault(r, {"truth": as_point_sets(Y_test[0])[0],
                                                      "name": names[test_idx[0]],
                                                      "hidden": hidden[::3].copy(), "models": {}})
                    completion_examples[r]["models"][name] = as_point_sets(completed[0])[0]
            sample_rng = _rng(seed, 2, f, all_models.index(name))
            samples = model.sample(len(test_idx), sample_rng)
            stats["mmd"].append(mmd(samples, Y_test))
            stats["coverage"].append(coverage(samples, Y_test))
            stats["one_nna"].append(one_nna(samples, Y_test))
            if name not in baselines:
                stats["reconstruction"][test_idx] = np.diag(landmark_rms_matrix(Y_test, model.decode(model.encode(Y_test))))
                stats["heldout_ll"].append(float(model.score(Y_test)))
            timings[f"fold{f}:{name}"] = time.perf_counter() - start

    # ---- full-data models: novelty / specificity, figures
    full = {}
    samples_fig = {}
    training_nn = procrustes_rms_matrix(Y, Y)
    np.fill_diagonal(training_nn, np.inf)
    training_nn_median = float(np.median(training_nn.min(1)))
    for name in settings.models:
        report_progress(step / steps_total, f"all shapes: {name}")
        step += 1
        start = time.perf_counter()
        model = make_model(name, settings.latent_dim, seed).fit(Y)
        samples = model.sample(settings.n_samples, _rng(seed, 3, settings.models.index(name)))
        nov = novelty(samples, Y)
        full[name] = {"latent_dim": int(model.latent_dim), "novelty": nov}
        samples_fig[name] = {"samples": as_point_sets(samples), "nearest": nov["nearest"],
                             "distance": nov["distance"]}
        timings[f"all:{name}"] = time.perf_counter() - start
    figures["samples"] = samples_fig
    figures["completion"] = completion_examples

    # ---- PPCA curves
    report_progress(step / steps_total, "PPCA curves")
    step += 1
    start = time.perf_counter()
    nll = ppca_nll_curve(Y, folds, settings.max_curve_dim)
    gen = generalisation_curve(Y, settings.max_curve_dim)
    spec = specificity_curve(Y, settings.n_samples, seed, min(settings.max_curve_dim, 20))
    timings["ppca_curves"] = time.perf_counter() - start
    figures["curves"] = {"nll": nll, "generalisation": gen, "specificity": spec}

    # ---- latent map and morph
    latent_section = None
    if settings.latent_map:
        report_progress(step / steps_total, "2-D latent map (GP-LVM)")
        start = time.perf_counter()
        gp2 = GPLVM(n_components=2).fit(Y)
        Z = gp2.latents_
        outliers = latent_outlier_scores(Z, gp2.kde_bandwidth_)
        a, b = choose_morph_endpoints(Z, gp2.kde_bandwidth_)
        morph = latent_morph(gp2, Z[a], Z[b], settings.morph_steps)
        endpoint_error = [float(landmark_rms_matrix(morph["shapes"][0], Y[a])[0, 0]),
                          float(landmark_rms_matrix(morph["shapes"][-1], Y[b])[0, 0])]
        latent_section = {
            "model": "gplvm", "latent_dim": 2, "kde_bandwidth": gp2.kde_bandwidth_,
            "points": {nm: [float(v) for v in z] for nm, z in zip(names, Z)},
            "outlier_score": dict(zip(names, outliers["score"])),
            "outlier_robust_z": dict(zip(names, outliers["robust_z"])),
            "outliers": [nm for nm, flag in zip(names, outliers["flagged"]) if flag],
            "morph": {"from": names[a], "to": names[b], "steps": settings.morph_steps,
                      "step_rms": morph["step"], "step_ratio_max_min": float(morph["step"].max() / morph["step"].min())
                      if morph["step"].min() > 0 else None,
                      "endpoint_rms": endpoint_error},
        }
        figures["latent_map"] = {"latents": Z, "score": outliers["robust_z"], "flagged": outliers["flagged"],
                                 "morph": morph, "from": a, "to": b}
        timings["latent_map"] = time.perf_counter() - start
    report_progress(1.0, "evaluation done")

    # ---- assemble the report (plain Python values; report.py rounds and writes)
    def summary(values) -> dict:
        values = np.asarray(values, dtype=float)
        return {"mean": float(np.mean(values)), "sd": float(np.std(values, ddof=1)) if values.size > 1 else 0.0}

    models_report = {}
    for name in all_models:
        stats = per_model[name]
        entry = {
            "kind": "baseline" if name in baselines else "model",
            "latent_dim_per_fold": stats["latent_dims"],
            "completion": {
                r: {"mean_sse": float(np.mean(stats["completion"][r])),
                    "sd_sse": float(np.std(stats["completion"][r], ddof=1)),
                    "mean_rms_per_hidden_landmark": float(np.mean(np.sqrt(
                        stats["completion"][r] / hidden_landmarks_of_shape[r]))),
                    "relative_to_mean_shape": float(np.mean(stats["completion_relative"][r])),
                    "per_shape": dict(zip(names, stats["completion"][r]))}
                for r in settings.regions},
            "heldout_samples": {"mmd": summary(stats["mmd"]), "coverage": summary(stats["coverage"]),
                                "one_nna": summary(stats["one_nna"])},
        }
        if name not in baselines:
            entry["heldout_reconstruction_rms"] = {**summary(stats["reconstruction"]),
                                                   "per_shape": dict(zip(names, stats["reconstruction"]))}
            entry["heldout_log_likelihood"] = {**summary(stats["heldout_ll"]), "per_fold": stats["heldout_ll"]}
            nov = full[name]["novelty"]
            entry["all_shapes"] = {
                "latent_dim": full[name]["latent_dim"],
                "specificity": float(np.mean(nov["distance"])),
                "novelty": {"mean": float(np.mean(nov["distance"])), "median": float(np.median(nov["distance"])),
                            "min": float(np.min(nov["distance"])), "max": float(np.max(nov["distance"])),
                            "relative_to_training_nn_median": float(np.median(nov["distance"]) / training_nn_median)
                            if training_nn_median > 0 else None,
                            "per_sample": nov["distance"].tolist(),
                            "nearest": [names[i] for i in nov["nearest"]]},
            }
        models_report[name] = entry

    report = {
        "format": "shapegen.evaluation",
        "format_version": 1,
        "data": {"n_shapes": n, "n_landmarks": n_coords // 3, "names": names,
                 "training_nn_median_procrustes_rms": training_nn_median, **(extra or {})},
        "settings": {"models": settings.models, "folds": settings.folds, "seed": seed,
                     "n_samples": settings.n_samples, "latent_dim": settings.latent_dim,
                     "regions": list(settings.regions), "max_curve_dim": settings.max_curve_dim,
                     "fold_test_sets": [[names[i] for i in f] for f in folds],
                     "hidden_landmarks_per_fold": hidden_counts,
                     "one_nna_chance_level": float(np.mean([one_nna_chance_level(len(f)) for f in folds]))},
        "models": models_report,
        "ppca_curves": {
            "nll_vs_latent_dim": {"latent_dims": nll["latent_dims"], "train_nll": nll["train_nll"],
                                  "test_nll": nll["test_nll"], "test_nll_stderr": nll["test_nll_stderr"],
                                  "best_latent_dim": nll["best_latent_dim"]},
            "generalisation_loo": {"modes": gen["modes"], "mean": gen["mean"], "stderr": gen["stderr"]},
            "specificity": {"modes": spec["modes"], "mean": spec["mean"]},
        },
        "latent_map": latent_section,
    }
    return EvaluationResult(report=report, figures=figures, timings=timings)
