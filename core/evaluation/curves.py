"""Curves of PPCA against its number of modes / latent dimension (thesis §5.5.4, Fig. 5.10;
Styner et al. 2003).

* generalisation G(m) = (1/N) Σ_i d(y_i, ŷ_i^{(m)}): leave-one-out reconstruction error,
  ŷ_i^{(m)} the projection of y_i onto the first m modes of the PCA of the other N − 1
  shapes (ShapeWorks / Scalismo `generalization`).
* specificity S(m): mean d_P of PPCA samples (m modes, fitted on all shapes) to their
  nearest training shape.
* held-out NLL: k-fold mean negative log-likelihood per shape of PPCA on training and
  held-out folds, −(1/n) Σ log N(y | μ, WWᵀ + σ²I), for q = 1 .. q_max.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..models import ModelInputError, PPCA
from .metrics import EvaluationError, landmark_rms_matrix, specificity
from .protocol import random_stream

__all__ = ["generalisation_curve", "specificity_curve", "ppca_nll_curve"]


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
        values.append(specificity(model.sample(n_samples, random_stream(seed, 7, m)), Y))
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
