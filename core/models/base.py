"""Shared parts of the shape models (thesis §5.3): input checks, PCA helpers, the common API.

Every model is an estimator in the scikit-learn habit: the constructor takes hyper-settings
only, `fit(Y)` learns attributes whose names end in `_`, and all randomness comes from an
explicit numpy Generator (never the global state).

Data convention (method.md §4): Y is N x D (N shapes, D = 3L landmark coordinates), N << D.
Models work on Y centred by its mean shape `mean_`.
"""

from __future__ import annotations

from typing import Callable, ClassVar

import numpy as np
from scipy.optimize import minimize

from ..errors import ModelFileError, ShapeGenError

__all__ = [
    "ModelInputError",
    "ShapeModel",
    "ProgressCallback",
    "as_generator",
    "check_training_data",
    "check_rows",
    "check_mask",
    "check_latent_dim",
    "principal_axes",
    "ledoit_wolf_shrinkage",
    "shrunk_spectrum",
    "latent_dim_for_variance",
    "default_latent_dim",
    "pca_latents",
]

ProgressCallback = Callable[[float, str], None]


class ModelInputError(ShapeGenError, ValueError):
    """Data or settings given to a shape model are unusable (the message says which and why)."""


# ----------------------------------------------------------------------------- validation

def as_generator(seed) -> np.random.Generator:
    """A numpy Generator from None / int / Generator (never touches the global state)."""
    if isinstance(seed, np.random.Generator):
        return seed
    if seed is None or isinstance(seed, (int, np.integer)):
        return np.random.default_rng(seed)
    raise ModelInputError(f"random_state / rng must be None, an int or a numpy Generator, not {type(seed).__name__}")


