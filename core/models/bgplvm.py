"""Bayesian GP-LVM (thesis §5.3.4; Titsias & Lawrence 2010; docs/method.md §4).

Prior p(X) = prod_n N(x_n | 0, I), variational q(X) = prod_n N(mu_n, diag S_n), ARD RBF kernel
(kernels.py), M inducing inputs Z (default 20) and Gaussian noise beta^-1. The collapsed bound
(T&L 2010 eq. 14, with A = K_mm + beta Psi2, psi-statistics from kernels.PsiStatistics):

  F = (N D / 2) log(beta / 2 pi) - (D / 2) log|A K_mm^-1| - (beta / 2) tr(Y Y^T)
      + (beta^2 / 2) tr(A^-1 Psi1^T Y Y^T Psi1) - (beta D / 2) psi0 + (beta D / 2) tr(K_mm^-1 Psi2)
      - KL(q(X) || p(X)),      KL = 1/2 sum_nq (mu^2 + S - log S - 1).

It is maximised over mu, log S, Z, log s_f^2, log a (inverse squared length-scales) and log beta
by L-BFGS-B with analytic gradients. Y enters only through Y Y^T (formed once, N x N), so an
iteration costs O(N M^2 Q + N^2 M), whatever D. Optimiser details (`_BoundProblem`): the latent
scale of each dimension, which only the KL term pins down, is profiled out (`profile_scale`);
the blocks are preconditioned by their measured curvature (`block_scales`). The bound has several local
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
from ..base.npzfile import ArraySpec
from ..base.progress import Progress
from .base import ModelInputError, as_generator, pca_latents, standardised_pca_latents
from .kernels import PsiStatistics, rbf
from .latent_variable import (FitProblem, LatentVariableModel, OptimiserRun, TrainingData, best_start,
                              inverse_cholesky, lbfgs)

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
    L_inv = inverse_cholesky(Kmm, "K_mm")
    X = L_inv @ Psi2 @ L_inv.T
    B = beta * X
    B.flat[:: B.shape[0] + 1] += 1.0
    R_inv, log_det_B = inverse_cholesky(B, "I + beta L^-1 Psi2 L^-T", log_det=True)
    return L_inv, R_inv, X, R_inv @ L_inv, log_det_B


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


class _BoundProblem(FitProblem):
    """-F in scale-profiled coordinates (`profile_scale`) over the bounded parameters; every
    run is preconditioned by `block_scales` measured at its start. Starting points (the bound
    has several local optima; neither start wins on all data): (a) PCA latents (relative scales
    kept), noise first held at 1 % of the data variance for `warm_up` iterations; (b) GPy's:
    PCA of the column-standardised data, each latent scaled to unit variance, noise = data
    variance; the inducing inputs are M latents drawn by `rng`, slightly perturbed."""

    def __init__(self, data: TrainingData, m: int, jitter: float, rng: np.random.Generator,
                 progress: Progress | None, ftol: float, stall: tuple[int, float], warm_up: int):
        n, q, data_var, Yc = data.gram.shape[0], data.latent_dim, data.variance, data.centred
        self.layout = BoundLayout(n, q, m)
        self.Y_root = gram_root(data.gram)                    # N x r, Y_root Y_root^T = Y Y^T
        self.n_features, self.jitter = data.n_features, jitter
        self.progress, self.ftol, self.stall = progress, ftol, stall
        self.bounds = ([(None, None)] * (n * q) + [(np.log(1e-10), np.log(1e3))] * (n * q) + [(None, None)] * (m * q)
                       + [(np.log(1e-8 * data_var), np.log(1e8 * data_var))] + [(np.log(1e-10), np.log(1e10))] * q
                       + [(None, np.log(1e8 / data_var))])
        self.starts, self.warm_ups = [], [warm_up, 0]
        for mu0, snr in ((pca_latents(Yc, q), 100.0), (standardised_pca_latents(Yc, q), 1.0)):
            Z0 = mu0[rng.permutation(n)[:m]] + 1e-3 * rng.standard_normal((m, q))
            self.starts.append(self.layout.pack(mu0, np.log(np.full((n, q), 0.1)), Z0, np.log(data_var), np.zeros(q),
                                                np.log(snr / data_var)))

    def objective(self, x_tilde):
        """-F in scale-profiled coordinates (`profile_scale`)."""
        x, chain = profile_scale(x_tilde, self.layout)
        value, grad = bgplvm_bound(x, self.layout, self.Y_root, self.n_features, self.jitter)
        return -value, -chain(grad)

    def _run(self, x_start, n_iter, span, stage, noise_fixed=False, stall=None) -> OptimiserRun:
        """L-BFGS-B on the bound from x_start, preconditioned by `block_scales` measured there."""
        scales = block_scales(self.objective, x_start, self.layout.splits)

        def preconditioned(y):
            value, grad = self.objective(x_start + scales * y)
            return value, grad * scales
        y_bounds = [(None if lo is None else (lo - o) / sc, None if hi is None else (hi - o) / sc)
                    for (lo, hi), o, sc in zip(self.bounds, x_start, scales)]
        if noise_fixed:
            y_bounds[-1] = (0.0, 0.0)
        result = lbfgs(preconditioned, np.zeros(self.layout.size), max_iter=max(n_iter, 1), progress=self.progress,
                       message=f"Bayesian GP-LVM: {stage}", bounds=y_bounds, progress_span=span,
                       ftol=self.ftol, stall=stall)
        x, _ = profile_scale(x_start + scales * result.x, self.layout)
        return OptimiserRun(x, -float(result.fun), int(result.nit), str(result.message))

    def run(self, x, n_iter, span, final):
        if final:
            return self._run(x, n_iter, span, "optimising the bound", stall=self.stall)
        return self._run(x, n_iter, span, "starting points")

    def run_start(self, index, n_iter, span):
        """The start's noise warm-up (if any), then its run, within n_iter iterations together."""
        x, warm_up, used = self.starts[index], self.warm_ups[index], 0
        if warm_up:
            warm = self._run(x, min(warm_up, n_iter), span, "warm-up (noise fixed)", noise_fixed=True)
            x, used = warm.x, warm.n_iter
        run = self.run(x, n_iter - used, span, final=False)
        return OptimiserRun(run.x, run.value, used + run.n_iter, run.message)


