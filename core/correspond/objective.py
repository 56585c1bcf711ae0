"""The population objective of groupwise refinement (refine.py): compactness of the
landmark population plus a spread term per shape, with analytic gradients. Beyond the
thesis: minimum description length (Davies et al. 2002) and the entropy-based particle
systems of Cates et al. 2007 (ShapeWorks) let the population decide where landmarks sit.

E(X) = w_c · C(X) + w_s · (1/N) Σ_m S_m(X_m)

* Compactness (the ensemble entropy of Cates et al. 2007, in its dual form):
  C = ½ log det(I + K/δ), K = Y Yᵀ / (N − 1) the N × N Gram matrix of the centred
  landmark vectors Y (N × 3L).
  K's nonzero eigenvalues are those of the 3L × 3L covariance Σ = YᵀY / (N − 1), so C is
  ½ log det(Σ + δ I) − ½ 3L log δ: the Gaussian entropy of the population, computed at
  N × N cost. ∂C/∂Y = (K + δ I)⁻¹ Y / (N − 1) (already centred: 1 is an eigenvector of
  K with eigenvalue 0). The regulariser δ is the variance below which a mode of variation
  stops counting logarithmically: a mode with eigenvalue λ ≫ δ costs ½ log λ (the
  description-length view: narrow modes are cheap), one with λ ≪ δ costs λ / 2δ (plain
  sum of squares, so noise is pulled in like Procrustes variance, not collapsed without
  bound). δ = L ρ², ρ = `regulariser` × the population's RMS landmark radius: the
  eigenvalue of a mode that moves every landmark by ρ.
* Spread (after the particle entropy of Cates et al. 2007): a Parzen estimate of the
  density of every landmark among its neighbours on the same shape, D_i = ε + Σ_{j≠i}
  k(|x_i − x_j|), and S_m = (1/L) Σ_i ½ max(0, log D_i − log D_i⁰)²: a landmark may not
  get more crowded than it was at the start D⁰ (NICP's sampling: the template's
  near-uniform Poisson-disk landmarks carried onto the shape). Maximising each shape's
  entropy outright (ShapeWorks) would first re-sample every shape uniformly on its own,
  throwing away what NICP matched; anchored to the start, the term is 0 with zero
  gradient there (a collection of identical shapes is left as it is) and grows as soon
  as compactness pulls landmarks together. k is a Gaussian of width σ_m truncated at 3σ_m
  and shifted to reach 0 there (no jump), counted only between landmarks whose surface
  normals agree (n_i · n_j > 0, so the two faces of a thin wall do not interact);
  σ_m = `sigma` × the mean spacing √(area_m / L) of L uniform points on shape m.

Shapes are compared after removing each one's similarity (`alignment` "similarity"): a
scale and rotation per shape from generalised Procrustes of the landmarks onto their mean
(held fixed between re-estimations, so the gradient stays exact; refine.py estimates
them again every few steps when that lowers E) and the centroid, removed at every
evaluation (a linear map: ∂/∂x = its transpose applied to ∂/∂z). With `normal_weight`
the compactness also sees every landmark's smooth surface normal (`CompactnessTerm`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial import cKDTree

__all__ = ["ObjectiveValue", "LandmarkState", "PopulationObjective", "CompactnessTerm", "SpreadTerm", "combined",
           "compactness", "spread", "spread_sigma", "regulariser_variance",
           "similarity_to_mean", "density", "PairCache", "CUTOFF", "DENSITY_FLOOR"]

#: the spread kernel reaches 0 at this many σ
CUTOFF = 3.0
#: ε of D_i (the kernel is 1 − e^(−4.5) at distance 0): a landmark without neighbours
#: is as crowded as one with a neighbour 2.5 σ away
DENSITY_FLOOR = 0.05


@dataclass(frozen=True)
class ObjectiveValue:
    """E = w_c C + w_s S̄ and its parts (S̄: the mean spread over the shapes)."""

    total: float
    compactness: float
    spread: float

    def as_row(self) -> list[float]:
        return [self.total, self.compactness, self.spread]


def regulariser_variance(points: np.ndarray, regulariser: float) -> float:
    """δ = L ρ², ρ = regulariser × RMS distance of the landmarks from their shape's centroid
    (over the population): the eigenvalue of a mode moving every landmark by ρ."""
    points = np.asarray(points, dtype=np.float64)
    centred = points - points.mean(axis=1, keepdims=True)
    radius = np.sqrt(np.mean(np.sum(centred**2, axis=2)))
    return float(points.shape[1] * (regulariser * radius) ** 2)


def compactness(points: np.ndarray, delta: float) -> tuple[float, np.ndarray]:
    """C = ½ log det(I + K/δ) and ∂C/∂X (N, L, 3) of the population `points` (N, L, 3)."""
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    y = points.reshape(n, -1)
    y = y - y.mean(axis=0)
    gram = y @ y.T / max(n - 1, 1)
    factor = cho_factor(gram + delta * np.eye(n))
    value = float(np.sum(np.log(np.diag(factor[0]))) - 0.5 * n * np.log(delta))
    gradient = cho_solve(factor, y) / max(n - 1, 1)
    return value, gradient.reshape(points.shape)


def spread_sigma(area: float, n_landmarks: int, sigma: float) -> float:
    """σ_m = sigma × √(area / L), the kernel width of shape m's spread term."""
    return float(sigma * np.sqrt(area / max(n_landmarks, 1)))


