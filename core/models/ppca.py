"""Probabilistic PCA with Ledoit-Wolf shrinkage (thesis §5.3.2, eqs. 5.14-5.19; docs/method.md §4).

Model: y = mu + W z + eps,  z ~ N(0, I_q),  eps ~ N(0, s^2 I_D)  =>  y ~ N(mu, C), C = W W^T + s^2 I.
Fit (closed form, eq. 5.18-5.19) on the shrunk covariance S_s = (1 - d) S + d (tr S / D) I:
  W = V_q (L_q - s^2 I)^(1/2),  s^2 = mean of the D - q discarded eigenvalues of S_s.
Everything goes through the thin SVD of the centred N x D data (N << D): no D x D matrix.
"""

from __future__ import annotations

import numpy as np

from ..base.errors import ModelFileError
from ..base.npzfile import ArraySpec
from ..base.progress import Progress
from .base import (ModelInputError, ShapeModel, ShapePosterior, as_generator, check_latent_dim,
                   check_rows, check_training_data, latent_dim_for_variance, ledoit_wolf_shrinkage,
                   principal_axes, shrunk_spectrum)

__all__ = ["PPCA", "MODE_RANGE"]

#: how far a mode reaches either way where it is shown on its own (Blender's mode shape
#: keys), in latent units: z ~ N(0, 1), so ±3 holds 99.7 % of the model's shapes along it
MODE_RANGE = 3.0

_LOG_2PI = np.log(2.0 * np.pi)


