"""The 2-D latent map and the morph (thesis §5.5.5, Figs. 5.11 and 5.12).

* outlier score of shape i = the leave-one-out negative log density of its latent under the
  Gaussian KDE of the others, −log[(1/(N−1)) Σ_{j≠i} N(z_i | z_j, h² I)], h the model's KDE
  bandwidth; robust z-score (score − median) / (1.4826 MAD), flagged above 3.
* morph: decode z(t) = (1 − t) z_a + t z_b along a straight latent line between the two
  training latents farthest apart whose line stays where the latent KDE has support
  (`choose_morph_endpoints`).
"""

from __future__ import annotations

import numpy as np

from ..models import kde
from .metrics import landmark_rms_matrix

__all__ = ["latent_outlier_scores", "choose_morph_endpoints", "latent_morph"]


def latent_outlier_scores(Z, bandwidth: float) -> dict:
    """Leave-one-out KDE outlier score of each latent (module docstring) and robust z-scores."""
    Z = np.asarray(Z, dtype=np.float64)
    score = -kde.leave_one_out_log_density(Z, bandwidth)
    median = np.median(score)
    mad = 1.4826 * np.median(np.abs(score - median))
    robust_z = (score - median) / mad if mad > 0 else np.zeros(len(Z))
    return {"score": score, "robust_z": robust_z, "flagged": robust_z > 3.0}


def choose_morph_endpoints(Z, bandwidth: float, quantile: float = 0.1, checks: int = 25) -> tuple[int, int]:
    """Two training latents to morph between: the pair farthest apart whose straight line stays
    where the latent KDE has support, i.e. the KDE log density at `checks` points along the line
    never drops below its `quantile` over the training latents themselves (a morph through empty
    latent space only shows the GP reverting to the mean shape). Falls back to the farthest pair."""
    Z = np.asarray(Z, dtype=np.float64)
    floor = np.quantile(kde.log_density(Z, Z, bandwidth), quantile)
    t = np.linspace(0.0, 1.0, checks)[:, None]
    d2 = np.sum((Z[:, None, :] - Z[None, :, :]) ** 2, -1)
    best, best_d2 = None, -1.0
    for a in range(len(Z)):
        for b in range(a + 1, len(Z)):
            if d2[a, b] <= best_d2:
                continue
            line = (1.0 - t) * Z[a] + t * Z[b]
            if kde.log_density(line, Z, bandwidth).min() >= floor:
                best, best_d2 = (a, b), d2[a, b]
    if best is None:
        a, b = np.unravel_index(int(np.argmax(d2)), d2.shape)
        best = (int(min(a, b)), int(max(a, b)))
    return best


def latent_morph(model, z_start, z_end, steps: int = 7) -> dict:
    """Decode z(t) = (1 − t) z_a + t z_b, t = 0 .. 1 in `steps` equal steps (Fig. 5.12).

    Returns t, the latents, the shapes (steps, 3L) and the step lengths d(frame_k, frame_k+1)
    (a smooth morph has near-equal steps)."""
    t = np.linspace(0.0, 1.0, steps)
    Z = (1.0 - t)[:, None] * np.asarray(z_start)[None, :] + t[:, None] * np.asarray(z_end)[None, :]
    shapes = model.decode(Z)
    step = np.array([landmark_rms_matrix(shapes[k], shapes[k + 1])[0, 0] for k in range(steps - 1)])
    return {"t": t, "latents": Z, "shapes": shapes, "step": step}
