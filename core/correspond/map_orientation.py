"""Which way round an intrinsic map goes: its orientation and, in a shared frame, its facing
(**beyond** the thesis; the intrinsic start, functional_map.py).

A body is nearly symmetric twice over: left–right (almost exactly) and, at the low
frequencies the coarse maps are decided on, front–back. So besides the right map π, three
near-isometries match the spectra and the wave kernel signatures about as well: its
left–right mirror, its front–back flip and both at once (a half turn about the body's
long axis). Signatures cannot choose among them; two further tests can.

**Orientation** (Ren et al. 2018, "Continuous and orientation-preserving correspondences
via functional maps", BCICP, their orientation term). For a function f on an oriented
surface the operator O_f h = ⟨n, ∇f × ∇h⟩ measures how h turns about f: it changes sign
when the surface's orientation is reversed. A map that keeps the orientation carries the
template's operator to the shape's: for descriptors that correspond (f_T = f_S ∘ π),
O_{f_T} C = C O_{f_S} in the reduced bases (C: shape coefficients → template coefficients
of the pulled-back function); a mirror or a front–back flip gives O_{f_T} C = −C O_{f_S}.
`orientation_score` is the cosine between the two sides, summed over a few smoothed wave
kernel signature channels: near +1 for a map that keeps the orientation, near −1 for its
mirror, near 0 for a map that is right on some parts and mirrored on others. It is an
integral over the whole surface, so it does not depend on the point map being right at
every vertex (the share of triangles whose images face outwards does: at 16
eigenfunctions a right map between two different people kept only 0.6 of them, on a par
with maps that fold).

**Facing.** A half turn keeps the orientation, so the test above cannot reject it. In a
frame the collection shares (Prepare aligns the shapes: one up axis and, by consensus, one
facing), the right map carries the template's points to points of the shape that lie the
same way round; a half turn carries them to the far side. `facing_agreement` is the cosine
of the angle of the best rotation (orthogonal Procrustes, mass-weighted) from the
template's points onto their images: near +1 when they face the same way whatever the
pose of the limbs, near −1 for the half turn.
"""

from __future__ import annotations

import numpy as np

__all__ = ["face_gradients", "orientation_operators", "orientation_score", "facing_agreement",
           "DESCRIPTOR_CHANNELS", "DESCRIPTOR_FUNCTIONS"]

#: the wave kernel signature channels (indices into the signature's log-energies, from the
#: lowest) whose smoothed versions serve as the descriptors f of the orientation operators,
#: smoothed by projection onto the first DESCRIPTOR_FUNCTIONS eigenfunctions
DESCRIPTOR_CHANNELS = (0, 5, 10, 15, 20)
DESCRIPTOR_FUNCTIONS = 16


def face_gradients(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(G, n, a) of a triangle mesh: G (F, 3, 3) the gradient of each corner's hat
    function on each face (the gradient of a piecewise-linear h on face f is
    Σ_c h[faces[f, c]] G[f, c]), n (F, 3) unit face normals (the order of the corners:
    outward on a consistently oriented closed mesh), a (F,) face areas. The hat function
    of corner c rises across the opposite edge e_c: ∇ = n × e_c / 2a."""
    corners = np.asarray(vertices, dtype=np.float64)[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    safe = np.where(double_area > 0, double_area, 1.0)
    normals = cross / safe[:, None]
    opposite = np.stack([corners[:, (c + 2) % 3] - corners[:, (c + 1) % 3] for c in range(3)], axis=1)
    gradients = np.cross(normals[:, None, :], opposite) / safe[:, None, None]
    gradients[double_area == 0] = 0.0
    return gradients, normals, double_area / 2


def orientation_operators(vertices: np.ndarray, faces: np.ndarray, basis: np.ndarray,
                          descriptors: np.ndarray) -> np.ndarray:
    """(d, k, k) the operators O_f h = ⟨n, ∇f × ∇h⟩ of the d `descriptors` (n, d) in the
    reduced `basis` (n, k: the first k eigenfunctions, mass-orthonormal):
    O[i, j] = ∫ φ_i ⟨n, ∇f × ∇φ_j⟩ dA, piecewise linear functions, per-face gradients,
    φ_i at a face its corners' mean. Scale-free: gradients scale as 1/length, areas as
    length²."""
    gradients, normals, areas = face_gradients(vertices, faces)
    on_faces = basis[faces]  # (F, 3, k)
    basis_gradients = np.einsum("fcd,fck->fkd", gradients, on_faces)  # (F, k, 3)
    weighted_means = areas[:, None] * on_faces.mean(axis=1)  # (F, k)
    operators = []
    for f in np.asarray(descriptors, dtype=np.float64).T:
        turned = np.cross(normals, np.einsum("fcd,fc->fd", gradients, f[faces]))  # n × ∇f
        # ⟨n, ∇f × ∇φ_j⟩ = ⟨∇φ_j, n × ∇f⟩
        operators.append(weighted_means.T @ np.einsum("fkd,fd->fk", basis_gradients, turned))
    return np.array(operators)


def orientation_score(template_operators: np.ndarray, shape_operators: np.ndarray, c: np.ndarray) -> float:
    """Cosine between O_T C and C O_S summed over the descriptors (module docstring):
    +1 for a map C (k × k, shape → template coefficients) that keeps the orientation, −1
    for one that reverses it; NaN when the operators vanish. Uses the first k rows and
    columns of the operators, k = len(c)."""
    k = len(c)
    left = template_operators[:, :k, :k] @ c
    right = c @ shape_operators[:, :k, :k]
    norm = np.sqrt((left**2).sum() * (right**2).sum())
    return float((left * right).sum() / norm) if norm > 0 else float("nan")


def facing_agreement(template_points: np.ndarray, image_points: np.ndarray, weights: np.ndarray) -> float:
    """cos θ of the rotation θ that best turns the template's points (centred, weighted by
    `weights`) onto their images under a map (orthogonal Procrustes, Kabsch: R = U diag(1,
    1, det) Vᵀ of the weighted cross-covariance, cos θ = (tr R − 1) / 2). +1: the map keeps
    the facing of a shared frame; −1: it turns the shape half round."""
    weights = np.asarray(weights, dtype=np.float64)
    share = weights / weights.sum()
    a = template_points - share @ template_points
    b = image_points - share @ image_points
    u, _, vt = np.linalg.svd((a * share[:, None]).T @ b)
    turn = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0]) @ vt
    return float((np.trace(turn) - 1.0) / 2.0)