class PPCA(ShapeModel):
    """PPCA shape model.

    Parameters
    ----------
    n_components : int, None or "heldout"
        Latent dimension q; None = smallest q explaining `variance_fraction` of the data's
        (unshrunk) variance (thesis §5.4.1, 80 %); "heldout" = the q with the highest mean held-out
        log-likelihood in K-fold cross-validation (docs/method.md §4 **beyond**; K = min(5, N) folds
        of a fixed shuffle, q from 1 to the smallest training fold size - 1, the same shrinkage
        setting in every fold). The per-q scores are kept in `heldout_scores_` (q -> mean
        log-likelihood per held-out shape).
    shrinkage : "ledoit-wolf" or float in [0, 1]
        Weight d of (tr S / D) I in the shrunk covariance; 0 = plain ML PPCA (Tipping & Bishop).
    variance_fraction : float
        Fraction for the explained-variance rule.
    sample_noise : bool
        If True `sample` adds the isotropic noise eps (the thesis' "finally add noise"); default
        False returns the smooth shapes mu + W z.
    """

    model_type = "ppca"
    _ARRAY_SPEC = {
        "model_type": ArraySpec("U", ()),
        "mean_": ArraySpec("f", ("D",)),
        "components_": ArraySpec("f", ("D", "Q")),
        "noise_variance_": ArraySpec("f", ()),
        "shrinkage_": ArraySpec("f", ()),
        "eigenvalues_": ArraySpec("f", ("R",)),
        "n_samples_": ArraySpec("iu", ()),
        "param_n_components": ArraySpec("iu", ()),   # -1: variance rule, -2: held-out likelihood
        "param_shrinkage": ArraySpec("U", ()),
        "param_variance_fraction": ArraySpec("f", ()),
        "param_sample_noise": ArraySpec("iu", ()),
    }
    _POSITIVE = ("noise_variance_",)

    def __init__(self, n_components: int | None = None, shrinkage="ledoit-wolf",
                 variance_fraction: float = 0.8, sample_noise: bool = False):
        self.n_components = n_components
        self.shrinkage = shrinkage
        self.variance_fraction = variance_fraction
        self.sample_noise = sample_noise

    # ------------------------------------------------------------------ fit
    def fit(self, Y, progress: Progress | None = None) -> "PPCA":
        """Closed-form fit (eqs. 5.18-5.19) on the shrunk covariance; returns self."""
        Y = check_training_data(Y)
        n, d = Y.shape
        if progress is not None:
            progress(0.0, "PPCA: thin SVD")
        mean = Y.mean(0)
        Yc = Y - mean
        _, eigvals, axes = principal_axes(Yc)
        shrinkage = self._shrinkage_value(Yc)
        spectrum, _ = shrunk_spectrum(eigvals, d, shrinkage)
        if self.n_components is None:
            q = latent_dim_for_variance(eigvals, self.variance_fraction, n, d)
        elif isinstance(self.n_components, str) and self.n_components == "heldout":
            self.heldout_scores_ = self._heldout_scores(Y)
            q = max(self.heldout_scores_, key=self.heldout_scores_.get)
        else:
            q = check_latent_dim(self.n_components, n, d)
            if q > spectrum.size:
                raise ModelInputError(f"latent dimension {q} exceeds the data's {spectrum.size} directions")
        self._set_parameters(mean, eigvals.sum(), spectrum, axes, q)
        self.shrinkage_ = float(shrinkage)
        self.eigenvalues_ = spectrum
        self.n_samples_ = n
        self._prepare()
        if progress is not None:
            progress(1.0, "PPCA: done")
        return self

    _HELDOUT_FOLDS = 5

    def _shrinkage_value(self, Yc: np.ndarray) -> float:
        if isinstance(self.shrinkage, str) and self.shrinkage == "ledoit-wolf":
            return ledoit_wolf_shrinkage(Yc)
        try:
            shrinkage = float(self.shrinkage)
        except (TypeError, ValueError):
            raise ModelInputError(f"shrinkage must be 'ledoit-wolf' or a number in [0, 1], got {self.shrinkage!r}") from None
        if not 0.0 <= shrinkage <= 1.0:
            raise ModelInputError(f"shrinkage must be in [0, 1], got {shrinkage}")
        return shrinkage

    def _set_parameters(self, mean, total, spectrum, axes, q) -> None:
        """mean_, components_, noise_variance_ from the shrunk spectrum (eq. 5.19): the
        discarded eigenvalues are spectrum[q:] and the D - rank directions off the data span."""
        d = mean.shape[0]
        noise_variance = (total - spectrum[:q].sum()) / (d - q)
        if not noise_variance > 1e-12 * total / d:
            smaller = f"choose a Latent Dimension below {q} (--latent-dim), " if q > 1 else ""
            raise ModelInputError(
                f"PPCA cannot fit {q} latent dimension(s): the training shapes vary in only {q} "
                f"direction(s), which leaves no noise to model; {smaller}add training shapes "
                "or choose another Model (gplvm or bgplvm)"
            )
        self.mean_ = mean
        self.components_ = axes[:, :q] * np.sqrt(np.maximum(spectrum[:q] - noise_variance, 0.0))
        self.noise_variance_ = float(noise_variance)

    def _heldout_scores(self, Y: np.ndarray) -> dict[int, float]:
        """Mean held-out log-likelihood per shape for each candidate q (K-fold, fixed shuffle)."""
        n, d = Y.shape
        if n < 3:
            raise ModelInputError(f"n_components='heldout' needs at least 3 shapes for cross-validation, got {n}")
        k = min(self._HELDOUT_FOLDS, n)
        folds = np.array_split(np.random.default_rng(0).permutation(n), k)
        q_max = min(n - max(len(f) for f in folds) - 1, d - 1)
        totals = np.zeros(q_max)
        valid = np.ones(q_max, bool)
        for held in folds:
            train = np.setdiff1d(np.arange(n), held)
            # one thin SVD per fold; every q from its spectrum
            mean = Y[train].mean(0)
            Yc = Y[train] - mean
            _, eigvals, axes = principal_axes(Yc)
            spectrum, _ = shrunk_spectrum(eigvals, d, self._shrinkage_value(Yc))
            model = self.clone()
            for q in range(1, q_max + 1):
                if not valid[q - 1]:
                    continue
                try:
                    model._set_parameters(mean, eigvals.sum(), spectrum, axes, q)
                except ModelInputError:           # zero noise variance (no shrinkage)
                    valid[q - 1] = False
                    continue
                model._prepare()
                totals[q - 1] += model.log_likelihood(Y[held]).sum()
        if not valid.any():
            raise ModelInputError("n_components='heldout': no latent dimension could be fitted in every fold")
        return {q: float(totals[q - 1] / n) for q in range(1, q_max + 1) if valid[q - 1]}

    def _prepare(self) -> None:
        """Cache M = W^T W + s^2 I (q x q) used by Woodbury / posterior formulas."""
        W = self.components_
        self._M = W.T @ W + self.noise_variance_ * np.eye(W.shape[1])
        self._M_chol = np.linalg.cholesky(self._M)

    @property
    def latent_dim(self) -> int:
        self._check_fitted()
        return int(self.components_.shape[1])

    @property
    def explained_variance_ratio_(self) -> np.ndarray:
        return self.eigenvalues_ / self.eigenvalues_.sum()

    # ------------------------------------------------------------------ API
    def encode(self, Y) -> np.ndarray:
        """Posterior means E[z | y] = M^-1 W^T (y - mu) (Tipping & Bishop 1999), (n, q)."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        return np.linalg.solve(self._M, self.components_.T @ (Y - self.mean_).T).T

    def decode(self, Z) -> np.ndarray:
        """Mean shapes mu + W z, (n, D)."""
        self._check_fitted()
        return self.mean_ + self._check_latents(Z) @ self.components_.T

    def sample_latents(self, n: int, rng=None) -> np.ndarray:
        """z ~ N(0, I), (n, q)."""
        self._check_fitted()
        return as_generator(rng).standard_normal((self._check_count(n), self.latent_dim))

    def decode_features(self, Z) -> np.ndarray:
        """decode(Z) = mean_ + decode_features(Z) @ decode_basis(): here the latents themselves."""
        self._check_fitted()
        return self._check_latents(Z)

    def decode_basis(self) -> np.ndarray:
        """(q, D): W^T."""
        self._check_fitted()
        return self.components_.T

    def sample_with_latents(self, n: int, rng=None) -> tuple[np.ndarray, np.ndarray]:
        """n shapes y = mu + W z, z ~ N(0, I) (+ N(0, s^2 I) if sample_noise), and their z."""
        rng = as_generator(rng)
        Y, Z = super().sample_with_latents(n, rng)
        if self.sample_noise:
            Y += np.sqrt(self.noise_variance_) * rng.standard_normal(Y.shape)
        return Y, Z

    def log_likelihood(self, Y) -> np.ndarray:
        """Exact log N(y | mu, W W^T + s^2 I) per row, by Woodbury and the determinant lemma:
        C^-1 = (I - W M^-1 W^T) / s^2,  log|C| = (D - q) log s^2 + log|M|."""
        self._check_fitted()
        Y = check_rows(Y, self.n_features_)
        d, q, s2 = self.n_features_, self.latent_dim, self.noise_variance_
        R = Y - self.mean_
        proj = np.linalg.solve(self._M_chol, self.components_.T @ R.T)     # L^-1 W^T r, (q, n)
        quad = (np.sum(R**2, 1) - np.sum(proj**2, 0)) / s2
        logdet = (d - q) * np.log(s2) + 2.0 * np.sum(np.log(np.diag(self._M_chol)))
        return -0.5 * (d * _LOG_2PI + logdet + quad)

    def score(self, Y) -> float:
        """Mean held-out log-likelihood per shape (exact)."""
        return float(np.mean(self.log_likelihood(Y)))

    def complete(self, Y_partial, observed_mask) -> np.ndarray:
        """Conditional Gaussian mean of the missing given the observed coordinates, per row:
        y_m = mu_m + W_m (W_o^T W_o + s^2 I)^-1 W_o^T (y_o - mu_o); observed entries kept."""
        Y, mask = self._check_partial(Y_partial, observed_mask)
        W, s2, q = self.components_, self.noise_variance_, self.latent_dim
        R = np.where(mask, Y - self.mean_, 0.0)
        WtW_rows = (mask.astype(float) @ (W[:, :, None] * W[:, None, :]).reshape(W.shape[0], q * q))
        M_rows = WtW_rows.reshape(-1, q, q) + s2 * np.eye(q)
        z = np.linalg.solve(M_rows, (R @ W)[:, :, None])[:, :, 0]          # (n, q)
        out = self.mean_ + z @ W.T
        return np.where(mask, Y, out)

    def posterior(self, y, observed_mask, start=None) -> ShapePosterior:
        """The exact conditional Gaussian of the noise-free shape f = mu + W z given the
        observed coordinates y_o = f_o + eps (the soft form of `complete`, §5.5.3):

          z | y_o ~ N(M_o^-1 W_o^T (y_o - mu_o), s^2 M_o^-1),   M_o = W_o^T W_o + s^2 I,
          E[f | y_o] = mu + W E[z | y_o],   Cov[f | y_o] = W s^2 M_o^-1 W^T,

        i.e. E[y_m | y_o] = mu_m + C_mo C_oo^-1 (y_o - mu_o) with C = W W^T + s^2 I on the
        hidden coordinates (their variance adds s^2 for a noisy y_m). Observed coordinates
        are not kept: the shape passes as near them as the model allows. `start` is unused."""
        self._check_fitted()
        y, mask = self._check_observed(y, observed_mask)
        W, s2, q = self.components_, self.noise_variance_, self.latent_dim
        W_o = W[mask]
        M_o = W_o.T @ W_o + s2 * np.eye(q)
        z = np.linalg.solve(M_o, W_o.T @ (y[mask] - self.mean_[mask]))
        root = W @ np.linalg.cholesky(s2 * np.linalg.inv(M_o))              # Cov f = root root^T
        return ShapePosterior(self.mean_ + W @ z, np.sum(root**2, 1), z)

    # ------------------------------------------------------------------ arrays
    @classmethod
    def _checked_arrays(cls, arrays, label):
        arrays = super()._checked_arrays(arrays, label)
        if arrays["components_"].shape[1] >= arrays["mean_"].shape[0]:
            raise ModelFileError(f"{label}: latent dimension must be smaller than D")
        return arrays
