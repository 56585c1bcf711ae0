"""Bayesian GP-LVM (thesis §5.3.4; Titsias & Lawrence 2010; method.md §4).

Prior p(X) = prod_n N(x_n | 0, I), variational q(X) = prod_n N(mu_n, diag S_n), ARD RBF kernel
(kernels.py), M inducing inputs Z (default 20) and Gaussian noise beta^-1. The collapsed bound
(T&L 2010 eq. 14, with A = K_mm + beta Psi2, psi-statistics from kernels.PsiStatistics):

  F = (N D / 2) log(beta / 2 pi) - (D / 2) log|A K_mm^-1| - (beta / 2) tr(Y Y^T)
      + (beta^2 / 2) tr(A^-1 Psi1^T Y Y^T Psi1) - (beta D / 2) psi0 + (beta D / 2) tr(K_mm^-1 Psi2)
      - KL(q(X) || p(X)),      KL = 1/2 sum_nq (mu^2 + S - log S - 1).

It is maximised over mu, log S, Z, log s_f^2, log a (inverse squared length-scales) and log beta
by L-BFGS-B with analytic gradients. Y enters only through Y Y^T (formed once, N x N), so an
iteration costs O(N M^2 Q + N^2 M), whatever D. Optimiser details (`fit`): the latent scale of
each dimension, which only the KL term pins down, is profiled out (`profile_scale`); the blocks
are preconditioned by their measured curvature (`block_scales`). The bound has several local
optima, so two starting points (PCA latents with a noise warm-up; GPy's standardised PCA with
noise = data variance) run 40 iterations each and the better one continues; it stops when 10
iterations together gain less than 3e-6 |F|, at a single-iteration relative decrease below
1e7 eps (scipy's and GPy's default), or after `max_iter` iterations in all.

Prediction uses the optimal q(u_d) = N(K_mm B_d, K_mm A^-1 K_mm) with B = beta A^-1 Psi1^T Y
(M x D, one pass over D after the fit). For a new, possibly partial, shape y* with observed
coordinates o, q(x*) = N(mu*, diag S*) maximises the per-point bound given q(u):

  L(y*) = -(D_o / 2) log(2 pi / beta) - (beta / 2) [ |y*_o|^2 - 2 psi1* B_o y*_o
          + tr(psi2* (B_o B_o^T + D_o (A^-1 - K_mm^-1))) ] - (beta D_o / 2) psi0* - KL(q(x*) || p)

(the ELBO of the new point with q(u) fixed at its training optimum, i.e. the change of the
uncollapsed bound when y* is added). `score` reports its mean; `complete` decodes
E_q(x*)[f] = psi1(mu*, S*) B.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dpotrf, dtrtri
from scipy.optimize import minimize

from ..errors import ModelFileError
from .base import (ModelInputError, ProgressCallback, ShapeModel, as_generator, check_latent_dim,
                   check_rows, check_training_data, default_latent_dim, lbfgs, pca_latents,
                   standardised_pca_latents)
from .kernels import PsiStatistics, ard_rbf

__all__ = ["BayesianGPLVM", "bgplvm_bound", "BoundLayout", "gram_root", "profile_scale", "block_scales"]

_LOG_2PI = np.log(2.0 * np.pi)


class BoundLayout:
    """Packing of the parameter vector [mu, log S, Z, log s_f^2, log a, log beta]."""

    def __init__(self, n: int, q: int, m: int):
        self.n, self.q, self.m = n, q, m
        ends = np.cumsum([n * q, n * q, m * q, 1, q, 1])
        self.splits = ends[:-1]
        self.size = int(ends[-1])
        self._blocks = [slice(int(lo), int(hi)) for lo, hi in zip([0, *ends[:-1]], ends)]

    def unpack(self, x):
        """Views (mu, log S, Z, log s_f^2, log a, log beta) into x."""
        mu, log_S, Z, log_var, log_alpha, log_beta = (x[block] for block in self._blocks)
        n, q, m = self.n, self.q, self.m
        return mu.reshape(n, q), log_S.reshape(n, q), Z.reshape(m, q), log_var[0], log_alpha, log_beta[0]

    @staticmethod
    def pack(mu, log_S, Z, log_var, log_alpha, log_beta):
        return np.concatenate([mu.ravel(), log_S.ravel(), Z.ravel(), [log_var], log_alpha, [log_beta]])


def _factors(Kmm: np.ndarray, Psi2: np.ndarray, beta: float):
    """Factors of A = K_mm + beta Psi2 (M x M) through Cholesky factors only:
    K_mm = L L^T, X = L^-1 Psi2 L^-T (PSD), B = I + beta X = L^-1 A L^-T = R R^T, P = R^-1 L^-1.
    Then K_mm^-1 = L^-T L^-1, A^-1 = P^T P, log|A K_mm^-1| = log|B| = 2 sum log diag R.
    Returns (L^-1, R^-1, X, P, log|B|)."""
    L_inv = _inverse_cholesky(Kmm, "K_mm")
    X = L_inv @ Psi2 @ L_inv.T
    B = beta * X
    B.flat[:: B.shape[0] + 1] += 1.0
    R_inv, log_det_B = _inverse_cholesky(B, "I + beta L^-1 Psi2 L^-T", log_det=True)
    return L_inv, R_inv, X, R_inv @ L_inv, log_det_B


def _inverse_cholesky(matrix: np.ndarray, name: str, log_det: bool = False):
    """L^-1 for matrix = L L^T (lower), and log|matrix| if asked; LinAlgError if not PD."""
    L, info = dpotrf(matrix, lower=1, clean=1)
    if info == 0:
        L_inv, info = dtrtri(L, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"{name} is not positive definite")
    return (L_inv, 2.0 * np.log(L.diagonal()).sum()) if log_det else L_inv


def gram_root(YYt: np.ndarray) -> np.ndarray:
    """R (N x r) with R R^T = Y Y^T (from the N x N Gram matrix; clipped eigenvalues)."""
    w, U = np.linalg.eigh(YYt)
    keep = w > w.max() * 1e-14
    return U[:, keep] * np.sqrt(w[keep])


def bgplvm_bound(x: np.ndarray, layout: BoundLayout, Y_root: np.ndarray, n_features: int, jitter: float):
    """Collapsed bound F (module docstring) and its gradient w.r.t. the packed parameters.

    Y enters through any `Y_root` with Y_root Y_root^T = Y Y^T (Y itself, or `gram_root(Y Y^T)`,
    N x N, so the cost does not grow with D). K_mm carries a jitter of `jitter * s_f^2` on its
    diagonal. With the factors of `_factors` (A^-1 = P^T P, B = L^-1 A L^-T = R R^T) and
    G = P Psi1^T Y_root, V = R^-1 X, W = V L^-1:
      tr(A^-1 Psi1^T Y Y^T Psi1) = |G|^2 (a sum of squares), tr(K_mm^-1 Psi2) = tr X,
      dF/dK_mm = -beta^2 / 2 (D W^T W + A^-1 Psi1^T Y Y^T Psi1 A^-1)    (K^-1 - A^-1 = beta L^-T B^-1 X L^-1),
      dF/dPsi2 = beta^2 / 2 (D P^T W - beta A^-1 Psi1^T Y Y^T Psi1 A^-1),
      dF/dPsi1 = beta^2 Y Y^T Psi1 A^-1 = beta^2 Y_root G^T P,
    all without differences of large terms, which keeps F accurate when K_mm is ill-conditioned.
    """
    mu, log_S, Z, log_var, log_alpha, log_beta = layout.unpack(x)
    n, d = layout.n, n_features
    S, variance, alpha, beta = np.exp(log_S), np.exp(log_var), np.exp(log_alpha), np.exp(log_beta)
    psi = PsiStatistics(mu, S, Z, variance, alpha, jitter)
    L_inv, R_inv, X, P, log_det_B = _factors(psi.Kmm, psi.psi2, beta)
    G = P @ (psi.psi1.T @ Y_root)                                 # (M, r)
    tr_YYt = (Y_root * Y_root).sum()
    tr_E2 = (G * G).sum()                                         # tr(A^-1 Psi1^T Y Y^T Psi1)
    tr_X = np.trace(X)                                            # tr(K_mm^-1 Psi2)
    kl = 0.5 * (mu * mu + S - log_S - 1.0).sum()
    F = (0.5 * n * d * (log_beta - _LOG_2PI) - 0.5 * d * log_det_B - 0.5 * beta * tr_YYt
         + 0.5 * beta**2 * tr_E2 - 0.5 * beta * d * psi.psi0 + 0.5 * beta * d * tr_X - kl)
    V = R_inv @ X
    W = V @ L_inv
    GP = G.T @ P                                                  # Y_root^T Psi1 A^-1, (r, M)
    GG = GP.T @ GP                                                # A^-1 Psi1^T Y Y^T Psi1 A^-1
    PW = P.T @ W                                                  # L^-T B^-1 X L^-1 (symmetric)
    G_Kmm = -0.5 * beta**2 * (d * (W.T @ W) + GG)
    G_Psi2 = 0.5 * beta**2 * (0.5 * d * (PW + PW.T) - beta * GG)
    G_Psi1 = beta**2 * (Y_root @ GP)
    # dF/dbeta: the explicit terms, plus tr(dF/dA Psi2) with D/2 tr((I - B^-1) X) = beta D/2 |V|^2
    # and tr(A^-1 Psi1^T Y Y^T Psi1 A^-1 Psi2) = tr(K1^T X K1), K1 = R^-T G
    K1 = R_inv.T @ G
    dF_dbeta = (0.5 * n * d / beta - 0.5 * tr_YYt + beta * tr_E2 - 0.5 * d * psi.psi0
                + 0.5 * beta * d * (V * V).sum() - 0.5 * beta**2 * (K1 * (X @ K1)).sum())
    d_mu, d_S, d_Z, d_logvar, d_alpha = psi.gradients(-0.5 * beta * d, G_Psi1, G_Psi2, G_Kmm)
    return F, layout.pack(d_mu - mu, d_S * S - 0.5 * (S - 1.0), d_Z, d_logvar, d_alpha * alpha, dF_dbeta * beta)


def profile_scale(x: np.ndarray, layout: BoundLayout):
    """Map optimiser coordinates x~ = [mu~, log S~, Z~, ...] to bound parameters with the latent
    scale of each dimension profiled out.

    The data term of F is invariant under mu_q -> c mu_q, Z_q -> c Z_q, S_q -> c^2 S_q,
    a_q -> a_q / c^2 (per latent dimension q); only the KL term fixes c, at
    c_q^2 = N / sum_n (mu_nq^2 + S_nq). A gradient optimiser crawls along this nearly flat
    direction, so the optimiser works on x~ and c_q is always set to its optimum:
    mu = c mu~, log S = log S~ + 2 log c, Z = c Z~, log a = log a~ - 2 log c. Stationary points
    are those of F (dF/d log c = 0 at the optimal c). Returns (x, chain) where
    chain(dF/dx) = dF/dx~.
    """
    mu_t, log_S_t, Z_t, log_var, log_alpha_t, log_beta = layout.unpack(x)
    S_t = np.exp(log_S_t)
    total = (mu_t**2 + S_t).sum(0)                                  # (Q,)
    log_c = 0.5 * (np.log(layout.n) - np.log(total))
    c = np.exp(log_c)
    mu, Z = mu_t * c, Z_t * c
    x_actual = layout.pack(mu, log_S_t + 2.0 * log_c, Z, log_var, log_alpha_t - 2.0 * log_c, log_beta)

    def chain(grad):
        g_mu, g_logS, g_Z, g_logvar, g_logalpha, g_logbeta = layout.unpack(grad)
        g_logc = (mu * g_mu).sum(0) + 2.0 * g_logS.sum(0) + (Z * g_Z).sum(0) - 2.0 * g_logalpha
        return layout.pack(c * g_mu - g_logc * mu_t / total, g_logS - 0.5 * g_logc * S_t / total,
                           c * g_Z, g_logvar, g_logalpha, g_logbeta)
    return x_actual, chain


def block_scales(objective, x: np.ndarray, splits, h: float = 1e-4) -> np.ndarray:
    """Diagonal preconditioner for L-BFGS: per parameter block, 1 / sqrt(curvature) of the
    objective along a +-1 direction on that block (one gradient difference per block).
    L-BFGS starts from a scalar Hessian guess; blocks whose curvatures differ by orders of
    magnitude (latents vs. log noise precision) otherwise cost many iterations."""
    _, g0 = objective(x)
    rng = np.random.default_rng(0)
    scales = np.ones(x.size)
    for block in np.split(np.arange(x.size), splits):
        if block.size == 0:
            continue
        direction = np.zeros(x.size)
        direction[block] = rng.choice([-1.0, 1.0], block.size)
        try:
            _, g1 = objective(x + h * direction)
            curvature = abs(direction @ (g1 - g0)) / (h * block.size)
        except np.linalg.LinAlgError:
            curvature = np.nan
        if np.isfinite(curvature) and curvature > 0:
            scales[block] = 1.0 / np.sqrt(max(curvature, 1e-12))
    return scales


class BayesianGPLVM(ShapeModel):
    """Bayesian GP-LVM shape model (sparse variational, ARD RBF).

    Parameters
    ----------
    n_components : int or None
        Latent dimension Q; None = the PPCA 80 % explained-variance rule (§5.4.1).
    n_inducing : int
        Inducing inputs M (thesis: 20); capped at N.
    max_iter : int
        At most this many L-BFGS-B iterations, starting points included (thesis: 2000 SCG
        iterations); the fit usually stops earlier, once the bound stalls (module docstring).
    n_restarts : int
        Starting points per row in encode / complete / score (best training q(x_n)).
    variance_fraction : float
        Fraction for the explained-variance rule.
    random_state : None, int or Generator
        Seeds the choice of initial inducing inputs.
    jitter : float
        Added to the diagonal of K_mm relative to s_f^2. Any jitter keeps F a lower bound on
        log p(Y) (the inducing variables just become noisy), but a larger one loosens it.
    """

    model_type = "bgplvm"
    # L-BFGS-B relative-decrease tolerance: scipy's (and GPy's) default factr = 1e7
    _FTOL = 1e7 * np.finfo(float).eps
    # the final run also stops once 10 iterations together gained less than 3e-6 |F|
    _STALL = (10, 3e-6)
    # iterations per starting point before the better one continues; noise warm-up of start (a)
    _START_ITERS = 40
    _WARM_UP = 15
    _ARRAY_SPEC = {
        "model_type": ("U", ()),
        "mean_": ("f", ("D",)),
        "latent_mean_": ("f", ("N", "Q")),
        "latent_variance_": ("f", ("N", "Q")),
        "inducing_": ("f", ("M", "Q")),
        "kernel_variance_": ("f", ()),
        "inverse_lengthscales_": ("f", ("Q",)),
        "noise_variance_": ("f", ()),
        "jitter_": ("f", ()),
        "B_": ("f", ("M", "D")),
        "elbo_": ("f", ()),
        "param_n_components": ("i", ()),
        "param_n_inducing": ("i", ()),
        "param_max_iter": ("i", ()),
        "param_n_restarts": ("i", ()),
        "param_variance_fraction": ("f", ()),
    }

    def __init__(self, n_components: int | None = None, n_inducing: int = 20, max_iter: int = 2000,
                 n_restarts: int = 3, variance_fraction: float = 0.8, random_state=None,
                 jitter: float = 1e-6):
        self.n_components = n_components
        self.n_inducing = n_inducing
        self.max_iter = max_iter
        self.n_restarts = n_restarts
        self.variance_fraction = variance_fraction
        self.random_state = random_state
        self.jitter = jitter

    # ------------------------------------------------------------------ fit
    def fit(self, Y, progress: ProgressCallback | None = None) -> "BayesianGPLVM":
        """Maximise the collapsed bound from a PCA initialisation; returns self."""
        Y = check_training_data(Y)
        n, d = Y.shape
        rng = as_generator(self.random_state)
        if isinstance(self.n_inducing, bool) or not isinstance(self.n_inducing, (int, np.integer)) or self.n_inducing < 1:
            raise ModelInputError(f"n_inducing must be a positive integer, got {self.n_inducing!r}")
        mean = Y.mean(0)
        Yc = Y - mean
        q = (default_latent_dim(Yc, self.variance_fraction) if self.n_components is None
             else check_latent_dim(self.n_components, n))
        m = int(min(self.n_inducing, n))
        if progress is not None:
            progress(0.0, "Bayesian GP-LVM: PCA initialisation")
        YYt = Yc @ Yc.T                                       # the only use of D-sized data
        Y_root = gram_root(YYt)                               # N x r, Y_root Y_root^T = Y Y^T
        data_var = np.trace(YYt) / (n * d)
        jitter = float(self.jitter)
        if not 0.0 < jitter < 1.0:
            raise ModelInputError(f"jitter must be in (0, 1), got {self.jitter!r}")
        layout = BoundLayout(n, q, m)
        bounds = ([(None, None)] * (n * q) + [(np.log(1e-10), np.log(1e3))] * (n * q) + [(None, None)] * (m * q)
                  + [(np.log(1e-8 * data_var), np.log(1e8 * data_var))] + [(np.log(1e-10), np.log(1e10))] * q
                  + [(None, np.log(1e8 / data_var))])

        def objective(x_tilde):
            """-F in scale-profiled coordinates (`profile_scale`)."""
            x, chain = profile_scale(x_tilde, layout)
            value, grad = bgplvm_bound(x, layout, Y_root, d, jitter)
            return -value, -chain(grad)

        def run(x_start, n_iter, span, message, noise_fixed=False, stall=None):
            """L-BFGS-B on the bound from x_start, preconditioned by `block_scales` measured
            there. Returns (x, F, iterations, message)."""
            scales = block_scales(objective, x_start, layout.splits)

            def preconditioned(y):
                value, grad = objective(x_start + scales * y)
                return value, grad * scales
            y_bounds = [(None if lo is None else (lo - o) / sc, None if hi is None else (hi - o) / sc)
                        for (lo, hi), o, sc in zip(bounds, x_start, scales)]
            if noise_fixed:
                y_bounds[-1] = (0.0, 0.0)
            result = lbfgs(preconditioned, np.zeros(layout.size), max_iter=max(n_iter, 1), progress=progress,
                           message=message, bounds=y_bounds, progress_span=span,
                           ftol=self._FTOL, stall=stall)
            x, _ = profile_scale(x_start + scales * result.x, layout)
            return x, -float(result.fun), int(result.nit), str(result.message)

        # two starting points (the bound has several local optima; neither start wins on all
        # data): (a) PCA latents (relative scales kept), noise first held at 1 % of the data
        # variance for `_WARM_UP` iterations; (b) GPy's: PCA of the column-standardised data,
        # each latent scaled to unit variance, noise = data variance. Each runs `_START_ITERS`
        # iterations; the better one continues until the bound stalls (`_STALL`) or `max_iter`.
        starts = [(pca_latents(Yc, q), 100.0, self._WARM_UP), (standardised_pca_latents(Yc, q), 1.0, 0)]
        n_start = int(min(self._START_ITERS, max(self.max_iter // 4, 1)))   # the final run keeps >= half
        candidates = []
        for i, (mu0, snr, n_warm) in enumerate(starts):
            Z0 = mu0[rng.permutation(n)[:m]] + 1e-3 * rng.standard_normal((m, q))
            x = layout.pack(mu0, np.log(np.full((n, q), 0.1)), Z0, np.log(data_var), np.zeros(q),
                            np.log(snr / data_var))
            span = (0.1 * i / len(starts), 0.1 * (i + 1) / len(starts))
            nit = 0
            if n_warm:
                x, _, nit, _ = run(x, min(n_warm, n_start), span, "Bayesian GP-LVM: warm-up (noise fixed)",
                                   noise_fixed=True)
            x, value, more, _ = run(x, n_start - nit, span, "Bayesian GP-LVM: starting points")
            candidates.append((value, x, nit + more))
        value, x, _ = max(candidates, key=lambda c: c[0])
        n_total = sum(c[2] for c in candidates)
        x, value, more, message = run(x, self.max_iter - n_total, (0.1, 0.95), "Bayesian GP-LVM: optimising the bound",
                                      stall=self._STALL)
        mu, log_S, Z, log_var, log_alpha, log_beta = layout.unpack(x)
        self.mean_ = mean
        self.latent_mean_ = mu.copy()
        self.latent_variance_ = np.exp(log_S)
        self.inducing_ = Z.copy()
        self.kernel_variance_ = float(np.exp(log_var))
        self.inverse_lengthscales_ = np.exp(log_alpha)
        self.noise_variance_ = float(np.exp(-log_beta))
        self.jitter_ = float(jitter)
        self.elbo_ = value
        self.n_iter_ = n_total + more
        self.optimizer_message_ = message
        self._prepare()
        # B = beta A^-1 Psi1^T Y: the one pass over D after the fit
        self.B_ = (self.beta_ * self._A_inv) @ (self._train_psi.psi1.T @ Yc)
        if progress is not None:
            progress(1.0, "Bayesian GP-LVM: done")
        return self

    @property
    def beta_(self) -> float:
        return 1.0 / self.noise_variance_

    def _prepare(self) -> None:
        """Training psi-statistics, K_mm^-1 and A^-1 (from the stored parameters)."""
        self._train_psi = PsiStatistics(self.latent_mean_, self.latent_variance_, self.inducing_,
                                        self.kernel_variance_, self.inverse_lengthscales_, self.jitter_)
        L_inv, R_inv, X, P, _ = _factors(self._train_psi.Kmm, self._train_psi.psi2, self.beta_)
        self._A_inv = P.T @ P
        posterior = -self.beta_ * (P.T @ (R_inv @ X @ L_inv))                     # A^-1 - K_mm^-1
        self._posterior_term = 0.5 * (posterior + posterior.T)

    @property
    def latent_dim(self) -> int:
        self._check_fitted()
        return int(self.latent_mean_.shape[1])

    # ------------------------------------------------------------------ API
    def decode(self, Z) -> np.ndarray:
        """Predictive mean at latent points: mean + k(z, Z_ind) B, (n, D)."""
        self._check_fitted()
        Z = self._check_latents(Z)
        return self.mean_ + ard_rbf(Z, self.inducing_, self.kernel_variance_, self.inverse_lengthscales_) @ self.B_

    def decode_features(self, Z) -> np.ndarray:
        """decode(Z) = mean_ + decode_features(Z) @ decode_basis(): k(z, Z_ind), (n, M)."""
        self._check_fitted()
        Z = self._check_latents(Z)
        return ard_rbf(Z, self.inducing_, self.kernel_variance_, self.inverse_lengthscales_)

    def decode_basis(self) -> np.ndarray:
        """(M, D): the predictive-mean weights B."""
        self._check_fitted()
        return self.B_

    def sample_latents(self, n: int, rng=None) -> np.ndarray:
        """x ~ N(0, I), the prior (§5.3.4.1), (n, Q)."""
        self._check_fitted()
        return as_generator(rng).standard_normal((self._check_count(n), self.latent_dim))

    def sample(self, n: int, rng=None) -> np.ndarray:
        """Prior latents (`sample_latents`) mapped by the predictive mean, (n, D)."""
        return self.decode(self.sample_latents(n, rng))

    def _row_setup(self, B_o: np.ndarray, r_o: np.ndarray):
        """Per-row constants of the per-point bound for observed residual r_o = (y - mean)_o.

        With the thin QR B_o^T = Q R: |r_o|^2 - 2 psi1 B_o r_o + tr(psi2 B_o B_o^T)
        = |c - R psi1|^2 + rest + tr((psi2 - psi1^T psi1) R^T R), c = Q^T r_o,
        rest = |r_o|^2 - |c|^2, so each evaluation costs O(M^2 Q), not O(D), without cancellation.
        Returns (c, R, rest, H, d_o) with H = B_o B_o^T + D_o (A^-1 - K_mm^-1).
        """
        Q, R = np.linalg.qr(B_o.T)
        c = Q.T @ r_o
        d_o = r_o.size
        H = R.T @ R + d_o * self._posterior_term
        return c, R, max(float(r_o @ r_o - c @ c), 0.0), H, d_o

    def _fit_rows(self, Y, mask):
        """Optimise q(x*) = N(mu*, diag S*) of each row against its observed coordinates
        (per-point bound, module docstring). Returns (mu*, S*, bound) per row."""
        R_all = np.where(mask, Y - self.mean_, 0.0)
        beta, q = self.beta_, self.latent_dim
        tp = self._train_psi
        kl_train = 0.5 * np.sum(tp.mu**2 + tp.S - np.log(tp.S) - 1.0, 1)
        psi2_var = tp.psi2n - tp.psi1[:, :, None] * tp.psi1[:, None, :]
        mus, Ss, bounds_out = np.empty((len(Y), q)), np.empty((len(Y), q)), np.empty(len(Y))
        for i in range(len(Y)):
            o = mask[i]
            args = self._row_setup(self.B_[:, o], R_all[i, o])
            c, R, rest, H, d_o = args
            # starting points: training q(x_n) with the best per-point bound
            G = R.T @ R
            data = (np.sum((c[:, None] - R @ tp.psi1.T) ** 2, 0) + rest
                    + np.einsum("nab,ab->n", psi2_var, G) + d_o * np.einsum("nab,ab->n", tp.psi2n, self._posterior_term))
            start_vals = -0.5 * beta * data - kl_train
            best = (-np.inf, None)
            for j in np.argsort(-start_vals)[: max(1, self.n_restarts)]:
                x0 = np.concatenate([tp.mu[j], np.log(tp.S[j])])
                res = minimize(self._row_bound, x0, args=args, jac=True, method="L-BFGS-B",
                               bounds=[(None, None)] * q + [(np.log(1e-10), np.log(1e3))] * q,
                               options={"maxiter": 200})
                if -res.fun > best[0]:
                    best = (-res.fun, res.x)
            bounds_out[i] = best[0]
            mus[i], Ss[i] = best[1][:q], np.exp(best[1][q:])
        return mus, Ss, bounds_out

    def _row_bound(self, x, c, R, rest, H, d_o):
        """-L(y*) for one row and its gradient w.r.t. [mu*, log S*] (args from `_row_setup`)."""
        q = self.latent_dim
        mu, log_S = x[None, :q], x[None, q:]
        S = np.exp(log_S)
        beta = self.beta_
        psi = PsiStatistics(mu, S, self.inducing_, self.kernel_variance_, self.inverse_lengthscales_)
        psi1, psi2 = psi.psi1[0], psi.psi2n[0]
        e = c - R @ psi1
        G = H - d_o * self._posterior_term                        # R^T R
        data = (e @ e + rest + np.sum((psi2 - np.outer(psi1, psi1)) * G)
                + d_o * np.sum(psi2 * self._posterior_term))
        value = (-0.5 * d_o * np.log(2 * np.pi / beta) - 0.5 * beta * data
                 - 0.5 * beta * d_o * psi.psi0 - 0.5 * np.sum(mu**2 + S - log_S - 1.0))
        d_mu, d_S, _, _, _ = psi.gradients(-0.5 * beta * d_o, beta * (R.T @ c)[None, :], -0.5 * beta * H)
        d_mu = d_mu - mu
        d_logS = d_S * S - 0.5 * (S - 1.0)
        return -value, -np.concatenate([d_mu[0], d_logS[0]])

    def encode(self, Y) -> np.ndarray:
        """Means mu* of the optimised q(x*) of each row, (n, Q)."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        return self._fit_rows(Y, np.ones(Y.shape, bool))[0]

    def score(self, Y) -> float:
        """Mean over rows of the per-point ELBO with q(x*) optimised (a lower-bound-based
        estimate of log p(y* | Y); module docstring)."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        return float(np.mean(self._fit_rows(Y, np.ones(Y.shape, bool))[2]))

    def complete(self, Y_partial, observed_mask) -> np.ndarray:
        """Optimise q(x*) against the observed coordinates, fill the rest with E_q[f] = psi1 B."""
        Y, mask = self._check_partial(Y_partial, observed_mask)
        mu, S, _ = self._fit_rows(np.where(mask, Y, 0.0), mask)
        psi = PsiStatistics(mu, S, self.inducing_, self.kernel_variance_, self.inverse_lengthscales_)
        return np.where(mask, Y, self.mean_ + psi.psi1 @ self.B_)

    # ------------------------------------------------------------------ arrays
    def _array_value(self, key: str):
        if key == "param_n_components":
            return -1 if self.n_components is None else int(self.n_components)
        if key.startswith("param_"):
            return getattr(self, key[len("param_"):])
        return getattr(self, key)

    def _restore(self, a) -> None:
        for key in ("kernel_variance_", "noise_variance_", "jitter_"):
            if not a[key] > 0:
                raise ModelFileError(f"BayesianGPLVM arrays: {key} must be positive")
        for key in ("latent_variance_", "inverse_lengthscales_"):
            if not np.all(a[key] > 0):
                raise ModelFileError(f"BayesianGPLVM arrays: {key} must be positive")
        nc = int(a["param_n_components"])
        self.__init__(n_components=None if nc < 0 else nc, n_inducing=int(a["param_n_inducing"]),
                      max_iter=int(a["param_max_iter"]), n_restarts=int(a["param_n_restarts"]),
                      variance_fraction=float(a["param_variance_fraction"]), jitter=float(a["jitter_"]))
        for key in ("mean_", "latent_mean_", "latent_variance_", "inducing_", "inverse_lengthscales_", "B_"):
            setattr(self, key, a[key])
        for key in ("kernel_variance_", "noise_variance_", "jitter_", "elbo_"):
            setattr(self, key, float(a[key]))
        try:
            self._prepare()
        except np.linalg.LinAlgError:
            raise ModelFileError("BayesianGPLVM arrays: the stored kernel matrices are not positive definite") from None
