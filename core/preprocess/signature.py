"""Odd-moment signatures of a posed shape: what a Chamfer cost cannot see (a spout, a
knob, a head: a small part that tells front from back or top from bottom), measured
exactly (surface integrals by quadrature, no sampling noise).

With the shape centred at its surface centroid, unit total variance, turned by R, and ẑ
its height mapped to [−1, 1]:

* facing: a_b = ∫ (x + i y) P_b(ẑ) dA / A, b < `order` (Legendre P_b): the horizontal
  dipole of each height band. A turn by θ about z multiplies it by e^{iθ}; a shape
  symmetric under turns about z has a = 0.
* up: u = (∫ z³ dA, ∫ z (x² + y²) dA) / A; a half turn about a horizontal axis negates it.

`facing_turn` and `upside_down` compare one shape's signature with reference shapes':
the correlation c = Σ_i ⟨a_j, a_i⟩ (complex) gives the turn −arg c that aligns j with
them, and its coherence |c| / Σ_i ‖a_j‖ ‖a_i‖ in [0, 1] how much the shapes share that
feature (near 0: no facing to agree on).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..meshes.mesh import Mesh
from ..base.progress import Progress, no_progress
from .moments import surface_moments

__all__ = ["Signatures", "FACING_FLOOR"]

#: a facing signature shorter than this (‖a‖, unit total variance) is no facing: a surface
#: of revolution leaves only its triangulation's noise (below 1e-5; the weakest facing
#: measured, PSB cups and vases with no handle or spout, 2e-4; procedural vases above 1e-3)
FACING_FLOOR = 1e-4


def _triangle_quadrature() -> tuple[np.ndarray, np.ndarray]:
    """Collapsed 4×4 Gauss rule on the unit triangle: (xi, eta) points and weights summing
    to 1 (fraction of the triangle's area); exact for polynomials up to degree 6."""
    g, w = np.polynomial.legendre.leggauss(4)
    g, w = (g + 1.0) / 2.0, w / 2.0
    u, v = np.meshgrid(g, g, indexing="ij")
    weights = 2.0 * (np.outer(w, w) * (1.0 - u)).ravel()
    return np.stack([u.ravel(), (v * (1.0 - u)).ravel()], axis=1), weights


_QUAD_POINTS, _QUAD_WEIGHTS = _triangle_quadrature()


class Signatures:
    """Every shape's exact third moments in its base pose (centred, unit total variance);
    its quadrature points and weights, and the vertices that bound its height, are made
    again from its mesh when a facing is asked for (kept, they took 23 MB per 20k-vertex
    shape: 23 GB for a collection of 1000)."""

    def __init__(self, meshes: Sequence[Mesh], base: Sequence[np.ndarray], order: int,
                 progress: Progress | None = None):
        self.order = order
        self.meshes, self.frames, self.third, self.radial = list(meshes), [], [], []
        report = progress or no_progress
        for count, (mesh, rotation) in enumerate(zip(meshes, base), 1):
            area, mean, cov = surface_moments(mesh)
            self.frames.append((area, mean, rotation, np.sqrt(np.trace(cov))))
            points, weights, _ = self.quadrature(len(self.frames) - 1)
            weighted = points * weights[:, None]
            self.third.append(np.einsum("na,nb,nc->abc", weighted, points, points))
            self.radial.append(weighted.T @ np.einsum("na,na->n", points, points))
            report(count / len(self.meshes), f"signatures of shape {count} of {len(self.meshes)}")
        self._facing: dict[tuple[int, bytes], np.ndarray] = {}

    def quadrature(self, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points, weights, corner vertices) of shape j in its base pose."""
        mesh, (area, mean, rotation, size) = self.meshes[j], self.frames[j]
        tri = (mesh.triangles - mean) @ rotation.T / size
        pts = (tri[:, None, 0]
               + _QUAD_POINTS[None, :, :1] * (tri[:, None, 1] - tri[:, None, 0])
               + _QUAD_POINTS[None, :, 1:] * (tri[:, None, 2] - tri[:, None, 0]))
        weights = (mesh.face_areas()[:, None] * _QUAD_WEIGHTS[None, :]).ravel() / area
        return pts.reshape(-1, 3), weights, tri.reshape(-1, 3)

    def facing(self, j: int, rotation: np.ndarray) -> np.ndarray:
        """a_b of shape j turned by `rotation` (module docstring), complex (order,);
        remembered by (j, rotation): the same shape in the same pose recurs as a reference."""
        key = (j, rotation.tobytes())
        if key not in self._facing:
            self._facing[key] = self._facing_of(j, rotation)
        return self._facing[key]

    def _facing_of(self, j: int, rotation: np.ndarray) -> np.ndarray:
        points, weights, vertices = self.quadrature(j)
        pts = points @ rotation.T
        heights = vertices @ rotation[2]
        lo, hi = heights.min(), heights.max()
        z = 2.0 * (pts[:, 2] - lo) / max(hi - lo, 1e-12) - 1.0
        basis = np.polynomial.legendre.legvander(z, self.order - 1)
        return (weights * (pts[:, 0] + 1j * pts[:, 1])) @ basis

    def up(self, j: int, rotation: np.ndarray) -> np.ndarray:
        """u of shape j turned by `rotation` (module docstring), (2,): with r the direction
        turned to z and the exact moments T = ∫ p⊗p⊗p dA / A, v = ∫ p |p|² dA / A of the
        base pose, ∫ z³ = T(r, r, r) and ∫ z (x² + y²) = r·v − T(r, r, r)."""
        r = rotation[2]
        cubic = float(np.einsum("abc,a,b,c->", self.third[j], r, r, r))
        return np.array([cubic, float(r @ self.radial[j]) - cubic])

    def facing_turn(self, j: int, rotation: np.ndarray,
                    references: Sequence[tuple[int, np.ndarray]]) -> tuple[float, float]:
        """(degrees, coherence): the turn about z that aligns shape j's facing with the
        references', and how strongly they share a facing (module docstring); a facing
        shorter than FACING_FLOOR counts as none (coherence 0, or the reference left out)."""
        a = self.facing(j, rotation)
        others = [b for b in (self.facing(i, r) for i, r in references) if np.linalg.norm(b) >= FACING_FLOOR]
        if np.linalg.norm(a) < FACING_FLOOR or not others:
            return 0.0, 0.0
        c = sum(np.vdot(b, a) for b in others)
        scale = sum(np.linalg.norm(a) * np.linalg.norm(b) for b in others)
        return float(-np.degrees(np.angle(c))), float(abs(c) / max(scale, 1e-300))

    def up_agreement(self, j: int, rotation: np.ndarray, references: Sequence[tuple[int, np.ndarray]]) -> float:
        """Correlation in [−1, 1] of shape j's up signature with the references': near −1
        it is upside down relative to them."""
        u = self.up(j, rotation)
        others = [self.up(i, r) for i, r in references]
        scale = sum(np.linalg.norm(u) * np.linalg.norm(b) for b in others)
        return float(sum(u @ b for b in others) / max(scale, 1e-300))
