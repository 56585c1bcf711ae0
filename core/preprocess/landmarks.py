"""Radius-based landmark selection on a dense surface sample (thesis §4.2.1, Alg. 2).

Alg. 2: take a random point as a landmark, discard every point within radius r of it,
repeat until no point is left. The result is roughly uniform over the surface and no two
landmarks are closer than r.

**beyond** (docs/method.md §2): points come from a dense area-weighted surface sample, not the
mesh vertices (a coarse mesh has too few); r is found by bisection so the count is within
a tolerance of the request; everything is seeded and deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..base.errors import MeshError
from ..meshes.mesh import Mesh

__all__ = ["Landmarks", "select_landmarks", "radius_select", "DEFAULT_LANDMARKS", "MIN_LANDMARKS"]

DEFAULT_LANDMARKS = 800
MIN_LANDMARKS = 4
#: Dense samples per requested landmark (at least MIN_DENSE_SAMPLES in all).
DENSE_SAMPLES_PER_LANDMARK = 25
MIN_DENSE_SAMPLES = 20_000
#: Accept a radius whose landmark count is within this relative tolerance of the request.
COUNT_TOLERANCE = 0.02
MAX_BISECTION_STEPS = 60


@dataclass(frozen=True)
class Landmarks:
    """Landmarks on one mesh: positions plus the face and barycentrics each lies at."""

    points: np.ndarray  # (L, 3)
    face_index: np.ndarray  # (L,)
    barycentric: np.ndarray  # (L, 3)
    radius: float  # the exclusion radius used: no two landmarks are closer than this

    def __len__(self) -> int:
        return int(self.points.shape[0])


def radius_select(points: np.ndarray, radius: float, order: np.ndarray, tree: cKDTree | None = None) -> np.ndarray:
    """Alg. 2 for a fixed radius: visit points in `order`, keep a point unless an earlier
    kept point lies within `radius`, then discard its neighbours. Returns kept indices."""
    tree = cKDTree(points) if tree is None else tree
    removed = np.zeros(len(points), dtype=bool)
    kept = []
    for index in order:
        if removed[index]:
            continue
        kept.append(index)
        removed[tree.query_ball_point(points[index], radius)] = True
    return np.asarray(kept, dtype=np.int64)


def select_landmarks(
    mesh: Mesh,
    n_landmarks: int = DEFAULT_LANDMARKS,
    seed: int = 0,
    n_dense: int | None = None,
    tolerance: float = COUNT_TOLERANCE,
) -> Landmarks:
    """About `n_landmarks` uniformly spread surface landmarks (count within `tolerance`).

    The radius is bisected between 0 and the bounding-box diagonal: the count of Alg. 2
    decreases (almost monotonically) with r. If no radius hits the tolerance exactly the
    closest count found is returned.
    """
    label = mesh.name or "mesh"
    if n_landmarks < MIN_LANDMARKS:
        raise ValueError(f"{label}: need at least {MIN_LANDMARKS} landmarks, asked for {n_landmarks}")
    rng = np.random.default_rng(seed)
    if n_dense is None:
        n_dense = max(MIN_DENSE_SAMPLES, DENSE_SAMPLES_PER_LANDMARK * n_landmarks)
    if n_dense < 2 * n_landmarks:
        raise ValueError(f"{label}: dense sample ({n_dense}) must be at least twice the landmark count")
    samples = mesh.sample_surface(n_dense, rng)
    order = rng.permutation(n_dense)
    tree = cKDTree(samples.points)

    # initial guess: disks of radius r/2 tiling the area, A ≈ L π (r/2)^2 · packing factor
    area = mesh.area()
    if area <= 0:
        raise MeshError(f"{label}: zero surface area, cannot place landmarks")
    guess = 2.0 * np.sqrt(area / (np.pi * n_landmarks * 0.9))
    low, high = 0.0, mesh.bbox_diagonal()
    radius = min(guess, high)
    best = None
    for _ in range(MAX_BISECTION_STEPS):
        kept = radius_select(samples.points, radius, order, tree)
        error = abs(len(kept) - n_landmarks)
        if best is None or error < best[0]:
            best = (error, radius, kept)
        if error <= tolerance * n_landmarks:
            break
        if len(kept) > n_landmarks:
            low = radius
        else:
            high = radius
        radius = 0.5 * (low + high)
    _, radius, kept = best
    return Landmarks(
        samples.points[kept].copy(),
        samples.face_index[kept].copy(),
        samples.barycentric[kept].copy(),
        float(radius),
    )
