"""Baselines every model is compared with: a memoriser of the training set and the mean
shape. They offer the models' fit / sample / complete interface."""

from __future__ import annotations

import numpy as np

__all__ = ["TrainingSetModel", "MeanShapeModel"]


class TrainingSetModel:
    """Memorisation baseline: samples are training shapes drawn without replacement (with
    replacement when more are asked than exist); completion copies the hidden coordinates of
    the training shape closest on the visible ones (nearest-neighbour completion)."""

    model_type = "training-set"

    def fit(self, Y, progress=None) -> "TrainingSetModel":
        self.training_ = np.asarray(Y, dtype=np.float64).copy()
        return self

    @property
    def latent_dim(self) -> int:
        return 0

    def sample(self, n: int, rng=None) -> np.ndarray:
        rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
        count = len(self.training_)
        return self.training_[rng.choice(count, n, replace=n > count)]

    def complete(self, Y_partial, observed_mask) -> np.ndarray:
        Y = np.asarray(Y_partial, dtype=np.float64)
        mask = np.asarray(observed_mask, bool)
        out = Y.copy()
        for i in range(len(Y)):
            o = mask[i]
            nearest = np.argmin(np.sum((self.training_[:, o] - Y[i, o]) ** 2, 1))
            out[i, ~o] = self.training_[nearest, ~o]
        return out


class MeanShapeModel(TrainingSetModel):
    """Collapsed baseline: every sample is the mean training shape, and completion fills the
    hidden coordinates with it (the reference level of the completion error: relative 1)."""

    model_type = "mean-shape"

    def sample(self, n: int, rng=None) -> np.ndarray:
        return np.repeat(self.training_.mean(0)[None, :], n, axis=0)

    def complete(self, Y_partial, observed_mask) -> np.ndarray:
        mask = np.asarray(observed_mask, bool)
        return np.where(mask, np.asarray(Y_partial, dtype=np.float64), self.training_.mean(0))
