"""What the GP-LVM and the Bayesian GP-LVM share (thesis §5.3.3-5.3.4): the fit prologue, the
two-start optimisation, the per-row latent search behind encode / score / complete, and
their numerical helpers (L-BFGS-B driver, inverse Cholesky factor).

Fit: Y is centred by its mean and enters only through the N x N Gram matrix Y Y^T (formed
once), the latent dimension Q is given or the 80 % rule (§5.4.1). The objective has several
local optima and neither of two starting points wins on all data, so each starting point runs
`_START_ITERS` L-BFGS-B iterations (at most a quarter of `max_iter`) and the better one
continues for the rest of `max_iter` (progress: starting points 0-0.1, final run 0.1-0.95).

Posterior given pins (`posterior`): the latent point z that best explains a few observed
coordinates under the latent prior, the MAP of p(y_o | z) p(z) with p(y_o | z) = N(m_o(z),
beta^-1 I) and p(z) = N(0, I), found by L-BFGS from a given latent (the live object's, so
a dragged pin moves the shape continuously) or from the training latents that explain the
observations best; the shape is the prediction m(z), its variance the GP's predictive
variance at z plus the latent uncertainty of the Laplace approximation carried through m
(Gauss-Newton: Cov z = (J^T J beta + I)^-1, J = d m_o / dz).

Row search: a new, possibly partial, row is explained by the latent point (GP-LVM) or the
q(x*) (Bayesian GP-LVM) that maximises a per-row objective of its observed coordinates.
L-BFGS-B starts from the `n_restarts` training points that score best and the best end point
wins; `encode` keeps its latent (mean), `score` reports the mean objective and `complete` fills
the hidden coordinates with the model's prediction there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.linalg.lapack import dpotrf, dtrtri
from scipy.optimize import minimize

from ..base.progress import Progress
from .base import (ModelInputError, ShapeModel, ShapePosterior, check_latent_dim, check_rows, check_training_data,
                   default_latent_dim)
from .scaling import ENCODE_SEARCH_SHAPES

__all__ = ["LatentVariableModel", "TrainingData", "FitProblem", "OptimiserRun", "two_start_search", "best_start",
           "lbfgs", "inverse_cholesky"]


def inverse_cholesky(matrix: np.ndarray, name: str, log_det: bool = False):
    """L^-1 for matrix = L L^T (lower, LAPACK potrf + trtri), and log|matrix| if asked;
    LinAlgError naming `name` if the matrix is not positive definite."""
    L, info = dpotrf(matrix, lower=1, clean=1)
    if info == 0:
        L_inv, info = dtrtri(L, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"{name} is not positive definite")
    return (L_inv, 2.0 * np.log(L.diagonal()).sum()) if log_det else L_inv


def lbfgs(objective, x0, *, max_iter: int, progress: Progress | None, message: str,
          bounds=None, progress_span: tuple[float, float] = (0.0, 1.0), gtol: float = 1e-6,
          ftol: float = 1e-12, stall: tuple[int, float] | None = None):
    """Minimise objective(x) -> (value, gradient) with scipy's L-BFGS-B.

    It stops after `max_iter` iterations, when the projected gradient is below `gtol`, when an
    iteration lowers the value by less than `ftol` relative (scipy's ftol = factr * eps) or,
    with stall = (k, rtol), when the last k iterations together lowered it by at most
    rtol |value|.

    `progress(fraction, message)` is called once per iteration; if it raises (e.g. Cancelled)
    the exception propagates and the fit stops (cooperative cancel).
    """
    lo, hi = progress_span
    count = [0]
    failures = [0]

    history = []

    def callback(intermediate_result):
        count[0] += 1
        if progress is not None:
            progress(lo + (hi - lo) * min(count[0] / max_iter, 1.0), message)
        if stall is not None:
            history.append(intermediate_result.fun)
            k, rtol = stall
            if len(history) > k and history[-k - 1] - history[-1] <= rtol * abs(history[-1]):
                raise StopIteration

    def guarded(x):
        # a trial step far outside the sane region can make a kernel matrix numerically
        # indefinite; report +inf so the line search backs off
        try:
            value, grad = objective(x)
            if np.isfinite(value) and np.all(np.isfinite(grad)):
                return value, grad
        except (np.linalg.LinAlgError, ValueError):
            pass
        failures[0] += 1
        return np.inf, np.zeros_like(x)

    x, result, best = np.asarray(x0, dtype=float), None, np.inf
    # L-BFGS-B may stop early after +inf trial values; restart it (fresh curvature memory)
    # from the last good point while it still makes progress and iterations remain
    for _ in range(20):
        failures_before = failures[0]
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            result = minimize(guarded, x, jac=True, method="L-BFGS-B", bounds=bounds, callback=callback,
                              options={"maxiter": max(max_iter - count[0], 1), "maxfun": 2 * max_iter + 20,
                                       "gtol": gtol, "ftol": ftol, "maxcor": 20})
        improved = result.fun < best - 1e-9 * max(abs(best), 1.0) if np.isfinite(best) else np.isfinite(result.fun)
        if not np.isfinite(result.fun):
            raise np.linalg.LinAlgError(f"{message}: the objective is not computable at the starting point")
        best, x = min(best, result.fun), result.x
        if failures[0] == failures_before or count[0] >= max_iter or not improved:
            break
    result.nit = count[0]
    return result


@dataclass(frozen=True)
class TrainingData:
    """The training rows as a GP-LVM fit uses them."""

    mean: np.ndarray          # (D,) mean shape
    centred: np.ndarray       # (N, D) Y - mean
    gram: np.ndarray          # (N, N) centred Y Y^T, the only D-sized product of the fit
    latent_dim: int

    @property
    def n_features(self) -> int:
        return self.centred.shape[1]

    @property
    def variance(self) -> float:
        """Mean variance per coordinate, tr(Y Y^T) / (N D)."""
        return float(np.trace(self.gram) / (self.gram.shape[0] * self.n_features))


@dataclass(frozen=True)
class OptimiserRun:
    """Where one optimiser run ended: the point, the objective there (maximised), its
    iterations and the optimiser's message."""

    x: np.ndarray
    value: float
    n_iter: int
    message: str


class FitProblem:
    """One fit's optimisation: starting points and L-BFGS-B runs of its objective."""

    starts: list[np.ndarray]

    def run(self, x: np.ndarray, n_iter: int, span: tuple[float, float], final: bool) -> OptimiserRun:
        """At most n_iter iterations from x, progress reported within `span`; the final run
        may stop on a stall (several iterations with too little gain)."""
        raise NotImplementedError

    def run_start(self, index: int, n_iter: int, span: tuple[float, float]) -> OptimiserRun:
        """The short run from starting point `index`."""
        return self.run(self.starts[index], n_iter, span, final=False)


def two_start_search(problem: FitProblem, max_iter: int, start_iters: int) -> OptimiserRun:
    """Run every starting point briefly and continue the best (module docstring); the result
    counts the iterations of all runs."""
    n_start = int(min(start_iters, max(max_iter // 4, 1)))   # the final run keeps >= half
    count = len(problem.starts)
    runs = [problem.run_start(i, n_start, (0.1 * i / count, 0.1 * (i + 1) / count)) for i in range(count)]
    best = max(runs, key=lambda run: run.value)
    used = sum(run.n_iter for run in runs)
    final = problem.run(best.x, max(max_iter - used, 1), (0.1, 0.95), final=True)
    return OptimiserRun(final.x, final.value, used + final.n_iter, final.message)


def best_start(objective, starts, args: tuple, bounds=None) -> tuple[np.ndarray, float]:
    """Minimise objective(x, *args) -> (value, gradient) by L-BFGS-B from each start; the end
    point with the lowest value and minus that value."""
    best_x, best = None, -np.inf
    for x0 in starts:
        result = minimize(objective, x0, args=args, jac=True, method="L-BFGS-B", bounds=bounds,
                          options={"maxiter": 200})
        if -result.fun > best:
            best_x, best = result.x, -result.fun
    return best_x, best


class LatentVariableModel(ShapeModel):
    """The shared fit and row search of `GPLVM` and `BayesianGPLVM` (module docstring).

    Subclasses set `_LABEL` (progress text) and `_START_ITERS`, and implement
    `_fit_problem(data, progress)` (the optimisation), `_set_optimum(data, problem, optimum)`
    (fitted attributes from the optimum), `_search_row(args, scoring)` (one row's search from
    the `_row_candidates` ranked by their score) and `_predict_rows(X)` (the prediction at the
    rows' search results).
    """

    _LABEL: ClassVar[str] = ""
    _START_ITERS: ClassVar[int] = 0

    # ------------------------------------------------------------------ fit
    def fit(self, Y, progress: Progress | None = None):
        """Optimise from two starting points and keep the better optimum; returns self."""
        data = self._training_data(Y, progress)
        problem = self._fit_problem(data, progress)
        optimum = two_start_search(problem, self.max_iter, self._START_ITERS)
        self.mean_ = data.mean
        self.n_iter_ = optimum.n_iter
        self.optimizer_message_ = optimum.message
        self._set_optimum(data, problem, optimum)
        if progress is not None:
            progress(1.0, f"{self._LABEL}: done")
        return self

    def _training_data(self, Y, progress: Progress | None) -> TrainingData:
        Y = check_training_data(Y)
        mean = Y.mean(0)
        Yc = Y - mean
        q = (default_latent_dim(Yc, self.variance_fraction) if self.n_components is None
             else check_latent_dim(self.n_components, Y.shape[0]))
        if progress is not None:
            progress(0.0, f"{self._LABEL}: PCA initialisation")
        return TrainingData(mean, Yc, Yc @ Yc.T, q)

    def _fit_problem(self, data: TrainingData, progress: Progress | None) -> FitProblem:
        raise NotImplementedError

    def _set_optimum(self, data: TrainingData, problem: FitProblem, optimum: OptimiserRun) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------------ row search
    @staticmethod
    def _row_setup(basis_o: np.ndarray, r_o: np.ndarray):
        """Constants of one row's search from its observed residual r_o = (y - mean)_o and the
        observed columns of the decode basis (K x D_o): with the thin QR basis_o^T = Q R,
        |r_o - basis_o^T f|^2 = |c - R f|^2 + rest, c = Q^T r_o, rest = |r_o|^2 - |c|^2, so an
        evaluation costs O(K^2), not O(D), without the cancellation of expanding the square.
        Returns (c, R, rest, D_o)."""
        Q, R = np.linalg.qr(basis_o.T)
        c = Q.T @ r_o
        return c, R, max(float(r_o @ r_o - c @ c), 0.0), r_o.size

    def _search_rows(self, Y: np.ndarray, mask: np.ndarray, scoring: bool = False, progress: Progress | None = None):
        """Each row's search result (n, K) (a row of `_row_candidates`' kind) and objective (n,).
        scoring=True asks for the search whose objective is the model's score; `progress`
        after each row."""
        residuals = np.where(mask, Y - self.mean_, 0.0)
        basis = self.decode_basis()
        found = np.empty((len(Y), self._row_candidates.shape[1]))
        values = np.empty(len(Y))
        for i, observed in enumerate(mask):
            args = self._row_setup(basis[:, observed], residuals[i, observed])
            found[i], values[i] = self._search_row(args, scoring)
            if progress is not None:
                progress((i + 1) / len(Y), f"shape {i + 1} of {len(Y)}")
        return found, values

    def _best_candidates(self, scores: np.ndarray) -> list[np.ndarray]:
        """The `n_restarts` (at least one) training candidates with the highest scores."""
        return [self._row_candidates[j] for j in np.argsort(-scores)[: max(1, self.n_restarts)]]

    def _search_row(self, args: tuple, scoring: bool) -> tuple[np.ndarray, float]:
        raise NotImplementedError

    def _predict_rows(self, found: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def encode(self, Y) -> np.ndarray:
        """The latent (mean) of each row's search (module docstring), (n, Q)."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        return self._search_rows(Y, np.ones(Y.shape, bool))[0][:, : self.latent_dim]

    def training_latents(self, Y, progress: Progress | None = None) -> np.ndarray:
        """The latents of the training rows Y (the rows fitted, in order), (N, Q): each
        row's search as `encode` (`progress` per row) up to `ENCODE_SEARCH_SHAPES` rows,
        above it the fit's own latents, the searches' first candidates (scaling.py)."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        if len(Y) != len(self._row_candidates):
            raise ModelInputError(f"{len(Y)} rows for a model fitted to {len(self._row_candidates)}")
        if len(Y) > ENCODE_SEARCH_SHAPES:
            return self._row_candidates[:, : self.latent_dim].copy()
        return self._search_rows(Y, np.ones(Y.shape, bool), progress=progress)[0][:, : self.latent_dim]

    def score(self, Y) -> float:
        """Mean over rows of the searched objective (see the model's `_search_row`)."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        return float(np.mean(self._search_rows(Y, np.ones(Y.shape, bool), scoring=True)[1]))

    # ------------------------------------------------------------------ posterior given pins
    def _feature_jacobian(self, z: np.ndarray) -> np.ndarray:
        """d decode_features(z) / dz at one latent z (Q,): (K, Q)."""
        raise NotImplementedError

    def _predictive_variance(self, z: np.ndarray) -> float:
        """The GP's predictive variance of the noise-free f at latent z (the same for every coordinate)."""
        raise NotImplementedError

    def pin_objective(self, z: np.ndarray, c: np.ndarray, R: np.ndarray) -> tuple[float, np.ndarray]:
        """-log p(y_o | z) - log p(z) up to a constant, and its gradient in z: with the row
        constants c, R of `_row_setup` (|y_o - m_o(z)|^2 = |c - R f(z)|^2 + const),
        E(z) = beta / 2 |c - R f(z)|^2 + |z|^2 / 2."""
        f = self.decode_features(z[None, :])[0]
        e = c - R @ f
        beta = 1.0 / self.noise_variance_
        value = 0.5 * beta * float(e @ e) + 0.5 * float(z @ z)
        grad = -beta * (self._feature_jacobian(z).T @ (R.T @ e)) + z
        return value, grad

    def posterior(self, y, observed_mask, start=None) -> ShapePosterior:
        """The MAP latent of the observed coordinates under the N(0, I) prior (module
        docstring), from `start` (Q,) alone when given, else from the `n_restarts` training
        latents that explain them best; the prediction there and its variance."""
        self._check_fitted()
        y, mask = self._check_observed(y, observed_mask)
        basis = self.decode_basis()
        c, R, _, _ = LatentVariableModel._row_setup(basis[:, mask], y[mask] - self.mean_[mask])
        q = self.latent_dim
        if start is not None:
            starts = [self._check_latents(start)[0]]
        else:
            latents = self._row_candidates[:, :q]
            beta = 1.0 / self.noise_variance_
            misfit = 0.5 * beta * np.sum((c[:, None] - R @ self.decode_features(latents).T) ** 2, 0)
            starts = [latents[j] for j in np.argsort(misfit + 0.5 * np.sum(latents**2, 1))[: max(1, self.n_restarts)]]
        z, _ = best_start(self.pin_objective, starts, (c, R))
        J = R @ self._feature_jacobian(z)                                   # d m_o / dz in the QR basis
        covariance = np.linalg.inv(J.T @ J / self.noise_variance_ + np.eye(q))
        root = basis.T @ (self._feature_jacobian(z) @ np.linalg.cholesky(covariance))   # (D, Q)
        variance = self._predictive_variance(z) + np.sum(root**2, 1)
        return ShapePosterior(self.decode(z[None, :])[0], variance, z)

    def complete(self, Y_partial, observed_mask) -> np.ndarray:
        """Search each row against its observed coordinates, predict there, keep the observed."""
        Y, mask = self._check_partial(Y_partial, observed_mask)
        found, _ = self._search_rows(np.where(mask, Y, 0.0), mask)
        return np.where(mask, Y, self._predict_rows(found))
