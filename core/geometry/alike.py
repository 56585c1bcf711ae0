"""Nearest points that face alike: for each query point the nearest of a point set whose
normal is within an angle of the query's own (the two faces of a thin wall lie close
together and face apart). Used by non-rigid ICP's backward matches (thesis 4.11 with
normal compatibility) and to carry per-point values between point sets of one surface.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["nearest_facing_alike"]


def nearest_facing_alike(points: np.ndarray, normals: np.ndarray, queries: np.ndarray, query_normals: np.ndarray,
                         min_cos: float, neighbours: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """For every query, the nearest of `points` among its `neighbours` nearest whose unit
    normal has a cosine of at least `min_cos` with the query's unit normal: (index,
    distance), distance inf where none of them has (index then that of the nearest)."""
    k = min(neighbours, len(points))
    distance, nearest = cKDTree(points).query(queries, k=k)
    distance, nearest = distance.reshape(-1, k), nearest.reshape(-1, k)
    ok = np.einsum("jkd,jd->jk", normals[nearest], query_normals) >= min_cos
    first = np.argmax(ok, axis=1)
    rows = np.arange(len(nearest))
    return nearest[rows, first], np.where(ok[rows, first], distance[rows, first], np.inf)