class BayesianGPLVM(LatentVariableModel):
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
    _LABEL = "Bayesian GP-LVM"
    # L-BFGS-B relative-decrease tolerance: scipy's (and GPy's) default factr = 1e7
    _FTOL = 1e7 * np.finfo(float).eps
    # the final run also stops once 10 iterations together gained less than 3e-6 |F|
    _STALL = (10, 3e-6)
    # iterations per starting point before the better one continues; noise warm-up of start (a)
    _START_ITERS = 40
    _WARM_UP = 15
    _ARRAY_SPEC = {
        "model_type": ArraySpec("U", ()),
        "mean_": ArraySpec("f", ("D",)),
        "latent_mean_": ArraySpec("f", ("N", "Q")),
        "latent_variance_": ArraySpec("f", ("N", "Q")),
        "inducing_": ArraySpec("f", ("M", "Q")),
        "kernel_variance_": ArraySpec("f", ()),
        "inverse_lengthscales_": ArraySpec("f", ("Q",)),
        "noise_variance_": ArraySpec("f", ()),
        "jitter_": ArraySpec("f", ()),
        "B_": ArraySpec("f", ("M", "D")),
        "elbo_": ArraySpec("f", ()),
        "param_n_components": ArraySpec("iu", ()),
        "param_n_inducing": ArraySpec("iu", ()),
        "param_max_iter": ArraySpec("iu", ()),
        "param_n_restarts": ArraySpec("iu", ()),
        "param_variance_fraction": ArraySpec("f", ()),
    }
    # model files keep the jitter setting as the fitted jitter_ (equal after a fit)
    _PARAMS_IN_FITTED = {"jitter": "jitter_"}
    _POSITIVE = ("kernel_variance_", "noise_variance_", "jitter_", "latent_variance_", "inverse_lengthscales_")

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
    def _fit_problem(self, data, progress):
        rng = as_generator(self.random_state)
        if isinstance(self.n_inducing, bool) or not isinstance(self.n_inducing, (int, np.integer)) or self.n_inducing < 1:
            raise ModelInputError(f"n_inducing must be a positive integer, got {self.n_inducing!r}")
        jitter = float(self.jitter)
        if not 0.0 < jitter < 1.0:
            raise ModelInputError(f"jitter must be in (0, 1), got {self.jitter!r}")
        m = int(min(self.n_inducing, data.gram.shape[0]))
        return _BoundProblem(data, m, jitter, rng, progress, self._FTOL, self._STALL, self._WARM_UP)

    def _set_optimum(self, data, problem, optimum):
        """q(X), inducing inputs and kernel from the optimum, F there; then
        B = beta A^-1 Psi1^T Y, the one pass over D after the fit."""
        mu, log_S, Z, log_var, log_alpha, log_beta = problem.layout.unpack(optimum.x)
        self.latent_mean_ = mu.copy()
        self.latent_variance_ = np.exp(log_S)
        self.inducing_ = Z.copy()
        self.kernel_variance_ = float(np.exp(log_var))
        self.inverse_lengthscales_ = np.exp(log_alpha)
        self.noise_variance_ = float(np.exp(-log_beta))
        self.jitter_ = problem.jitter
        self.elbo_ = optimum.value
        self._prepare()
        self.B_ = (self.beta_ * self._A_inv) @ (self._train_psi.psi1.T @ data.centred)

    @property
    def beta_(self) -> float:
        return 1.0 / self.noise_variance_

    def _prepare(self) -> None:
        """Training psi-statistics, K_mm^-1 and A^-1 (from the stored parameters), and the row
        search's per-candidate constants."""
        tp = self._train_psi = PsiStatistics(self.latent_mean_, self.latent_variance_, self.inducing_,
                                             self.kernel_variance_, self.inverse_lengthscales_, self.jitter_)
        L_inv, R_inv, X, P, _ = _factors(tp.Kmm, tp.psi2, self.beta_)
        self._A_inv = P.T @ P
        posterior = -self.beta_ * (P.T @ (R_inv @ X @ L_inv))                     # A^-1 - K_mm^-1
        self._posterior_term = 0.5 * (posterior + posterior.T)
        self._row_candidates = np.hstack([tp.mu, np.log(tp.S)])
        self._train_kl = 0.5 * np.sum(tp.mu**2 + tp.S - np.log(tp.S) - 1.0, 1)
        self._psi2_variance = tp.psi2n - tp.psi1[:, :, None] * tp.psi1[:, None, :]

    @property
    def latent_dim(self) -> int:
        self._check_fitted()
        return int(self.latent_mean_.shape[1])

    # ------------------------------------------------------------------ API
    def decode(self, Z) -> np.ndarray:
        """Predictive mean at latent points: mean + k(z, Z_ind) B, (n, D)."""
        features = self.decode_features(Z)
        return self.mean_ + features @ self.B_

    def decode_features(self, Z) -> np.ndarray:
        """decode(Z) = mean_ + decode_features(Z) @ decode_basis(): k(z, Z_ind), (n, M)."""
        self._check_fitted()
        scale = np.sqrt(self.inverse_lengthscales_)                    # the ARD kernel (kernels.py)
        return rbf(self._check_latents(Z) * scale, self.inducing_ * scale, self.kernel_variance_)

    def decode_basis(self) -> np.ndarray:
        """(M, D): the predictive-mean weights B."""
        self._check_fitted()
        return self.B_

    def sample_latents(self, n: int, rng=None) -> np.ndarray:
        """x ~ N(0, I), the prior (§5.3.4.1), (n, Q)."""
        self._check_fitted()
        return as_generator(rng).standard_normal((self._check_count(n), self.latent_dim))

    def _row_setup(self, B_o: np.ndarray, r_o: np.ndarray):
        """The shared row constants (c, R, rest, D_o) with H = B_o B_o^T + D_o (A^-1 - K_mm^-1):
        |r_o|^2 - 2 psi1 B_o r_o + tr(psi2 B_o B_o^T) = |c - R psi1|^2 + rest
        + tr((psi2 - psi1^T psi1) R^T R). Returns (c, R, rest, H, D_o)."""
        c, R, rest, d_o = super()._row_setup(B_o, r_o)
        return c, R, rest, R.T @ R + d_o * self._posterior_term, d_o

    def _search_row(self, args, scoring):
        """Optimise q(x*) = N(mu*, diag S*) of one row against its observed coordinates (the
        per-point bound of the module docstring, also the score: a lower-bound-based estimate
        of log p(y* | Y)), from the training q(x_n) with the best per-point bound. Returns
        ([mu*, log S*], bound)."""
        c, R, rest, H, d_o = args
        tp = self._train_psi
        G = R.T @ R
        data = (np.sum((c[:, None] - R @ tp.psi1.T) ** 2, 0) + rest + np.einsum("nab,ab->n", self._psi2_variance, G)
                + d_o * np.einsum("nab,ab->n", tp.psi2n, self._posterior_term))
        q = self.latent_dim
        return best_start(self._row_bound, self._best_candidates(-0.5 * self.beta_ * data - self._train_kl), args,
                          bounds=[(None, None)] * q + [(np.log(1e-10), np.log(1e3))] * q)

    def _predict_rows(self, found):
        """E_q(x*)[f] = mean + psi1(mu*, S*) B."""
        q = self.latent_dim
        psi = PsiStatistics(found[:, :q], np.exp(found[:, q:]), self.inducing_, self.kernel_variance_,
                            self.inverse_lengthscales_)
        return self.mean_ + psi.psi1 @ self.B_

    def _feature_jacobian(self, z):
        """d k(z, Z_m) / dz_q = -k(z, Z_m) a_q (z_q - Z_mq), (M, Q)."""
        k = self.decode_features(z[None, :])[0]
        return -k[:, None] * self.inverse_lengthscales_ * (z[None, :] - self.inducing_)

    def _predictive_variance(self, z):
        """s_f^2 - k^T (K_mm^-1 - A^-1) k at a point z (the variance of the optimal q(u)'s
        prediction, without the noise)."""
        k = self.decode_features(z[None, :])[0]
        return max(self.kernel_variance_ + float(k @ self._posterior_term @ k), 0.0)

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