def _as_float_matrix(Y, name: str) -> np.ndarray:
    try:
        Y = np.asarray(Y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ModelInputError(f"{name} must be a numeric array ({exc})") from None
    if Y.ndim != 2:
        raise ModelInputError(f"{name} must be a 2-D array (shapes x coordinates), got {Y.ndim}-D shape {Y.shape}")
    return Y


def check_training_data(Y) -> np.ndarray:
    """Y as float64 (N, D); refuses N < 2, D < 1, NaN / inf and data without any variance."""
    Y = _as_float_matrix(Y, "Y")
    n, d = Y.shape
    if n < 2:
        raise ModelInputError(f"Y has {n} shape(s); a shape model needs at least 2")
    if d < 1:
        raise ModelInputError("Y has no coordinates (D = 0)")
    bad = ~np.isfinite(Y)
    if bad.any():
        rows = np.unique(np.nonzero(bad)[0])
        raise ModelInputError(
            f"Y contains NaN or infinite values in {bad.sum()} entries (rows {rows[:10].tolist()}"
            f"{' ...' if rows.size > 10 else ''})"
        )
    if not np.any(Y != Y[0]):
        raise ModelInputError("Y has no variance: all shapes are identical")
    return Y


def check_rows(Y, n_features: int, name: str = "Y", allow_nan: bool = False) -> np.ndarray:
    """Rows to encode / score / complete: float64 (n, D) with the training D."""
    if np.ndim(Y) == 1:
        Y = np.asarray(Y)[None, :]
    Y = _as_float_matrix(Y, name)
    if Y.shape[1] != n_features:
        raise ModelInputError(
            f"{name} has {Y.shape[1]} coordinates per shape but the model was fitted on D = {n_features}"
        )
    if not allow_nan and not np.all(np.isfinite(Y)):
        raise ModelInputError(f"{name} contains NaN or infinite values")
    return Y


def check_mask(mask, shape: tuple[int, int]) -> np.ndarray:
    """Observed-coordinate mask: bool (n, D), True = observed, at least one observed per row."""
    mask = np.asarray(mask)
    if mask.ndim == 1:
        mask = mask[None, :]
    if mask.dtype != bool:
        raise ModelInputError(f"observed_mask must be a boolean array, got dtype {mask.dtype}")
    if mask.shape != shape:
        raise ModelInputError(f"observed_mask has shape {mask.shape} but Y_partial has shape {shape}")
    empty = np.nonzero(~mask.any(axis=1))[0]
    if empty.size:
        raise ModelInputError(f"observed_mask rows {empty[:10].tolist()} observe no coordinate")
    return mask


def check_latent_dim(q, n_samples: int, n_features: int | None = None) -> int:
    """A latent dimension: integer with 1 <= q < N (and q < D when given)."""
    if isinstance(q, bool) or not isinstance(q, (int, np.integer)):
        raise ModelInputError(f"latent dimension must be an integer, got {q!r}")
    q = int(q)
    if q < 1:
        raise ModelInputError(f"latent dimension must be >= 1, got {q}")
    if q >= n_samples:
        raise ModelInputError(
            f"latent dimension {q} must be smaller than the number of shapes N = {n_samples}"
        )
    if n_features is not None and q >= n_features:
        raise ModelInputError(
            f"latent dimension {q} must be smaller than the number of coordinates D = {n_features}"
        )
    return q


# ----------------------------------------------------------------------------- PCA helpers

def principal_axes(Yc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thin SVD of centred data: (scores U*s (N, r), ML eigenvalues s^2/N (r,), axes V (D, r)).

    Only the r = min(N, D) non-trivial directions are formed, never a D x D matrix.
    Signs are fixed (largest |entry| of each axis positive) so results are reproducible.
    """
    n = Yc.shape[0]
    U, s, Vt = np.linalg.svd(Yc, full_matrices=False)
    flip = np.sign(Vt[np.arange(Vt.shape[0]), np.argmax(np.abs(Vt), axis=1)])
    flip[flip == 0] = 1.0
    U, Vt = U * flip, Vt * flip[:, None]
    return U * s, s**2 / n, Vt.T


def ledoit_wolf_shrinkage(Yc: np.ndarray) -> float:
    """Ledoit & Wolf (2004) shrinkage of S = Yc^T Yc / N towards (tr S / D) I (thesis §5.3.2.2).

    Same estimator as sklearn.covariance.ledoit_wolf_shrinkage, computed from the N x N Gram
    matrix G = Yc Yc^T:  ||S||_F^2 = ||G||_F^2 / N^2,  sum_n ||y_n||^4 from the row norms.
    """
    n, d = Yc.shape
    gram = Yc @ Yc.T
    row_sq = np.diag(gram).copy()
    mu = row_sq.sum() / (n * d)                       # tr S / D
    frob_S2 = np.sum(gram**2) / n**2                  # ||S||_F^2
    beta_sum = np.sum(row_sq**2)                      # sum_n ||y_n||^4
    beta = (beta_sum / n - frob_S2) / (d * n)
    delta = (frob_S2 - 2.0 * mu * row_sq.sum() / n + d * mu**2) / d
    beta = min(beta, delta)
    return 0.0 if beta == 0 else float(beta / delta)


def shrunk_spectrum(eigvals: np.ndarray, n_features: int, shrinkage: float) -> tuple[np.ndarray, float]:
    """Eigenvalues of (1 - s) S + s (tr S / D) I in the data span, and the value off it.

    Shrinkage towards a multiple of I keeps the eigenvectors (method.md §4).
    """
    floor = shrinkage * eigvals.sum() / n_features
    return (1.0 - shrinkage) * eigvals + floor, floor


def latent_dim_for_variance(spectrum: np.ndarray, total: float, fraction: float) -> int:
    """Smallest q whose q largest eigenvalues explain `fraction` of the total variance (§5.4.1)."""
    cumulative = np.cumsum(spectrum) / total
    return int(np.searchsorted(cumulative, fraction - 1e-12) + 1)


def default_latent_dim(Yc: np.ndarray, fraction: float = 0.8) -> int:
    """The 80 % rule on the Ledoit-Wolf shrunk covariance, capped at N - 1 (used by all models)."""
    n, d = Yc.shape
    _, eigvals, _ = principal_axes(Yc)
    spectrum, _ = shrunk_spectrum(eigvals, d, ledoit_wolf_shrinkage(Yc))
    q = latent_dim_for_variance(spectrum, eigvals.sum(), fraction)
    return max(1, min(q, n - 1, d - 1 if d > 1 else 1))


def pca_latents(Yc: np.ndarray, q: int) -> np.ndarray:
    """PCA initialisation of latents (§5.3.3): the first q principal scores, scaled so the first
    has unit standard deviation (relative scales kept, which ARD needs).

    The scores U s come from the N x N Gram matrix Yc Yc^T = U s^2 U^T (cheaper than the SVD
    of Yc for N << D), with the signs of `principal_axes` (largest |entry| of V = Yc^T U / s
    positive)."""
    r = min(Yc.shape)
    eigvals, U = np.linalg.eigh(Yc @ Yc.T)
    eigvals, U = eigvals[::-1][: min(q, r)], U[:, ::-1][:, : min(q, r)]
    s = np.sqrt(np.maximum(eigvals, 0.0))
    axes = Yc.T @ (U / np.where(s > 0, s, 1.0))
    flip = np.sign(axes[np.argmax(np.abs(axes), axis=0), np.arange(axes.shape[1])])
    flip[flip == 0] = 1.0
    Z = U * (s * flip)
    if Z.shape[1] < q:  # fewer non-trivial directions than q: pad with tiny deterministic values
        pad = 1e-3 * np.linspace(-1, 1, Yc.shape[0])[:, None] * np.ones((1, q - Z.shape[1]))
        Z = np.hstack([Z, pad])
    scale = Z[:, 0].std()
    return Z / (scale if scale > 0 else 1.0)


def standardised_pca_latents(Yc: np.ndarray, q: int) -> np.ndarray:
    """GPy's latent initialisation: PCA of the column-standardised data, each of the q
    scores scaled to unit standard deviation."""
    column_std = Yc.std(0)
    Z = pca_latents(Yc / np.where(column_std > 0, column_std, 1.0), q)
    return Z / np.maximum(Z.std(0), 1e-12)


# ----------------------------------------------------------------------------- optimiser

def lbfgs(objective, x0, *, max_iter: int, progress: ProgressCallback | None, message: str,
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


# ----------------------------------------------------------------------------- common API

class ShapeModel:
    """Common API of PPCA, GP-LVM and Bayesian GP-LVM (issue 4).

    Subclasses implement `fit`, `encode`, `decode`, `complete`, `score`, `sample` and declare
    `_ARRAY_SPEC`: key -> (dtype kind, shape as symbols) for `to_arrays` / `from_arrays`.
    Symbols are dimension names ('N', 'D', 'Q', 'M', ...) that must agree across keys.
    """

    model_type: ClassVar[str] = ""
    _ARRAY_SPEC: ClassVar[dict[str, tuple[str, tuple[str, ...]]]] = {}
    _HYPER_KEYS: ClassVar[tuple[str, ...]] = ()

    # ---- helpers used by subclasses
    def _check_fitted(self) -> None:
        if not hasattr(self, "mean_"):
            raise ModelInputError(f"this {type(self).__name__} is not fitted yet: call fit(Y) first")

    @property
    def n_features_(self) -> int:
        self._check_fitted()
        return int(self.mean_.shape[0])

    @property
    def latent_dim(self) -> int:
        """Latent dimension Q of the fitted model."""
        raise NotImplementedError

    @staticmethod
    def _check_count(n) -> int:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ModelInputError(f"number of samples must be a non-negative integer, got {n!r}")
        return int(n)

    def _check_latents(self, Z) -> np.ndarray:
        Z = np.asarray(Z, dtype=np.float64)
        if Z.ndim == 1:
            Z = Z[None, :]
        if Z.ndim != 2 or Z.shape[1] != self.latent_dim:
            raise ModelInputError(f"latents must have shape (n, {self.latent_dim}), got {Z.shape}")
        if not np.all(np.isfinite(Z)):
            raise ModelInputError("latents contain NaN or infinite values")
        return Z

    def _check_partial(self, Y_partial, observed_mask) -> tuple[np.ndarray, np.ndarray]:
        self._check_fitted()
        Y = check_rows(Y_partial, self.n_features_, "Y_partial", allow_nan=True)
        mask = check_mask(observed_mask, Y.shape)
        if not np.all(np.isfinite(Y[mask])):
            raise ModelInputError("Y_partial has NaN or infinite values at observed coordinates")
        return Y, mask

    # ---- serialisation
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain numeric / str arrays (no objects) describing the fitted model."""
        self._check_fitted()
        out = {"model_type": np.array(self.model_type)}
        for key in self._ARRAY_SPEC:
            if key == "model_type":
                continue
            out[key] = np.array(self._array_value(key))
        return out

    def _array_value(self, key: str):
        return getattr(self, key)

    @classmethod
    def from_arrays(cls, arrays) -> "ShapeModel":
        """Rebuild a fitted model from `to_arrays()` output; refuses anything else (ModelFileError)."""
        arrays = _validate_arrays(cls, arrays)
        model = cls.__new__(cls)
        model._restore(arrays)
        return model

    def _restore(self, arrays: dict[str, np.ndarray]) -> None:
        raise NotImplementedError


def _validate_arrays(cls, arrays) -> dict[str, np.ndarray]:
    name = cls.__name__
    if not hasattr(arrays, "keys"):
        raise ModelFileError(f"{name}.from_arrays needs a mapping of arrays, got {type(arrays).__name__}")
    keys = set(arrays.keys())
    expected = set(cls._ARRAY_SPEC)
    missing, unknown = sorted(expected - keys), sorted(keys - expected)
    if missing:
        raise ModelFileError(f"{name} arrays are missing key(s) {missing}")
    if unknown:
        raise ModelFileError(f"{name} arrays have unexpected key(s) {unknown}")
    sizes: dict[str, int] = {}
    defined_by: dict[str, str] = {}
    out = {}
    for key, (kind, shape) in cls._ARRAY_SPEC.items():
        value = arrays[key]
        if not isinstance(value, np.ndarray):
            raise ModelFileError(f"{name} array '{key}' is a {type(value).__name__}, not a numpy array")
        if value.dtype.kind == "O":
            raise ModelFileError(f"{name} array '{key}' holds Python objects; refused")
        kinds = {"f": "f", "i": "iu", "U": "U"}[kind]
        if value.dtype.kind not in kinds:
            raise ModelFileError(f"{name} array '{key}' has dtype {value.dtype}, expected kind '{kind}'")
        if value.ndim != len(shape):
            raise ModelFileError(f"{name} array '{key}' has shape {value.shape}, expected {len(shape)}-D {shape}")
        for axis, symbol in enumerate(shape):
            size = value.shape[axis]
            if symbol.isdigit():
                if size != int(symbol):
                    raise ModelFileError(f"{name} array '{key}' has shape {value.shape}, expected {shape}")
            elif sizes.setdefault(symbol, size) != size:
                raise ModelFileError(
                    f"{name} array '{key}' has {symbol} = {size} along axis {axis}, "
                    f"but array '{defined_by[symbol]}' has {symbol} = {sizes[symbol]}"
                )
            else:
                defined_by.setdefault(symbol, key)
        if kind == "f" and not np.all(np.isfinite(value)):
            raise ModelFileError(f"{name} array '{key}' contains NaN or infinite values")
        out[key] = value.astype(np.float64) if kind == "f" else value
    if str(out["model_type"]) != cls.model_type:
        raise ModelFileError(f"arrays describe a '{out['model_type']}' model, not '{cls.model_type}' ({name})")
    for symbol in ("N", "D", "Q", "M"):
        if sizes.get(symbol, 1) < 1:
            raise ModelFileError(f"{name} arrays have {symbol} = 0")
    return out
