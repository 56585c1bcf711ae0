"""Shared parts of the shape models (thesis §5.3): input checks, PCA helpers, the common API.

Every model is an estimator in the scikit-learn habit: the constructor takes hyper-settings
only, `fit(Y)` learns attributes whose names end in `_`, and all randomness comes from an
explicit numpy Generator (never the global state).

Data convention (docs/method.md §4): Y is N x D (N shapes, D = 3L landmark coordinates), N << D.
Models work on Y centred by its mean shape `mean_`.
"""

from __future__ import annotations

import copy
import inspect
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..base.errors import ModelFileError, ShapeGenError
from ..base.npzfile import ArraySpec, validate_arrays

__all__ = [
    "ModelInputError",
    "ShapeModel",
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
    "standardised_pca_latents",
    "ShapePosterior",
]


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

    Shrinkage towards a multiple of I keeps the eigenvectors (docs/method.md §4).
    """
    floor = shrinkage * eigvals.sum() / n_features
    return (1.0 - shrinkage) * eigvals + floor, floor


def latent_dim_for_variance(eigvals: np.ndarray, fraction: float, n_samples: int, n_features: int) -> int:
    """Smallest q whose q largest sample eigenvalues explain `fraction` of the data's total
    variance (§5.4.1), 1 <= q <= min(N, D) - 1. The explained variance of the data itself,
    never of a shrunk spectrum: shrinkage moves variance off the data span, so the shrunk
    leading eigenvalues would never add up to the fraction and every collection would get
    N - 1 dimensions."""
    if not 0.0 < fraction <= 1.0:
        raise ModelInputError(f"variance_fraction must be in (0, 1], got {fraction}")
    cumulative = np.cumsum(eigvals) / eigvals.sum()
    q = int(np.searchsorted(cumulative, fraction - 1e-12) + 1)
    return max(1, min(q, n_samples - 1, n_features - 1 if n_features > 1 else 1))


def default_latent_dim(Yc: np.ndarray, fraction: float = 0.8) -> int:
    """The 80 % rule (`latent_dim_for_variance`) on centred data Yc (used by all models)."""
    return latent_dim_for_variance(principal_axes(Yc)[1], fraction, *Yc.shape)


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


# ----------------------------------------------------------------------------- posterior

@dataclass(frozen=True)
class ShapePosterior:
    """The most probable shape given some observed coordinates (soft: they are noisy
    observations under the model's noise, so the shape need not pass through them), how
    uncertain each coordinate stays, and the latent point it comes from (`ShapeModel.posterior`).

    mean: (D,) posterior mean of the noise-free shape f (for the GP-LVMs, f at the most
    probable latent point); variance: (D,) posterior variance of f per coordinate; latent: (Q,).
    """

    mean: np.ndarray
    variance: np.ndarray
    latent: np.ndarray


# ----------------------------------------------------------------------------- common API

#: Integer codes of the non-integer choices of a parameter in model files.
_PARAM_CODES: dict[str, dict[object, int]] = {"n_components": {None: -1, "heldout": -2}}


class ShapeModel:
    """Common API of PPCA, GP-LVM and Bayesian GP-LVM.

    The parameters are the constructor's arguments, each stored under its own name
    (scikit-learn's convention): `get_params` reads them through the signature, and `clone`
    and the model files (`to_arrays`, `from_arrays`) build on it.

    Subclasses implement `fit`, `encode`, `decode`, `sample_latents`, `complete`, `posterior`,
    `score`, `decode_features`, `decode_basis` and `_prepare` (caches derived from the fitted
    attributes), and declare `_ARRAY_SPEC`: the arrays of `to_arrays` as npzfile ArraySpecs,
    i.e. "model_type", "param_<name>" per saved parameter and the fitted attributes (names
    ending in "_"). Equal dimension names ('N', 'D', 'Q', 'M', ...) must agree across arrays.
    """

    model_type: ClassVar[str] = ""
    _ARRAY_SPEC: ClassVar[dict[str, ArraySpec]] = {}
    #: parameters left out of model files: random_state only seeds `fit` (and a Generator has
    #: no file form), so a loaded model has the default
    _UNSAVED_PARAMS: ClassVar[tuple[str, ...]] = ("random_state",)
    #: parameter -> the fitted attribute that holds its value in model files
    _PARAMS_IN_FITTED: ClassVar[dict[str, str]] = {}
    #: fitted attributes whose every entry must be positive in a model file
    _POSITIVE: ClassVar[tuple[str, ...]] = ()

    # ---- parameters
    @classmethod
    def _param_names(cls) -> tuple[str, ...]:
        return tuple(inspect.signature(cls.__init__).parameters)[1:]

    def get_params(self) -> dict[str, object]:
        """The constructor's arguments by name (scikit-learn's `get_params`)."""
        return {name: getattr(self, name) for name in self._param_names()}

    def clone(self) -> "ShapeModel":
        """A new, unfitted model with copies of this one's parameters (scikit-learn's `clone`)."""
        return type(self)(**copy.deepcopy(self.get_params()))

    @classmethod
    def _saved_param_names(cls) -> tuple[str, ...]:
        return tuple(name for name in cls._param_names()
                     if name not in cls._UNSAVED_PARAMS and name not in cls._PARAMS_IN_FITTED)

    @classmethod
    def _fitted_keys(cls) -> tuple[str, ...]:
        return tuple(key for key in cls._ARRAY_SPEC if key != "model_type" and not key.startswith("param_"))

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

    def _check_observed(self, y, observed_mask) -> tuple[np.ndarray, np.ndarray]:
        """One row y (D,) and its mask (D,) for `posterior`: finite where observed, at least
        one coordinate observed."""
        Y, mask = self._check_partial(np.asarray(y, dtype=np.float64).reshape(1, -1),
                                      np.asarray(observed_mask).reshape(1, -1))
        return Y[0], mask[0]

    def posterior(self, y, observed_mask, start=None) -> ShapePosterior:
        """The most probable shape given the coordinates of y where observed_mask is True,
        each a noisy observation under the model's noise (thesis §5.5.3, completion, made
        soft), with its per-coordinate posterior variance; `start` (Q,) is where a latent
        search starts (the GP-LVMs; ignored by PPCA's closed form)."""
        raise NotImplementedError

    # ---- sampling
    def training_latents(self, Y, progress=None) -> np.ndarray:
        """The latents of the training rows Y (the rows the model was fitted to, in order),
        (N, Q): `encode`; the GP-LVMs may take the fit's own (latent_variable.py)."""
        return self.encode(Y)

    def sample_with_latents(self, n: int, rng=None) -> tuple[np.ndarray, np.ndarray]:
        """n shapes (n, D) from the model, as its settings ask (PPCA: `sample_noise`), and the
        latents (n, Q) they were decoded from."""
        rng = as_generator(rng)
        latents = self.sample_latents(n, rng)
        return self.decode(latents), latents

    def sample(self, n: int, rng=None) -> np.ndarray:
        """n shapes (n, D) from the model (`sample_with_latents` without the latents)."""
        return self.sample_with_latents(n, rng)[0]

    # ---- serialisation
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain numeric / str arrays (no objects) describing the fitted model: its type, the
        saved parameters as "param_<name>" and the fitted attributes."""
        self._check_fitted()
        out = {"model_type": np.array(self.model_type)}
        for name in self._saved_param_names():
            key = f"param_{name}"
            out[key] = _encode_param(name, getattr(self, name), self._ARRAY_SPEC[key].kinds)
        for key in self._fitted_keys():
            out[key] = np.array(getattr(self, key))
        return out

    @classmethod
    def from_arrays(cls, arrays) -> "ShapeModel":
        """Rebuild a fitted model from `to_arrays()` output; refuses anything else (ModelFileError)."""
        arrays = cls._checked_arrays(arrays, f"{cls.__name__} arrays")
        defaults = inspect.signature(cls.__init__).parameters
        params = {name: _decode_param(name, arrays[f"param_{name}"], defaults[name].default)
                  for name in cls._saved_param_names()}
        params.update({name: arrays[key].item() for name, key in cls._PARAMS_IN_FITTED.items()})
        model = cls(**params)
        for key in cls._fitted_keys():
            setattr(model, key, arrays[key].item() if arrays[key].ndim == 0 else arrays[key])
        try:
            model._prepare()
        except np.linalg.LinAlgError:
            raise ModelFileError(f"{cls.__name__} arrays: the stored kernel matrices are not positive definite") from None
        return model

    def _prepare(self) -> None:
        raise NotImplementedError

    @classmethod
    def _checked_arrays(cls, arrays, label: str) -> dict[str, np.ndarray]:
        """`arrays` validated against `_ARRAY_SPEC` (exactly its keys; float arrays as float64)."""
        if not hasattr(arrays, "keys"):
            raise ModelFileError(f"{label}: need a mapping of arrays, got {type(arrays).__name__}")
        unknown = sorted(set(arrays.keys()) - set(cls._ARRAY_SPEC))
        validate_arrays(arrays, cls._ARRAY_SPEC, label)
        if unknown:
            raise ModelFileError(f"{label}: unexpected array(s) {unknown}")
        out = {key: np.asarray(arrays[key]) for key in cls._ARRAY_SPEC}
        out = {key: value.astype(np.float64) if value.dtype.kind == "f" else value for key, value in out.items()}
        if str(out["model_type"]) != cls.model_type:
            raise ModelFileError(f"arrays describe a '{out['model_type']}' model, not '{cls.model_type}' ({cls.__name__})")
        for key, value in out.items():
            if 0 in value.shape:
                raise ModelFileError(f"{label}: array {key!r} is empty (shape {value.shape})")
        for key in cls._POSITIVE:
            if not np.all(out[key] > 0):
                raise ModelFileError(f"{label}: {key} must be positive")
        return out


def _encode_param(name: str, value, kinds: str) -> np.ndarray:
    """A parameter as a 0-d array of the spec's kind ('U' text, 'f' float, else integer; None
    and text choices by `_PARAM_CODES`)."""
    if kinds == "U":
        return np.array(str(value))
    if kinds == "f":
        return np.array(float(value))
    if value is None or isinstance(value, str):
        return np.array(_PARAM_CODES[name][value])
    return np.array(int(value))


def _decode_param(name: str, array: np.ndarray, default):
    """The inverse of `_encode_param`: text that reads as a number becomes a float, integer
    codes their choice, and integers of a parameter whose default is a bool a bool."""
    if array.dtype.kind == "U":
        text = str(array)
        try:
            return float(text)
        except ValueError:
            return text
    if array.dtype.kind == "f":
        return float(array)
    number = int(array)
    choices = {code: choice for choice, code in _PARAM_CODES.get(name, {}).items()}
    if number in choices:
        return choices[number]
    return bool(number) if isinstance(default, bool) else number
