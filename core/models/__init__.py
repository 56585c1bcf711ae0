"""Shape models of thesis §5.3 behind one estimator API (docs/method.md §4).

- `PPCA`           probabilistic PCA with Ledoit-Wolf shrinkage (§5.3.2)
- `GPLVM`          GP latent variable model, RBF kernel, KDE latent density (§5.3.3, §5.4.3)
- `BayesianGPLVM`  variational sparse Bayesian GP-LVM, ARD RBF (§5.3.4, Titsias & Lawrence 2010)

All share (base.ShapeModel): fit(Y, progress=None), sample(n, rng), sample_with_latents(n, rng),
sample_latents(n, rng), encode(Y), decode(Z), complete(Y_partial, observed_mask),
posterior(y, observed_mask, start) (the most probable shape given pinned coordinates), score(Y),
latent_dim, get_params(), clone(), to_arrays(), from_arrays(d). The two GP-LVMs share their fit
and row search (latent_variable.LatentVariableModel). `make_model` builds any of them by name.

Modules: base (input checks, PCA helpers, the common API and model arrays), latent_variable
(the GP-LVMs' shared fit, row search and numerics), kernels (RBF kernel, psi-statistics), kde
(latent Gaussian KDE), ppca, gplvm, bgplvm, scaling (how their cost grows with the number of
shapes; the note an N³ fit of many shapes gives).
"""

from ..base.errors import ModelFileError
from .base import ModelInputError, ShapeModel
from .bgplvm import BayesianGPLVM
from .gplvm import GPLVM
from .ppca import PPCA

__all__ = ["PPCA", "GPLVM", "BayesianGPLVM", "MODEL_TYPES", "ModelInputError", "ShapeModel",
           "make_model", "model_from_arrays"]

MODEL_TYPES: dict[str, type[ShapeModel]] = {"ppca": PPCA, "gplvm": GPLVM, "bgplvm": BayesianGPLVM}


def make_model(name: str, latent_dim: int | None = None, seed: int = 0, **options) -> ShapeModel:
    """An unfitted model of type `name` with the project defaults: latent dimension
    `latent_dim` (None = the model's 80 % rule), `seed` as its random_state where it takes one,
    and any other constructor arguments in `options`."""
    if name not in MODEL_TYPES:
        raise ModelInputError(f"unknown model name {name!r} (known: {', '.join(MODEL_TYPES)})")
    cls = MODEL_TYPES[name]
    accepted = set(cls._param_names()) - {"n_components", "random_state"}
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise ModelInputError(f"{cls.__name__} has no option(s) {unknown} (options: {', '.join(sorted(accepted))})")
    if "random_state" in cls._param_names():
        options["random_state"] = seed
    return cls(n_components=latent_dim, **options)


def model_from_arrays(arrays) -> ShapeModel:
    """Rebuild any fitted model from its `to_arrays()` dict, dispatching on 'model_type'."""
    if not hasattr(arrays, "keys") or "model_type" not in arrays.keys():
        raise ModelFileError("model arrays have no 'model_type' key")
    name = str(arrays["model_type"])
    if name not in MODEL_TYPES:
        raise ModelFileError(f"unknown model_type '{name}' (known: {', '.join(MODEL_TYPES)})")
    return MODEL_TYPES[name].from_arrays(arrays)
