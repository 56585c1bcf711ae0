"""Exact surface moments (uniform density over the surface, so neither mesh resolution nor
interior vertices bias them; method.md §1) and the size a scaling mode equalises."""

from __future__ import annotations

import numpy as np

from ..errors import MeshError
from ..mesh import Mesh, cross_rows, face_chunks

__all__ = ["SCALE_MODES", "surface_moments", "third_central_moment", "scale_measure"]

SCALE_MODES = ("variance", "bbox", "none")


def surface_moments(mesh: Mesh) -> tuple[float, np.ndarray, np.ndarray]:
    """Exact area, mean and covariance of the uniform distribution on the surface.

    For a triangle with corners a, b, c and area A: ∫x dA = A (a+b+c)/3 and
    ∫x xᵀ dA = A/12 (a aᵀ + b bᵀ + c cᵀ + s sᵀ), s = a + b + c. Summed over the faces in
    chunks (no (F, 3, 3) array) and computed once per mesh (`Mesh.cached`).
    """
    total, mean, cov = mesh.cached("surface_moments", _surface_moments)
    return total, mean.copy(), cov.copy()


def _surface_moments(mesh: Mesh) -> tuple[float, np.ndarray, np.ndarray]:
    total, first, second = 0.0, np.zeros(3), np.zeros((3, 3))
    for a, b, c in face_chunks(mesh):
        cross = cross_rows(b - a, c - a)
        areas = 0.5 * np.sqrt(np.einsum("ij,ij->i", cross, cross))
        s = a + b + c
        total += float(areas.sum())
        first += areas @ s
        for corner in (a, b, c, s):
            second += (corner * areas[:, None]).T @ corner
    if total <= 0:
        raise MeshError(f"{mesh.name or 'mesh'}: surface area is zero")
    mean = first / (3.0 * total)
    cov = second / (12.0 * total) - np.outer(mean, mean)
    return total, mean, 0.5 * (cov + cov.T)


def third_central_moment(mesh: Mesh, axis: np.ndarray, centre: np.ndarray) -> float:
    """Exact surface mean of f³ for the linear function f(x) = axis · (x − centre).

    Over a triangle with corner values f1, f2, f3: mean f³ = (Σ f_i³ + Σ_{i≠j} f_i² f_j
    + f1 f2 f3) / 10.
    """
    weighted, total = 0.0, 0.0
    for a, b, c in face_chunks(mesh):
        f1, f2, f3 = (a - centre) @ axis, (b - centre) @ axis, (c - centre) @ axis
        cubic = (
            f1**3 + f2**3 + f3**3
            + f1**2 * (f2 + f3) + f2**2 * (f1 + f3) + f3**2 * (f1 + f2)
            + f1 * f2 * f3
        ) / 10.0
        cross = cross_rows(b - a, c - a)
        areas = 0.5 * np.sqrt(np.einsum("ij,ij->i", cross, cross))
        weighted += float(areas @ cubic)
        total += float(areas.sum())
    return weighted / total


def scale_measure(mesh: Mesh, mode: str) -> float:
    """The size a scaling mode equalises: total surface variance, or bounding-box volume."""
    if mode == "variance":
        _, _, cov = surface_moments(mesh)
        return float(np.trace(cov))
    if mode == "bbox":
        lo, hi = mesh.bounds()
        return float(np.prod(hi - lo))
    raise ValueError(f"unknown scale mode {mode!r}; choose from {SCALE_MODES}")