def density(points: np.ndarray, normals: np.ndarray, sigma: float, candidates: np.ndarray | None = None
            ) -> "_Density":
    """The Parzen density D_i of every landmark of one shape (see the module docstring).
    candidates: pairs (i < j) that include every pair closer than 3σ (a `PairCache`'s);
    None: found afresh."""
    points = np.asarray(points, dtype=np.float64)
    if candidates is None:
        candidates = cKDTree(points).query_pairs(CUTOFF * sigma, output_type="ndarray").reshape(-1, 2)
    offset = points[candidates[:, 1]] - points[candidates[:, 0]]
    squared = np.einsum("nd,nd->n", offset, offset)
    keep = (squared < (CUTOFF * sigma) ** 2) & (
        np.einsum("nd,nd->n", normals[candidates[:, 0]], normals[candidates[:, 1]]) > 0)
    pairs, offset = candidates[keep], offset[keep]
    gauss = np.exp(-squared[keep] / (2 * sigma**2))
    kernel = np.maximum(gauss - np.exp(-CUTOFF**2 / 2), 0.0)
    n = len(points)
    values = DENSITY_FLOOR + np.bincount(pairs[:, 0], kernel, n) + np.bincount(pairs[:, 1], kernel, n)
    return _Density(values, pairs, offset, gauss, sigma)


@dataclass(frozen=True)
class _Density:
    values: np.ndarray  # D_i
    pairs: np.ndarray  # (P, 2) neighbours i < j within the cutoff, normals agreeing
    offset: np.ndarray  # x_j − x_i
    gauss: np.ndarray  # g(r_ij)
    sigma: float

    def gradient(self, weights: np.ndarray) -> np.ndarray:
        """∂/∂x of Σ_i weights_i log D_i: Σ_j (c_k + c_j) g_kj (x_j − x_k) / σ² for landmark k,
        c_i = weights_i / D_i (∂k_ij/∂x_i = g_ij (x_j − x_i) / σ²)."""
        c = weights / self.values
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        pull = ((c[i] + c[j]) * self.gauss / self.sigma**2)[:, None] * self.offset  # on i, towards j
        n = len(self.values)
        return np.stack([np.bincount(i, pull[:, a], n) - np.bincount(j, pull[:, a], n) for a in range(3)], axis=1)


class PairCache:
    """Neighbour pairs of one shape's moving landmarks (a Verlet list): every pair within
    3σ + `skin`, found again only once some landmark has moved by more than skin / 2 since
    (until then every pair closer than 3σ is among them)."""

    def __init__(self, sigma: float, skin: float | None = None):
        self.sigma = sigma
        self.skin = sigma if skin is None else skin
        self.anchor: np.ndarray | None = None
        self.pairs = np.zeros((0, 2), dtype=np.int64)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        if self.anchor is None or len(self.anchor) != len(points) or \
                np.max(np.sum((points - self.anchor) ** 2, axis=1)) > (self.skin / 2) ** 2:
            self.anchor = np.array(points, dtype=np.float64)
            self.pairs = cKDTree(self.anchor).query_pairs(CUTOFF * self.sigma + self.skin,
                                                          output_type="ndarray").reshape(-1, 2)
        return self.pairs


