"""The completion task (thesis §5.5.3, Table 5.1): a region of each held-out shape is hidden
and the model reconstructs it from the rest.

E = Σ_{hidden coordinates c} (ŷ_c − y_c)² per test shape, reported as the mean over test
shapes. Regions (landmark sets chosen on the mean of the *training* shapes, so the same
landmarks are hidden on every test shape and nothing about the test shape leaks into the
mask): "top" third along z (up), "middle" third along z (the thesis's vase task), "rear"
third along x (lowest x; the thesis's car task).
"""

from __future__ import annotations

import numpy as np

from .metrics import EvaluationError

__all__ = ["REGIONS", "region_mask", "hidden_coordinates", "completion_errors"]

#: Regions hidden in the completion task: name -> (axis of the normalised frame, third).
REGIONS: dict[str, tuple[int, str]] = {"top": (2, "high"), "middle": (2, "middle"), "rear": (0, "low")}


def region_mask(reference_points, region: str) -> np.ndarray:
    """Hidden landmarks (bool, L) of a completion region, chosen on one reference point set
    (L, 3) — in `run_evaluation` the mean training shape — by its extent along an axis:
    "top" z > z_min + 2/3 Δz, "middle" the middle third of z, "rear" x < x_min + 1/3 Δx."""
    if region not in REGIONS:
        raise EvaluationError(f"unknown completion region {region!r} (known: {', '.join(REGIONS)})")
    P = np.asarray(reference_points, dtype=np.float64).reshape(-1, 3)
    axis, third = REGIONS[region]
    v = P[:, axis]
    lo, hi = v.min(), v.max()
    cut1, cut2 = lo + (hi - lo) / 3.0, lo + 2.0 * (hi - lo) / 3.0
    hidden = {"low": v < cut1, "middle": (v >= cut1) & (v <= cut2), "high": v > cut2}[third]
    if hidden.all() or not hidden.any():
        raise EvaluationError(f"completion region {region!r} hides {'all' if hidden.all() else 'no'} landmarks")
    return hidden


def hidden_coordinates(hidden_landmarks: np.ndarray) -> np.ndarray:
    """Landmark mask (L,) -> coordinate mask (3L,) in the row layout [x1 y1 z1 x2 ...]."""
    return np.repeat(np.asarray(hidden_landmarks, bool), 3)


def completion_errors(Y_true, Y_completed, hidden) -> np.ndarray:
    """Thesis Table 5.1: E_i = Σ_{c hidden} (ŷ_ic − y_ic)² per shape (coordinate mask (3L,))."""
    Y_true = np.asarray(Y_true, dtype=np.float64).reshape(len(Y_true), -1)
    Y_completed = np.asarray(Y_completed, dtype=np.float64).reshape(len(Y_completed), -1)
    return np.sum((Y_completed[:, hidden] - Y_true[:, hidden]) ** 2, axis=1)
