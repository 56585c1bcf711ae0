"""Spherical Gaussian kernel density estimate over latent points (thesis §5.4.3).

The GP-LVM samples its latents from it, and the evaluation's latent map scores outliers and
checks morph paths with it. For centres z_1..z_N in R^Q and bandwidth h:

  log density          log p_h(x) = log (1/N) sum_j N(x | z_j, h^2 I)
  leave-one-out        log p_h^(-i)(z_i) = log (1/(N-1)) sum_{j != i} N(z_i | z_j, h^2 I)
  bandwidth            the h of a log grid (1/100 to 10 times the median nearest-neighbour
                       distance) with the highest mean leave-one-out log density
  sampling             x = z_j + h e, j uniform, e ~ N(0, I)
"""

from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from .kernels import sq_dists

__all__ = ["log_density", "leave_one_out_log_density", "leave_one_out_bandwidth", "sample"]


def _log_kernels(d2: np.ndarray, bandwidth: float, q: int) -> np.ndarray:
    """log N(x | z, h^2 I) from squared distances |x - z|^2."""
    return -0.5 * d2 / bandwidth**2 - q * np.log(bandwidth) - 0.5 * q * np.log(2 * np.pi)


def _sq_dists_to_others(centres: np.ndarray) -> np.ndarray:
    """|z_i - z_j|^2 with +inf on the diagonal (a centre is not its own neighbour)."""
    d2 = sq_dists(centres, centres)
    np.fill_diagonal(d2, np.inf)
    return d2


def _leave_one_out(d2_others: np.ndarray, bandwidth: float, q: int) -> np.ndarray:
    return logsumexp(_log_kernels(d2_others, bandwidth, q), axis=1) - np.log(len(d2_others) - 1)


def log_density(points: np.ndarray, centres: np.ndarray, bandwidth: float) -> np.ndarray:
    """log p_h at each row of `points` (n, Q), (n,)."""
    log_k = _log_kernels(sq_dists(points, centres), bandwidth, centres.shape[1])
    return logsumexp(log_k, axis=1) - np.log(len(centres))


def leave_one_out_log_density(centres: np.ndarray, bandwidth: float) -> np.ndarray:
    """log p_h^(-i)(z_i) of each centre under the estimate of the others, (N,)."""
    return _leave_one_out(_sq_dists_to_others(centres), bandwidth, centres.shape[1])


def leave_one_out_bandwidth(centres: np.ndarray, n_grid: int = 60) -> float:
    """The grid bandwidth with the highest mean leave-one-out log density (module docstring)."""
    q = centres.shape[1]
    d2 = _sq_dists_to_others(centres)
    nn = np.sqrt(np.min(d2, 1))
    scale = np.median(nn[np.isfinite(nn)]) if np.any(nn > 0) else 1.0
    scale = scale if scale > 0 else 1.0
    grid = scale * np.geomspace(1e-2, 10.0, n_grid)
    scores = [np.mean(_leave_one_out(d2, h, q)) for h in grid]
    return float(grid[int(np.argmax(scores))])


def sample(centres: np.ndarray, bandwidth: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """n draws from the estimate, (n, Q)."""
    chosen = centres[rng.integers(0, centres.shape[0], n)]
    return chosen + bandwidth * rng.standard_normal(chosen.shape)