def spread(points: np.ndarray, normals: np.ndarray, sigma: float, start_log_density: np.ndarray,
           candidates: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """S = (1/L) Σ_i ½ max(0, log D_i − log D_i⁰)² and ∂S/∂x (L, 3) of one shape's landmarks
    (`candidates`: as for `density`)."""
    found = density(points, normals, sigma, candidates)
    excess = np.maximum(np.log(found.values) - start_log_density, 0.0)
    n = len(points)
    return float(0.5 * np.sum(excess**2) / n), found.gradient(excess / n)

def similarity_to_mean(points: np.ndarray, rounds: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Generalised Procrustes (Gower 1975): per shape a scale s_m and rotation R_m so that
    s_m (X_m − x̄_m) R_mᵀ match the mean of the others so aligned. Returns (scales (N,),
    rotations (N, 3, 3)); the mean keeps the population's mean size."""
    centred = np.asarray(points, dtype=np.float64) - np.mean(points, axis=1, keepdims=True)
    size = np.sqrt(np.sum(centred**2) / len(centred))
    mean = centred.mean(axis=0)
    scales, rotations = np.ones(len(centred)), np.tile(np.eye(3), (len(centred), 1, 1))
    for _ in range(rounds):
        for m, x in enumerate(centred):
            u, singular, vt = np.linalg.svd(x.T @ mean)
            flip = np.array([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
            rotations[m] = (u * flip @ vt).T
            scales[m] = float(np.sum(singular * flip) / max(np.sum(x**2), np.finfo(float).tiny))
        mean = np.mean(scales[:, None, None] * centred @ rotations.transpose(0, 2, 1), axis=0)
        mean *= size / max(np.sqrt(np.sum(mean**2)), np.finfo(float).tiny)
    return scales, rotations


@dataclass(frozen=True)
class LandmarkState:
    """Landmarks on their surfaces as the objective sees them (N shapes, L landmarks)."""

    points: np.ndarray  # (N, L, 3)
    face_normals: np.ndarray  # (N, L, 3) normal of the face each landmark lies on
    normals: np.ndarray  # (N, L, 3) smooth (interpolated vertex) normals
    normal_jacobians: np.ndarray  # (N, L, 3, 3) ∂normal/∂point along the face


class CompactnessTerm:
    """C(z(X)) with every shape's landmark vector z_m = [s_m (X_m − x̄_m) R_mᵀ, κ r n_m R_mᵀ]:
    positions with the shape's similarity removed and, with `normal_weight` κ > 0, the
    smooth surface normals at the landmarks scaled by κ × the population's RMS landmark
    radius r (ShapeWorks' "use normals": a feature such as a belly, where the wall turns
    vertical, then costs variance when it is not lined up, even where sliding along the
    wall barely moves the positions). δ and r are fixed at the `start`."""

    def __init__(self, start: LandmarkState, regulariser: float, alignment: str, normal_weight: float = 0.0):
        points = np.asarray(start.points, dtype=np.float64)
        n = len(points)
        self.alignment = alignment
        self.centre = alignment != "none"
        self.scales, self.rotations = np.ones(n), np.tile(np.eye(3), (n, 1, 1))
        if self.centre:
            self.realign(points)
        aligned = self.aligned(points)
        self.delta = regulariser_variance(aligned, regulariser)
        self.normal_scale = float(normal_weight) * float(np.sqrt(np.mean(np.sum(aligned**2, axis=2))))

    def realign(self, points: np.ndarray) -> None:
        """Every shape's scale and rotation from generalised Procrustes of `points`
        ("similarity"), or its scale alone (the RMS radius of its centred landmarks
        brought to the population's mean: "scale")."""
        if self.alignment == "similarity":
            self.scales, self.rotations = similarity_to_mean(points)
        else:
            centred = points - points.mean(axis=1, keepdims=True)
            radius = np.sqrt(np.sum(centred**2, axis=(1, 2)))
            self.scales = radius.mean() / np.maximum(radius, np.finfo(float).tiny)

    def aligned(self, points: np.ndarray) -> np.ndarray:
        """Every shape's landmarks with its similarity (or scale and centroid) removed."""
        if self.centre:
            points = points - points.mean(axis=1, keepdims=True)
        return self.scales[:, None, None] * points @ self.rotations.transpose(0, 2, 1)

    def evaluate(self, state: LandmarkState) -> tuple[float, np.ndarray]:
        """C and ∂C/∂X (N, L, 3)."""
        points = state.points
        features = self.aligned(points)
        if self.normal_scale:
            rotated = self.normal_scale * state.normals @ self.rotations.transpose(0, 2, 1)
            features = np.concatenate([features, rotated], axis=1)
        value, grad_z = compactness(features, self.delta)
        n_landmarks = points.shape[1]
        grad_x = self.scales[:, None, None] * grad_z[:, :n_landmarks] @ self.rotations
        if self.centre:
            grad_x -= grad_x.mean(axis=1, keepdims=True)
        if self.normal_scale:  # through n(x): Jᵀ ∂C/∂n
            grad_n = self.normal_scale * grad_z[:, n_landmarks:] @ self.rotations
            grad_x += np.einsum("mlij,mli->mlj", state.normal_jacobians, grad_n)
        return value, grad_x


class SpreadTerm:
    """S_m of some shapes (their landmarks at the start: `start_points`, `start_face_normals`;
    kernel widths `sigmas`), each with its own `PairCache`."""

    def __init__(self, start_points, start_face_normals, sigmas):
        self.sigmas = np.asarray(sigmas, dtype=np.float64)
        self.start_log_density = [np.log(density(x, nm, s).values)
                                  for x, nm, s in zip(start_points, start_face_normals, self.sigmas)]
        self.pair_caches = [PairCache(s) for s in self.sigmas]

    def evaluate(self, points: np.ndarray, face_normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """S_m of every shape (n,) and ∂S_m/∂X_m (n, L, 3)."""
        values, gradients = np.zeros(len(points)), np.zeros_like(points)
        for m, (x, normals) in enumerate(zip(points, face_normals)):
            values[m], gradients[m] = spread(x, normals, self.sigmas[m], self.start_log_density[m],
                                             self.pair_caches[m](x))
        return values, gradients


def combined(weights: tuple[float, float], compactness_value: float, compactness_gradient, spread_values,
             spread_gradients) -> tuple[ObjectiveValue, np.ndarray]:
    """E = w_c C + w_s (1/N) Σ_m S_m and its gradient, from the two terms' parts."""
    w_c, w_s = weights
    n = len(spread_values)
    value = ObjectiveValue(w_c * compactness_value + w_s * float(np.sum(spread_values)) / n, compactness_value,
                           float(np.sum(spread_values)) / n)
    return value, w_c * compactness_gradient + (w_s / n) * spread_gradients


class PopulationObjective:
    """E(X) = w_c C + w_s (1/N) Σ_m S_m (module docstring; `CompactnessTerm`, `SpreadTerm`
    anchored at the landmarks `start`) in one process: `evaluate` returns the value and
    ∂E/∂X (N, L, 3). refine.py evaluates the spread term per shape where the shapes live."""

    def __init__(self, start: LandmarkState, areas, compactness_weight: float, spread_weight: float,
                 regulariser: float, sigma: float, alignment: str, normal_weight: float = 0.0):
        n_landmarks = start.points.shape[1]
        self.weights = (float(compactness_weight), float(spread_weight))
        self.compactness = CompactnessTerm(start, regulariser, alignment, normal_weight)
        self.spread = SpreadTerm(start.points, start.face_normals,
                                 [spread_sigma(a, n_landmarks, sigma) for a in areas])

    def evaluate(self, state: LandmarkState) -> tuple[ObjectiveValue, np.ndarray]:
        """E and ∂E/∂X at the landmarks of `state`."""
        value_c, grad_c = self.compactness.evaluate(state) if self.weights[0] else (0.0, 0.0)
        values_s, grads_s = self.spread.evaluate(state.points, state.face_normals) if self.weights[1] else (
            np.zeros(len(state.points)), 0.0)
        return combined(self.weights, value_c, grad_c, values_s, grads_s)
