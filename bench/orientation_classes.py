"""Procedural classes of the orientation benchmark (bench/orientation_policy.py) besides the
core's (`core.demo_data`): bottles with a cap as a second part, and teddy bears made of
several parts, sitting and standing. Each shape stands on +z facing +x in its own frame
(the "as given" pose every class of the benchmark starts from).
"""

from __future__ import annotations

import numpy as np

from shapegen_core.demo_data.revolved import _revolved_mesh
from shapegen_core.meshes.mesh import Mesh

__all__ = ["make_bottles", "make_teddies"]


def make_bottles(n: int, seed: int) -> list[Mesh]:
    """Bottles: a body of revolution (base, shoulder at 50-70 % of the height, neck of
    30-45 % of the body's radius) closed at both ends, and a cap on the neck as a second
    part."""
    rng = np.random.default_rng(seed)
    shapes = []
    for i in range(n):
        radius, height = rng.uniform(0.35, 0.5), rng.uniform(1.6, 2.4)
        shoulder, neck = rng.uniform(0.5, 0.7) * height, rng.uniform(0.3, 0.45) * radius
        t = np.linspace(0.0, 1.0, 6)
        body = np.stack([np.full(6, radius), t * shoulder], axis=1)
        bend = np.stack([neck + (radius - neck) * np.cos(0.5 * np.pi * t), shoulder + t * 0.2 * height], axis=1)
        neck_ring = np.stack([np.full(3, neck), np.linspace(shoulder + 0.2 * height, height, 3)], axis=1)
        profile = np.concatenate([[[0.0, 0.0]], body, bend[1:], neck_ring[1:], [[0.0, height]]])
        vertices, faces = _revolved_mesh(profile, lambda theta, z: np.ones_like(theta), rng, int(rng.integers(24, 36)))
        cap_height = rng.uniform(0.06, 0.1) * height
        cap = np.array([[0.0, height - 0.3 * cap_height], [neck * 1.15, height - 0.3 * cap_height],
                        [neck * 1.15, height + cap_height], [0.0, height + cap_height]])
        cap_vertices, cap_faces = _revolved_mesh(cap, lambda theta, z: np.ones_like(theta), rng, 16)
        shapes.append(Mesh(np.vstack([vertices, cap_vertices]), np.vstack([faces, cap_faces + len(vertices)]),
                           name=f"bottle_{i:03d}"))
    return shapes


def _ellipsoid(centre, radii, subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions)
    return np.asarray(sphere.vertices) * radii + centre, np.asarray(sphere.faces)


def make_teddies(n: int, seed: int) -> list[Mesh]:
    """Teddy bears of separate parts (body, head, snout towards +x, two ears, two arms, two
    legs): every other one sitting (legs forward on the ground, the body low), the others
    standing (legs down)."""
    rng = np.random.default_rng(seed)
    shapes = []
    for i in range(n):
        size = rng.uniform(0.8, 1.2)
        body_r = np.array([0.45, 0.42, 0.6]) * rng.uniform(0.9, 1.1, 3) * size
        head_r = rng.uniform(0.32, 0.4) * size
        leg_r = np.array([0.16, 0.16, 0.32]) * rng.uniform(0.9, 1.1) * size
        sitting = i % 2 == 1
        if sitting:
            body_z = body_r[2] * 0.9
            legs = [((0.35 * size, s * 0.25 * size, leg_r[0]), (leg_r[2], leg_r[1], leg_r[0])) for s in (-1, 1)]
        else:
            body_z = 2 * leg_r[2] * 0.9 + body_r[2] * 0.8
            legs = [((0.0, s * 0.22 * size, leg_r[2]), leg_r) for s in (-1, 1)]
        head_z = body_z + body_r[2] * 0.85 + head_r * 0.8
        parts = [((0.0, 0.0, body_z), body_r), ((0.0, 0.0, head_z), (head_r,) * 3),
                 ((head_r * 0.85, 0.0, head_z - 0.2 * head_r), (0.16 * size,) * 3)]
        parts += [((0.0, s * head_r * 0.7, head_z + head_r * 0.75), (0.12 * size, 0.12 * size, 0.12 * size))
                  for s in (-1, 1)]
        arm = np.array([0.13, 0.13, 0.3]) * size
        parts += [((0.12 * size, s * (body_r[1] + 0.08 * size), body_z + 0.2 * body_r[2]), arm) for s in (-1, 1)]
        parts += legs
        vertices, faces, count = [], [], 0
        for centre, radii in parts:
            v, f = _ellipsoid(np.asarray(centre, float), np.asarray(radii, float))
            vertices.append(v)
            faces.append(f + count)
            count += len(v)
        shapes.append(Mesh(np.vstack(vertices), np.vstack(faces), name=f"teddy_{i:03d}"))
    return shapes
