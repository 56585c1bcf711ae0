"""The random choices of the evaluation protocol: one reproducible random stream per
purpose, and the k-fold split of the shapes."""

from __future__ import annotations

import numpy as np

from .metrics import EvaluationError

__all__ = ["random_stream", "kfold_indices", "heldout_folds"]


def random_stream(seed: int, *stream: int) -> np.random.Generator:
    """An independent, reproducible random stream per purpose (seed, stream id...)."""
    return np.random.default_rng([int(seed), *stream])


def kfold_indices(n: int, folds: int, rng: np.random.Generator) -> list[np.ndarray]:
    """A random partition of range(n) into `folds` test sets of near-equal size (sorted)."""
    if isinstance(folds, bool) or not isinstance(folds, (int, np.integer)) or folds < 2:
        raise EvaluationError(f"folds must be an integer >= 2, got {folds!r}")
    if folds > n:
        raise EvaluationError(f"{folds} folds need at least {folds} shapes, but the collection has {n}")
    return [np.sort(part) for part in np.array_split(rng.permutation(n), folds)]


def heldout_folds(n: int, folds: int, seed: int) -> list[np.ndarray]:
    """The k-fold split `run_evaluation` uses for `seed` (random stream 1)."""
    return kfold_indices(n, folds, random_stream(seed, 1))
