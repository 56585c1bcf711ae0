"""Outlier flags of a correspondence, each with a reason a user can act on.

A shape is flagged when any one rule holds (thresholds in `CorrespondenceSettings`):
* residual: its data-term residual (registration.py `fit_residual`) is far above the
  collection's median;
* size: its bounding-box diagonal differs from the template's by a large factor;
* leave-one-out reconstruction: its corresponded landmarks are far from their
  reconstruction in a PPCA shape model (§5.3.1) of the *other* shapes. A shape turned
  upside down, turned about its axis, mirrored or of another class can still fit its own
  surface closely (small residual), but its landmarks then sit on the wrong parts, so no
  combination of the other shapes' modes reproduces them. Above 200 shapes the model
  leaves out one of 20 interleaved groups (its shapes among them) instead of one shape.
"""

from __future__ import annotations

import numpy as np

from .settings import CorrespondenceSettings

__all__ = ["flag_outliers", "held_out_groups", "leave_one_out_errors", "robust_scores"]

#: fewest shapes for which the robust (median/MAD) rules are used
MIN_SHAPES_ROBUST = 3
#: fewest shapes for the leave-one-out model (it is fitted to the other M - 1 >= 4)
MIN_SHAPES_LEAVE_ONE_OUT = 5
#: up to this many shapes each is left out alone; beyond, LEAVE_OUT_GROUPS groups
LEAVE_ONE_OUT_SHAPES, LEAVE_OUT_GROUPS = 200, 20


def leave_one_out_errors(points: np.ndarray, variance: float) -> np.ndarray:
    """e_i = RMS over landmarks of ‖y_i − ŷ_i‖, ŷ_i = μ + W Wᵀ (y_i − μ): the
    reconstruction of shape i (landmarks (L, 3), flattened to y_i) from the PPCA model of
    the other shapes (§5.3.1; μ their mean, W the maximum-likelihood principal subspace
    in its noise-free limit: the fewest principal directions explaining `variance` of
    their variance). points: (M, L, 3). Above LEAVE_ONE_OUT_SHAPES shapes the model
    leaves out a group instead (`held_out_groups`): one SVD per shape made this O(M³ L)
    (1000 shapes of 800 landmarks: about 1000 s)."""
    points = np.asarray(points, dtype=np.float64)
    flat = points.reshape(len(points), -1)
    errors = np.empty(len(points))
    for held in held_out_groups(len(points)):
        others = np.delete(flat, held, axis=0)
        mean = others.mean(axis=0)
        _, singular, directions = np.linalg.svd(others - mean, full_matrices=False)
        energy = singular ** 2
        total = energy.sum()
        rank = 0 if total <= 0 else int(np.searchsorted(np.cumsum(energy) / total, variance) + 1)
        basis = directions[:rank]
        for i in held:
            offset = flat[i] - mean
            residual = offset - (offset @ basis.T) @ basis
            errors[i] = np.sqrt((residual.reshape(-1, 3) ** 2).sum(axis=1).mean())
    return errors


def held_out_groups(count: int) -> list[list[int]]:
    """The shapes each model of `leave_one_out_errors` leaves out: each shape alone up to
    LEAVE_ONE_OUT_SHAPES shapes, else LEAVE_OUT_GROUPS interleaved groups (i mod groups):
    a shape's model is still fitted without it, from all but 1/LEAVE_OUT_GROUPS of the
    others."""
    if count <= LEAVE_ONE_OUT_SHAPES:
        return [[i] for i in range(count)]
    return [list(range(g, count, LEAVE_OUT_GROUPS)) for g in range(LEAVE_OUT_GROUPS)]


def robust_scores(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(ratio to the median, robust z-score (v − median) / (1.4826 · MAD), median)."""
    values = np.asarray(values, dtype=np.float64)
    median = float(np.median(values))
    mad = 1.4826 * float(np.median(np.abs(values - median)))
    ratios = values / median if median > 0 else np.where(values > 0, np.inf, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(values > median, (values - median) / mad if mad > 0 else np.inf, 0.0)
    return ratios, z, median


def flag_outliers(residuals: np.ndarray, scale_ratios: np.ndarray,
                  settings: CorrespondenceSettings = CorrespondenceSettings(),
                  points: np.ndarray | None = None) -> list[str]:
    """A reason string per shape ("" = fits). Rules (any one flags):
    (`settings.outliers`) residual: residual > median + `residual_mad_factor` · 1.4826 · MAD
    and > `residual_min_ratio` × median (needs 3+ shapes), or > `max_residual`; size:
    bounding-box diagonal differs from the
    template's by more than `max_scale_ratio` (either way); leave-one-out (with the
    corresponded `points` (M, L, 3) of 5+ shapes): reconstruction error
    (`leave_one_out_errors`) > median + `loo_mad_factor` · 1.4826 · MAD and >
    `loo_min_ratio` × median."""
    rules = settings.outliers
    residuals = np.asarray(residuals, dtype=np.float64)
    count = len(residuals)
    residual_ratios, residual_z, median = robust_scores(residuals)
    if points is not None and count >= MIN_SHAPES_LEAVE_ONE_OUT:
        loo_ratios, loo_z, _ = robust_scores(leave_one_out_errors(points, rules.loo_variance))
    else:
        loo_ratios = loo_z = np.zeros(count)
    reasons = []
    for i, (residual, ratio) in enumerate(zip(residuals, scale_ratios)):
        why = []
        if count >= MIN_SHAPES_ROBUST and residual_z[i] > rules.residual_mad_factor \
                and residual_ratios[i] > rules.residual_min_ratio:
            why.append(f"residual {residual:.4f} of the diagonal is far above the collection's median {median:.4f}")
        elif residual > rules.max_residual:
            why.append(f"residual {residual:.4f} of the diagonal exceeds {rules.max_residual}")
        if ratio > rules.max_scale_ratio or ratio < 1.0 / rules.max_scale_ratio:
            why.append(f"size is {ratio:.3g}× the template's (alignment or scaling failed or is off)")
        if loo_z[i] > rules.loo_mad_factor and loo_ratios[i] > rules.loo_min_ratio:
            why.append(f"landmarks {loo_ratios[i]:.1f}× farther from the other shapes' model than the median shape "
                       "(leave-one-out reconstruction; upside down, turned, mirrored or another class?)")
        reasons.append("; ".join(why))
    return reasons
