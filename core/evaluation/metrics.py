"""Distances between corresponding shapes and the sample-quality metrics built on them
(thesis §5.5.2; Styner et al. 2003; Gretton et al. 2012; Achlioptas et al. 2018;
Lopez-Paz & Oquab 2017).

A shape is a row y ∈ R^{3L} of the landmark matrix or L points p_1..p_L ∈ R^3.

Distances between two shapes a, b (L points each)
-------------------------------------------------
* per-landmark RMS            d(a, b)   = sqrt( (1/L) Σ_l ‖a_l − b_l‖² )
* Procrustes (similarity) RMS d_P(a→b) = min_{s>0, R∈SO(3), t} sqrt( (1/L) Σ_l ‖s R a_l + t − b_l‖² )
  closed form (Umeyama 1991): with centred ā, b̄ and H = āᵀ b̄ = U Σ Vᵀ,
  d_P² = (‖b̄‖² − (σ_1 + σ_2 + δ σ_3)² / ‖ā‖²) / L,  δ = sign det(V Uᵀ).
  It aligns the first argument onto the second (not symmetric when scales differ).

Metrics
-------
* novelty(s) = min_n d_P(s → y_n) per sample s (thesis §5.5.2, Fig. 5.7).
* specificity (Styner et al. 2003) = (1/S) Σ_s min_n d_P(s → y_n): mean distance of S model
  samples to their nearest training shape (ShapeWorks / Scalismo `specificity`); small =
  samples look like data.
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
"""

from __future__ import annotations

import numpy as np

from ..base.errors import ShapeGenError
from ..models.kernels import rbf_from_sq_dists

__all__ = [
    "EvaluationError",
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
]


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
        return float(np.mean(rbf_from_sq_dists(landmark_rms_matrix(P, Q) ** 2, 1.0, h * h)))

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
