"""Latent vectors in training standard deviations: the units of Explore's sliders.

A value v_k stands for z_k = centre_k + v_k scale_k, where centre and scale are the mean and
standard deviation of the training shapes' latents in dimension k. A dimension whose training
latents reach beyond `limit` standard deviations (an outlier among more than ten shapes;
with ten or fewer none can, by Samuelson's inequality |x - mean| <= sd sqrt(N - 1)) gets the
scale max|z_k - centre_k| / limit instead, so the ±limit range covers every training shape.

Random values come from the model's own latent density (its `sample_latents`: PPCA and
Bayesian GP-LVM the prior N(0, I), GP-LVM the KDE of the training latents) and stay within
±limit: a draw with any value outside is redrawn (from the same generator; the density
truncated to the box), and when `max_draws` draws all fall outside, the last is clipped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..base.errors import ShapeGenError

__all__ = ["LatentUnits", "RandomValues", "SLIDER_LIMIT"]

#: the sliders' range, in training standard deviations
SLIDER_LIMIT = 3.0


@dataclass(frozen=True)
class RandomValues:
    """One random latent vector in slider units, and how it was obtained."""

    values: np.ndarray     # (Q,) within ±limit
    redraws: int           # draws rejected before this one
    clipped: bool          # True: no draw fell within ±limit, the last one was clipped


@dataclass(frozen=True)
class LatentUnits:
    """Per latent dimension: z = centre + value × scale (module docstring)."""

    centre: np.ndarray
    scale: np.ndarray
    limit: float = SLIDER_LIMIT

    @classmethod
    def from_training(cls, latents: np.ndarray, limit: float = SLIDER_LIMIT) -> "LatentUnits":
        """Mean and standard deviation of the training latents (N, Q), the scale widened where
        a training latent lies beyond ±limit of them (and 1 where they do not vary)."""
        latents = np.asarray(latents, dtype=np.float64)
        centre = latents.mean(axis=0)
        spread = np.abs(latents - centre).max(axis=0) / limit
        scale = np.maximum(latents.std(axis=0), spread)
        scale[~(scale > 1e-9)] = 1.0
        return cls(centre, scale, float(limit))

    def to_values(self, z: np.ndarray) -> np.ndarray:
        """Slider values of latent vector(s) z."""
        return (np.asarray(z, dtype=np.float64) - self.centre) / self.scale

    def to_latent(self, values: np.ndarray) -> np.ndarray:
        """Latent vector(s) of slider values."""
        return self.centre + np.asarray(values, dtype=np.float64) * self.scale

    def random(self, sample_latents: Callable[[int, np.random.Generator], np.ndarray],
               rng: np.random.Generator, max_draws: int = 1000, batch: int = 50) -> RandomValues:
        """A draw of `sample_latents(n, rng)` (the model's latent density) within ±limit,
        redrawn in batches of `batch` up to `max_draws` draws, else the last one clipped."""
        if max_draws < 1 or batch < 1:
            raise ShapeGenError(f"max_draws and batch must be at least 1, got {max_draws} and {batch}")
        drawn = 0
        while drawn < max_draws:
            values = self.to_values(sample_latents(min(batch, max_draws - drawn), rng))
            inside = np.nonzero(np.all(np.abs(values) <= self.limit, axis=1))[0]
            if inside.size:
                return RandomValues(values[inside[0]], drawn + int(inside[0]), False)
            drawn += len(values)
        return RandomValues(np.clip(values[-1], -self.limit, self.limit), drawn - 1, True)
