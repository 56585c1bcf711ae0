"""Gaussian process latent variable model (thesis §5.3.3, Lawrence 2005; docs/method.md §4).

Y (N x D, centred) = f(Z) + noise with independent GPs per coordinate:
  K = s_f^2 exp(-|z - z'|^2 / (2 l^2)) + beta^-1 I                       (eq. 5.38)
  log p(Y | Z) = -(N D / 2) log 2 pi - (D / 2) log|K| - 1/2 tr(K^-1 Y Y^T)   (eq. 5.34)
maximised (with the N(0, I) latent prior, MAP) over Z and (log s_f^2, log l, log beta) by
L-BFGS-B with analytic gradients (eq. 5.35 generalised: dL/dK = 1/2 (K^-1 Y Y^T K^-1 - D K^-1)).
Y Y^T is formed once, so an iteration costs O(N^3 + N^2 Q), whatever D. Z is initialised by
PCA; two starting points run briefly and the better one continues (latent_variable.py).

Sampling (§5.4.3): Gaussian KDE over the learnt Z (kde.py), spherical bandwidth chosen by
leave-one-out log-likelihood over a grid, mapped through the GP posterior mean (eq. 5.42).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..base.npzfile import ArraySpec
from ..base.progress import Progress
from . import kde
from .base import as_generator, pca_latents, standardised_pca_latents
from .kernels import rbf, rbf_from_sq_dists, sq_dists
from .latent_variable import (FitProblem, LatentVariableModel, OptimiserRun, TrainingData, best_start,
                              inverse_cholesky, lbfgs)

__all__ = ["GPLVM", "gplvm_log_likelihood", "MIN_LENGTHSCALE"]

_LOG_2PI = np.log(2.0 * np.pi)


def gplvm_log_likelihood(params: np.ndarray, YYt: np.ndarray, n_features: int, latent_dim: int):
    """log p(Y | Z, theta) (eq. 5.34) and its gradient w.r.t. params = [Z.ravel(), log s_f^2,
    log l, log beta]. Only Y Y^T (N x N) and D are needed."""
    n = YYt.shape[0]
    Z = params[: n * latent_dim].reshape(n, latent_dim)
    log_var, log_ls, log_beta = params[n * latent_dim:]
    variance, ls2, noise = np.exp(log_var), np.exp(2.0 * log_ls), np.exp(-log_beta)
    r2 = sq_dists(Z, Z)
    Kf = rbf_from_sq_dists(r2, variance, ls2)
    K = Kf.copy()
    K.flat[:: n + 1] += noise
    L_inv, log_det = inverse_cholesky(K, "K", log_det=True)
    K_inv = L_inv.T @ L_inv
    K_inv_YYt = K_inv @ YYt
    value = -0.5 * (n * n_features * _LOG_2PI + n_features * log_det + np.trace(K_inv_YYt))
    G = 0.5 * (K_inv_YYt @ K_inv - n_features * K_inv)        # dL/dK (symmetric)
    G = 0.5 * (G + G.T)
    T = G * Kf
    rows = T.sum(1)
    dZ = -(2.0 / ls2) * (rows[:, None] * Z - T @ Z)
    grad = np.concatenate([dZ.ravel(), [T.sum(), np.sum(T * r2) / ls2, -noise * np.trace(G)]])
    return value, grad


#: Lower bound of the RBF length-scale, in units of the (unit-spread, N(0, I)-prior) latents.
MIN_LENGTHSCALE = 0.25


class _MapProblem(FitProblem):
    """-(eq. 5.34 - 1/2 sum_n |z_n|^2) over [Z, log s_f^2, log l, log beta], bounded, from two
    starting points: (a) PCA latents (relative scales kept), noise 1 % of the data variance;
    (b) GPy's: PCA of the column-standardised data, each latent scaled to unit variance,
    noise 10 %. The final run stops once `stall` iterations together gained too little."""

    def __init__(self, data: TrainingData, progress: Progress | None, stall: tuple[int, float]):
        n, q, data_var = data.gram.shape[0], data.latent_dim, data.variance
        self.data, self.progress, self.stall = data, progress, stall
        # noise variance kept >= 1e-8 of the data variance so K stays positive definite;
        # length-scale kept >= MIN_LENGTHSCALE (latents start at unit spread and carry the
        # N(0, I) prior below): without both, few shapes (N = 6, Q = 2) let the optimiser
        # collapse to a white-noise kernel that memorises each shape and decodes every new
        # latent to the mean shape (measured: ℓ = 0.03 with latents spread 1–4)
        self.bounds = ([(None, None)] * (n * q)
                       + [(None, None), (np.log(MIN_LENGTHSCALE), None), (None, np.log(1e8 / data_var))])
        self.starts = [np.concatenate([Z0.ravel(), [np.log(data_var), 0.0, np.log(snr / data_var)]])
                       for Z0, snr in ((pca_latents(data.centred, q), 100.0),
                                       (standardised_pca_latents(data.centred, q), 10.0))]

    def objective(self, x):
        data = self.data
        n_latent = data.gram.shape[0] * data.latent_dim
        value, grad = gplvm_log_likelihood(x, data.gram, data.n_features, data.latent_dim)
        # MAP with the unit Gaussian latent prior of Lawrence (2005): −½ Σ ‖z_n‖²
        z = x[:n_latent]
        value = value - 0.5 * float(z @ z)
        grad = grad.copy()
        grad[:n_latent] -= z
        return -value, -grad

    def run(self, x, n_iter, span, final):
        stage, stopping = ("optimising latents", {"ftol": 0.0, "stall": self.stall}) if final else ("starting points", {})
        result = lbfgs(self.objective, x, max_iter=n_iter, progress=self.progress, message=f"GP-LVM: {stage}",
                       bounds=self.bounds, progress_span=span, **stopping)
        return OptimiserRun(result.x, -float(result.fun), int(result.nit), str(result.message))


class GPLVM(LatentVariableModel):
    """GP-LVM shape model with an RBF kernel.

    Parameters
    ----------
    n_components : int or None
        Latent dimension Q; None = the PPCA 80 % explained-variance rule (§5.4.1).
    max_iter : int
        At most this many L-BFGS-B iterations for Z and the hyperparameters (both starting
        points and the final run together).
    n_restarts : int
        Starting latents per row in encode / complete / score (best training latents).
    variance_fraction : float
        Fraction for the explained-variance rule.
    random_state : None, int or Generator
        Unused by the (deterministic) fit; kept for a uniform API.
    """

    model_type = "gplvm"
    _LABEL = "GP-LVM"
    # iterations per starting point before the better one continues; the final run stops once
    # 10 iterations together gained less than 1e-9 |objective| (not on one small step)
    _START_ITERS = 60
    _STALL = (10, 1e-9)
    _ARRAY_SPEC = {
        "model_type": ArraySpec("U", ()),
        "mean_": ArraySpec("f", ("D",)),
        "latents_": ArraySpec("f", ("N", "Q")),
        "alpha_": ArraySpec("f", ("N", "D")),
        "kernel_variance_": ArraySpec("f", ()),
        "lengthscale_": ArraySpec("f", ()),
        "noise_variance_": ArraySpec("f", ()),
        "kde_bandwidth_": ArraySpec("f", ()),
        "log_likelihood_": ArraySpec("f", ()),
        "param_n_components": ArraySpec("iu", ()),
        "param_max_iter": ArraySpec("iu", ()),
        "param_n_restarts": ArraySpec("iu", ()),
        "param_variance_fraction": ArraySpec("f", ()),
    }
    _POSITIVE = ("kernel_variance_", "lengthscale_", "noise_variance_", "kde_bandwidth_")

    def __init__(self, n_components: int | None = None, max_iter: int = 1000, n_restarts: int = 3,
                 variance_fraction: float = 0.8, random_state=None):
        self.n_components = n_components
        self.max_iter = max_iter
        self.n_restarts = n_restarts
        self.variance_fraction = variance_fraction
        self.random_state = random_state

    # ------------------------------------------------------------------ fit
    def _fit_problem(self, data, progress):
        return _MapProblem(data, progress, self._STALL)

    def _set_optimum(self, data, problem, optimum):
        """Latents and kernel from the optimum; eq. 5.34 there (without the prior); K^-1 Y for
        the posterior mean; the latent KDE's bandwidth."""
        x, n, q = optimum.x, data.gram.shape[0], data.latent_dim
        self.latents_ = x[: n * q].reshape(n, q).copy()
        log_var, log_ls, log_beta = x[n * q:]
        self.kernel_variance_ = float(np.exp(log_var))
        self.lengthscale_ = float(np.exp(log_ls))
        self.noise_variance_ = float(np.exp(-log_beta))
        self.log_likelihood_ = float(gplvm_log_likelihood(x, data.gram, data.n_features, q)[0])
        self._prepare()
        self.alpha_ = self._K_inv @ data.centred
        self.kde_bandwidth_ = kde.leave_one_out_bandwidth(self.latents_)

    def _prepare(self) -> None:
        """K^-1 of the training latents (scipy's Cholesky solve, as the decode basis K^-1 Y was
        always formed), and the row search's per-candidate constants: the training kernel
        matrix and the predictive variance at each training latent."""
        n = self.latents_.shape[0]
        Kf = self._kernel(self.latents_, self.latents_)
        self._K_inv = cho_solve(cho_factor(Kf + self.noise_variance_ * np.eye(n), lower=True), np.eye(n))
        self._train_kernel = Kf
        self._train_variance = self.kernel_variance_ + self.noise_variance_ - np.sum(Kf * (Kf @ self._K_inv), 1)
        self._row_candidates = self.latents_

    def _kernel(self, A, B) -> np.ndarray:
        return rbf(A, B, self.kernel_variance_, self.lengthscale_**2)

    @property
    def latent_dim(self) -> int:
        self._check_fitted()
        return int(self.latents_.shape[1])

    # ------------------------------------------------------------------ API
    def decode(self, Z) -> np.ndarray:
        """GP posterior mean k(z, Z) K^-1 Y + mean (eq. 5.42), (n, D)."""
        self._check_fitted()
        return self.mean_ + self._kernel(self._check_latents(Z), self.latents_) @ self.alpha_

    def decode_features(self, Z) -> np.ndarray:
        """decode(Z) = mean_ + decode_features(Z) @ decode_basis(): k(z, Z_train), (n, N)."""
        self._check_fitted()
        return self._kernel(self._check_latents(Z), self.latents_)

    def decode_basis(self) -> np.ndarray:
        """(N, D): K^-1 Y."""
        self._check_fitted()
        return self.alpha_

    def sample_latents(self, n: int, rng=None) -> np.ndarray:
        """z from the leave-one-out-bandwidth Gaussian KDE over the latents (§5.4.3), (n, Q)."""
        self._check_fitted()
        return kde.sample(self.latents_, self.kde_bandwidth_, self._check_count(n), as_generator(rng))

    def _search_row(self, args, scoring):
        """Optimise one row's latent against its observed coordinates y_o.

        First maximise log N(y_o | m_o(z), beta^-1 I), i.e. least squares between y_o and the
        GP posterior mean m(z) = k(z)^T K^-1 Y (encode / complete). scoring=True then
        maximises the full GP predictive density log N(y_o | m_o(z), s^2(z) I),
        s^2(z) = s_f^2 + beta^-1 - k^T K^-1 k, from the least-squares latent and the best
        training latents: `score` is its mean over rows, the density at the optimised latent (a
        point estimate of z, not a marginal over it, hence optimistic). With small noise its
        -D/2 log s^2(z) term pulls z onto training latents, which is why completion uses the
        mean fit. Starting points: the `n_restarts` training latents with the best objective.
        """
        c, R, rest, d_o = args
        resid = np.sum((c[:, None] - R @ self._train_kernel) ** 2, 0) + rest       # at each training latent
        z, value = best_start(self._row_mean_fit, self._best_candidates(-resid), args)
        if scoring:
            s2 = self._train_variance
            start_obj = -0.5 * d_o * np.log(2 * np.pi * s2) - 0.5 * resid / s2
            z, value = best_start(self._row_density, [z] + self._best_candidates(start_obj), args)
        return z, value

    def _predict_rows(self, found):
        return self.decode(found)

    def _feature_jacobian(self, z):
        """d k(z, Z_n) / dz = -k(z, Z_n) (z - Z_n) / l^2, (N, Q)."""
        diff = z[None, :] - self.latents_
        k = rbf_from_sq_dists(np.sum(diff**2, 1), self.kernel_variance_, self.lengthscale_**2)
        return -k[:, None] * diff / self.lengthscale_**2

    def _predictive_variance(self, z):
        """s_f^2 - k^T (K + beta^-1 I)^-1 k at z (eq. 5.42's variance, without the noise)."""
        k = self._kernel(z[None, :], self.latents_)[0]
        return max(self.kernel_variance_ - float(k @ self._K_inv @ k), 0.0)

    def _row_terms(self, z, c, R):
        """k(z), the residual |y_o - m_o(z)|^2 (minus `rest`), d resid / dk and dk / dz."""
        diff = z[None, :] - self.latents_
        k = rbf_from_sq_dists(np.sum(diff**2, 1), self.kernel_variance_, self.lengthscale_**2)
        e = c - R @ k
        dk_dz = -k[:, None] * diff / self.lengthscale_**2
        return k, float(e @ e), -2.0 * (R.T @ e), dk_dz

    def _row_mean_fit(self, z, c, R, rest, d_o):
        """-log N(y_o | m_o(z), beta^-1 I) and its gradient in z."""
        _, resid, dresid_dk, dk_dz = self._row_terms(z, c, R)
        s2 = self.noise_variance_
        ll = -0.5 * d_o * np.log(2 * np.pi * s2) - 0.5 * (resid + rest) / s2
        return -ll, dk_dz.T @ (0.5 * dresid_dk / s2)

    def _row_density(self, z, c, R, rest, d_o):
        """-log N(y_o | m_o(z), s^2(z) I) and its gradient in z."""
        k, resid, dresid_dk, dk_dz = self._row_terms(z, c, R)
        resid += rest
        K_inv_k = self._K_inv @ k
        s2 = max(self.kernel_variance_ + self.noise_variance_ - k @ K_inv_k, 1e-300)
        ll = -0.5 * d_o * np.log(2 * np.pi * s2) - 0.5 * resid / s2
        dll_dk = (d_o / s2 - resid / s2**2) * K_inv_k - 0.5 * dresid_dk / s2
        return -ll, -(dk_dz.T @ dll_dk)
