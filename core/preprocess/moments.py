"""Exact surface moments (uniform density over the surface, so neither mesh resolution nor
interior vertices bias them; docs/method.md §1) and the size a scaling mode equalises."""

from __future__ import annotations

import numpy as np

from ..base.errors import MeshError
from ..meshes.mesh import FACE_CHUNK, Mesh

__all__ = ["SCALE_MODES", "surface_moments", "third_central_moment", "scale_measure"]

SCALE_MODES = ("variance", "bbox", "none")


def surface_moments(mesh: Mesh) -> tuple[float, np.ndarray, np.ndarray]:
    """Exact area, mean and covariance of the uniform distribution on the surface.

    For a triangle with corners a, b, c and area A: ∫x dA = A (a+b+c)/3 and
    ∫x xᵀ dA = A/12 (a aᵀ + b bᵀ + c cᵀ + s sᵀ), s = a + b + c. Summed over chunks of
    faces (no (F, 3, 3) array of a dense mesh) and computed once per mesh (`Mesh.cached`).
    """
    total, mean, cov = mesh.cached("surface_moments", _surface_moments)
    return total, mean.copy(), cov.copy()


def _surface_moments(mesh: Mesh) -> tuple[float, np.ndarray, np.ndarray]:
    areas = mesh.face_areas()
    total = float(areas.sum())
    if total <= 0:
        raise MeshError(f"{mesh.name or 'mesh'}: surface area is zero")
    first, second = np.zeros(3), np.zeros((3, 3))
    for start, tri in _triangle_chunks(mesh):
        area = areas[start:start + len(tri)]
        s = tri.sum(axis=1)
        if mesh.n_faces <= FACE_CHUNK:  # main's exact operations (every result downstream depends on its last bits)
            first += (area[:, None] * s).sum(axis=0)
            second += np.einsum("f,fki,fkj->ij", area, tri, tri) + np.einsum("f,fi,fj->ij", area, s, s)
            continue
        first += area @ s  # a dense mesh: matrix products, several times faster than the 3-operand einsum
        for corner in (tri[:, 0], tri[:, 1], tri[:, 2], s):
            second += (corner * area[:, None]).T @ corner
    mean = first / (3.0 * total)
    second /= 12.0 * total
    cov = second - np.outer(mean, mean)
    return total, mean, 0.5 * (cov + cov.T)


def third_central_moment(mesh: Mesh, axis: np.ndarray, centre: np.ndarray) -> float:
    """Exact surface mean of f³ for the linear function f(x) = axis · (x − centre).

    Over a triangle with corner values f1, f2, f3: mean f³ = (Σ f_i³ + Σ_{i≠j} f_i² f_j
    + f1 f2 f3) / 10.
    """
    areas = mesh.face_areas()
    weighted = 0.0
    for start, tri in _triangle_chunks(mesh):
        f = (tri - centre) @ axis  # (n, 3)
        f1, f2, f3 = f[:, 0], f[:, 1], f[:, 2]
        cubic = (
            f1**3 + f2**3 + f3**3
            + f1**2 * (f2 + f3) + f2**2 * (f1 + f3) + f3**2 * (f1 + f2)
            + f1 * f2 * f3
        ) / 10.0
        weighted += float((areas[start:start + len(tri)] * cubic).sum())
    return weighted / float(areas.sum())


def _triangle_chunks(mesh: Mesh):
    """(first face index, (n, 3, 3) corner coordinates) of the mesh's faces, FACE_CHUNK
    faces at a time (one chunk, the whole mesh, below that: the sums are then the
    exact same floating-point operations as over the whole array)."""
    for start in range(0, mesh.n_faces, FACE_CHUNK):
        yield start, mesh.vertices[mesh.faces[start:start + FACE_CHUNK]]


def scale_measure(mesh: Mesh, mode: str) -> float:
    """The size a scaling mode equalises: total surface variance, or bounding-box volume."""
    if mode == "variance":
        _, _, cov = surface_moments(mesh)
        return float(np.trace(cov))
    if mode == "bbox":
        lo, hi = mesh.bounds()
        return float(np.prod(hi - lo))
    raise ValueError(f"unknown scale mode {mode!r}; choose from {SCALE_MODES}")
