"""Gaussian process latent variable model (thesis §5.3.3, Lawrence 2005; method.md §4).

Y (N x D, centred) = f(Z) + noise with independent GPs per coordinate:
  K = s_f^2 exp(-|z - z'|^2 / (2 l^2)) + beta^-1 I                       (eq. 5.38)
  log p(Y | Z) = -(N D / 2) log 2 pi - (D / 2) log|K| - 1/2 tr(K^-1 Y Y^T)   (eq. 5.34)
maximised (with the N(0, I) latent prior, MAP) over Z and (log s_f^2, log l, log beta) by
L-BFGS-B with analytic gradients (eq. 5.35 generalised: dL/dK = 1/2 (K^-1 Y Y^T K^-1 - D K^-1)).
Y Y^T is formed once, so an iteration costs O(N^3 + N^2 Q), whatever D. Z is initialised by
PCA; two starting points run briefly and the better one continues (`GPLVM.fit`).

Sampling (§5.4.3): Gaussian KDE over the learnt Z, spherical bandwidth chosen by leave-one-out
log-likelihood over a grid, mapped through the GP posterior mean (eq. 5.42).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.lapack import dpotrf, dtrtri
from scipy.optimize import minimize
from scipy.special import logsumexp

from ..errors import ModelFileError
from .base import (ModelInputError, ProgressCallback, ShapeModel, as_generator, check_latent_dim,
                   check_rows, check_training_data, default_latent_dim, lbfgs, pca_latents,
                   standardised_pca_latents)
from .kernels import rbf, sq_dists

__all__ = ["GPLVM", "gplvm_log_likelihood"]

_LOG_2PI = np.log(2.0 * np.pi)


def gplvm_log_likelihood(params: np.ndarray, YYt: np.ndarray, n_features: int, latent_dim: int):
    """log p(Y | Z, theta) (eq. 5.34) and its gradient w.r.t. params = [Z.ravel(), log s_f^2,
    log l, log beta]. Only Y Y^T (N x N) and D are needed."""
    n = YYt.shape[0]
    Z = params[: n * latent_dim].reshape(n, latent_dim)
    log_var, log_ls, log_beta = params[n * latent_dim:]
    variance, ls2, noise = np.exp(log_var), np.exp(2.0 * log_ls), np.exp(-log_beta)
    r2 = sq_dists(Z, Z)
    Kf = variance * np.exp(-0.5 * r2 / ls2)
    K = Kf.copy()
    K.flat[:: n + 1] += noise
    L, info = dpotrf(K, lower=1, clean=1)                     # K = L L^T
    if info == 0:
        L_inv, info = dtrtri(L, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("K is not positive definite")
    K_inv = L_inv.T @ L_inv
    log_det = 2.0 * np.log(L.diagonal()).sum()
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


class GPLVM(ShapeModel):
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
    # iterations per starting point before the better one continues; the final run stops once
    # 10 iterations together gained less than 1e-9 |objective| (not on one small step)
    _START_ITERS = 60
    _STALL = (10, 1e-9)
    _ARRAY_SPEC = {
        "model_type": ("U", ()),
        "mean_": ("f", ("D",)),
        "latents_": ("f", ("N", "Q")),
        "alpha_": ("f", ("N", "D")),
        "kernel_variance_": ("f", ()),
        "lengthscale_": ("f", ()),
        "noise_variance_": ("f", ()),
        "kde_bandwidth_": ("f", ()),
        "log_likelihood_": ("f", ()),
        "param_n_components": ("i", ()),
        "param_max_iter": ("i", ()),
        "param_n_restarts": ("i", ()),
        "param_variance_fraction": ("f", ()),
    }

    def __init__(self, n_components: int | None = None, max_iter: int = 1000, n_restarts: int = 3,
                 variance_fraction: float = 0.8, random_state=None):
        self.n_components = n_components
        self.max_iter = max_iter
        self.n_restarts = n_restarts
        self.variance_fraction = variance_fraction
        self.random_state = random_state

    # ------------------------------------------------------------------ fit
    def fit(self, Y, progress: ProgressCallback | None = None) -> "GPLVM":
        """Maximise eq. 5.34 from a PCA initialisation; then fit the latent KDE. Returns self."""
        Y = check_training_data(Y)
        n, d = Y.shape
        mean = Y.mean(0)
        Yc = Y - mean
        q = (default_latent_dim(Yc, self.variance_fraction) if self.n_components is None
             else check_latent_dim(self.n_components, n))
        if progress is not None:
            progress(0.0, "GP-LVM: PCA initialisation")
        YYt = Yc @ Yc.T                                      # the only use of D-sized data
        data_var = np.trace(YYt) / (n * d)
        # noise variance kept >= 1e-8 of the data variance so K stays positive definite;
        # length-scale kept >= MIN_LENGTHSCALE (latents start at unit spread and carry the
        # N(0, I) prior below): without both, few shapes (N = 6, Q = 2) let the optimiser
        # collapse to a white-noise kernel that memorises each shape and decodes every new
        # latent to the mean shape (measured: ℓ = 0.03 with latents spread 1–4)
        bounds = ([(None, None)] * (n * q)
                  + [(None, None), (np.log(MIN_LENGTHSCALE), None), (None, np.log(1e8 / data_var))])

        def objective(x):
            value, grad = gplvm_log_likelihood(x, YYt, d, q)
            # MAP with the unit Gaussian latent prior of Lawrence (2005): −½ Σ ‖z_n‖²
            z = x[: n * q]
            value = value - 0.5 * float(z @ z)
            grad = grad.copy()
            grad[: n * q] -= z
            return -value, -grad

        # two starting points (the likelihood has several local optima; neither start wins on
        # all data): (a) PCA latents (relative scales kept), noise 1 % of the data variance;
        # (b) GPy's: PCA of the column-standardised data, each latent scaled to unit variance,
        # noise 10 %. Each runs `_START_ITERS` iterations; the better one continues.
        starts = [(pca_latents(Yc, q), 100.0), (standardised_pca_latents(Yc, q), 10.0)]
        n_start = int(min(self._START_ITERS, max(self.max_iter // 4, 1)))   # the final run keeps >= half
        candidates = []
        for i, (Z0, snr) in enumerate(starts):
            x0 = np.concatenate([Z0.ravel(), [np.log(data_var), 0.0, np.log(snr / data_var)]])
            result = lbfgs(objective, x0, max_iter=n_start, progress=progress, message="GP-LVM: starting points",
                           bounds=bounds, progress_span=(0.1 * i / len(starts), 0.1 * (i + 1) / len(starts)))
            candidates.append(result)
        best = min(candidates, key=lambda r: r.fun)
        n_start_total = sum(r.nit for r in candidates)
        result = lbfgs(objective, best.x, max_iter=max(self.max_iter - n_start_total, 1), progress=progress,
                       message="GP-LVM: optimising latents", bounds=bounds, progress_span=(0.1, 0.95),
                       ftol=0.0, stall=self._STALL)
        n_iter = n_start_total + result.nit
        x = result.x
        self.mean_ = mean
        self.latents_ = x[: n * q].reshape(n, q).copy()
        log_var, log_ls, log_beta = x[n * q:]
        self.kernel_variance_ = float(np.exp(log_var))
        self.lengthscale_ = float(np.exp(log_ls))
        self.noise_variance_ = float(np.exp(-log_beta))
        self.log_likelihood_ = float(gplvm_log_likelihood(x, YYt, d, q)[0])  # eq. 5.34, without the prior
        self.n_iter_ = int(n_iter)
        self.optimizer_message_ = str(result.message)
        self._prepare()
        self.alpha_ = self._K_inv @ Yc                       # K^-1 Y for the posterior mean
        self.kde_bandwidth_ = kde_bandwidth(self.latents_)
        if progress is not None:
            progress(1.0, "GP-LVM: done")
        return self

    def _prepare(self) -> None:
        n = self.latents_.shape[0]
        K = self._kernel(self.latents_, self.latents_) + self.noise_variance_ * np.eye(n)
        self._K_inv = cho_solve(cho_factor(K, lower=True), np.eye(n))

    def _kernel(self, A, B) -> np.ndarray:
        return rbf(A, B, self.kernel_variance_, self.lengthscale_)

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
        rng = as_generator(rng)
        n = self._check_count(n)
        centres = self.latents_[rng.integers(0, self.latents_.shape[0], n)]
        return centres + self.kde_bandwidth_ * rng.standard_normal(centres.shape)

    def sample(self, n: int, rng=None) -> np.ndarray:
        """z from the KDE over the latents (`sample_latents`), decoded."""
        return self.decode(self.sample_latents(n, rng))

    @staticmethod
    def _row_setup(A_o: np.ndarray, r_o: np.ndarray):
        """Per-row constants for the latent search, from the observed residual r_o = (y - mean)_o.

        With the thin QR A_o^T = Q R (A = K^-1 Y, N x D), |r_o - A_o^T k|^2 = |c - R k|^2 + rest,
        c = Q^T r_o, rest = |r_o|^2 - |c|^2: each later evaluation costs O(N^2 + NQ), not O(D),
        and is free of the cancellation in |r_o|^2 - 2 k^T A_o r_o + k^T A_o A_o^T k.
        """
        Q, R = np.linalg.qr(A_o.T)
        c = Q.T @ r_o
        return c, R, max(float(r_o @ r_o - c @ c), 0.0), r_o.size

    def _fit_rows(self, Y, mask, density: bool = False):
        """Optimise each row's latent against its observed coordinates y_o. Returns (Z, objective).

        density=False: maximise log N(y_o | m_o(z), beta^-1 I), i.e. least squares between y_o
          and the GP posterior mean m(z) = k(z)^T K^-1 Y (used by encode / complete).
        density=True: maximise the full GP predictive density log N(y_o | m_o(z), s^2(z) I),
          s^2(z) = s_f^2 + beta^-1 - k^T K^-1 k (used by score), started from the least-squares
          latents. (With small noise its -D/2 log s^2(z) term pulls z onto training latents, which
          is why completion uses the mean fit.)
        Starting points: the `n_restarts` training latents with the best objective.
        """
        R_all = np.where(mask, Y - self.mean_, 0.0)
        Kf = self._kernel(self.latents_, self.latents_)
        s2_train = self.kernel_variance_ + self.noise_variance_ - np.sum(Kf * (Kf @ self._K_inv), 1)
        n_starts = max(1, self.n_restarts)
        Z_out = np.empty((Y.shape[0], self.latent_dim))
        obj_out = np.empty(Y.shape[0])
        for i in range(Y.shape[0]):
            o = mask[i]
            args = self._row_setup(self.alpha_[:, o], R_all[i, o])
            c, R, rest, d_o = args
            resid = np.sum((c[:, None] - R @ Kf) ** 2, 0) + rest       # at each training latent
            starts = [self.latents_[j] for j in np.argsort(resid)[:n_starts]]
            best_z, best = self._best_start(self._row_mean_fit, starts, args)
            if density:
                start_obj = -0.5 * d_o * np.log(2 * np.pi * s2_train) - 0.5 * resid / s2_train
                starts = [best_z] + [self.latents_[j] for j in np.argsort(-start_obj)[:n_starts]]
                best_z, best = self._best_start(self._row_density, starts, args)
            Z_out[i], obj_out[i] = best_z, best
        return Z_out, obj_out

    @staticmethod
    def _best_start(objective, starts, args):
        best_z, best = None, -np.inf
        for z0 in starts:
            res = minimize(objective, z0, args=args, jac=True, method="L-BFGS-B", options={"maxiter": 200})
            if -res.fun > best:
                best_z, best = res.x, -res.fun
        return best_z, best

    def _row_terms(self, z, c, R):
        """k(z), the residual |y_o - m_o(z)|^2 (minus `rest`), d resid / dk and dk / dz."""
        diff = z[None, :] - self.latents_
        k = self.kernel_variance_ * np.exp(-0.5 * np.sum(diff**2, 1) / self.lengthscale_**2)
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

    def encode(self, Y) -> np.ndarray:
        """Latents whose posterior mean best fits each row (least squares, restarts from the best
        training latents), (n, Q)."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        return self._fit_rows(Y, np.ones(Y.shape, bool))[0]

    def score(self, Y) -> float:
        """Mean over rows of max_z log N(y | m(z), s^2(z) I): the GP predictive log density at the
        optimised latent (a point estimate of z, not a marginal over it, hence optimistic)."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        return float(np.mean(self._fit_rows(Y, np.ones(Y.shape, bool), density=True)[1]))

    def complete(self, Y_partial, observed_mask) -> np.ndarray:
        """Optimise each row's latent against its observed coordinates, decode, keep observed."""
        Y, mask = self._check_partial(Y_partial, observed_mask)
        Z, _ = self._fit_rows(np.where(mask, Y, 0.0), mask)
        return np.where(mask, Y, self.decode(Z))

    # ------------------------------------------------------------------ arrays
    def _array_value(self, key: str):
        if key == "param_n_components":
            return -1 if self.n_components is None else int(self.n_components)
        if key.startswith("param_"):
            return getattr(self, key[len("param_"):])
        return getattr(self, key)

    def _restore(self, a) -> None:
        for key in ("kernel_variance_", "lengthscale_", "noise_variance_", "kde_bandwidth_"):
            if not a[key] > 0:
                raise ModelFileError(f"GPLVM arrays: {key} must be positive")
        nc = int(a["param_n_components"])
        self.__init__(n_components=None if nc < 0 else nc, max_iter=int(a["param_max_iter"]),
                      n_restarts=int(a["param_n_restarts"]),
                      variance_fraction=float(a["param_variance_fraction"]))
        for key in ("mean_", "latents_", "alpha_"):
            setattr(self, key, a[key])
        for key in ("kernel_variance_", "lengthscale_", "noise_variance_", "kde_bandwidth_", "log_likelihood_"):
            setattr(self, key, float(a[key]))
        try:
            self._prepare()
        except np.linalg.LinAlgError:
            raise ModelFileError("GPLVM arrays: kernel matrix of the stored latents is not positive definite") from None


def kde_bandwidth(Z: np.ndarray, n_grid: int = 60) -> float:
    """Spherical Gaussian KDE bandwidth maximising the leave-one-out log-likelihood (§5.4.3)
    over a log grid spanning 1/100 to 10 times the median nearest-neighbour distance."""
    n, q = Z.shape
    d2 = sq_dists(Z, Z)
    np.fill_diagonal(d2, np.inf)
    nn = np.sqrt(np.min(d2, 1))
    scale = np.median(nn[np.isfinite(nn)]) if np.any(nn > 0) else 1.0
    scale = scale if scale > 0 else 1.0
    grid = scale * np.geomspace(1e-2, 10.0, n_grid)
    scores = []
    for h in grid:
        log_k = -0.5 * d2 / h**2 - q * np.log(h) - 0.5 * q * np.log(2 * np.pi)
        scores.append(np.mean(logsumexp(log_k, axis=1) - np.log(n - 1)))
    return float(grid[int(np.argmax(scores))])
