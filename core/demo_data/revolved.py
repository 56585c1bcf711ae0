"""Closed surfaces of revolution without a ground truth of their own: barrels
(`make_barrels`), cups (`make_cups`) and mugs with a handle (`make_mugs`), the fixtures of
orientation tests and benchmarks (see the package's docstring)."""

from __future__ import annotations

import numpy as np

from ..meshes.mesh import Mesh
from ..preprocess import ShapeTransform
from .vases import random_placement


def capped_ring_faces(count: int, n_around: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """Faces of `count` rings of `n_around` vertices (vertex 1 + k·n_around + i), a pole
    vertex 0 below the first and one after the last closing the ends. Each quad between
    two rings is cut along its rising diagonal, or (with `rng`) along either at random."""
    ring = lambda k: 1 + k * n_around + np.arange(n_around)  # noqa: E731
    j = np.arange(n_around)
    first, last, top = ring(0), ring(count - 1), count * n_around + 1
    faces = [np.stack([np.zeros(n_around, int), first[(j + 1) % n_around], first[j]], axis=1)]
    for k in range(count - 1):
        a, b = ring(k), ring(k + 1)
        a0, a1, b0, b1 = a[j], a[(j + 1) % n_around], b[j], b[(j + 1) % n_around]
        flip = np.ones(n_around, bool) if rng is None else rng.random(n_around) < 0.5
        faces.append(np.where(flip[:, None], np.stack([a0, a1, b1], 1), np.stack([a0, a1, b0], 1)))
        faces.append(np.where(flip[:, None], np.stack([a0, b1, b0], 1), np.stack([a1, b1, b0], 1)))
    faces.append(np.stack([np.full(n_around, top), last[j], last[(j + 1) % n_around]], axis=1))
    return np.concatenate(faces)


def _revolved_mesh(profile: np.ndarray, radius_scale, rng: np.random.Generator,
                   n_around: int) -> tuple[np.ndarray, np.ndarray]:
    """Closed surface of revolution about z: profile (rings, 2) rows (r, z) from the bottom
    pole to the top pole (r = 0 at both ends), outward faces; radius_scale(theta, z)
    multiplies the radius; each ring gets its own angular offset."""
    rings = profile[1:-1]
    offsets = rng.uniform(0, 2 * np.pi / n_around, len(rings))
    theta = 2 * np.pi * np.arange(n_around)[None, :] / n_around + offsets[:, None]
    z = np.broadcast_to(rings[:, 1:2], theta.shape)
    r = rings[:, 0:1] * radius_scale(np.angle(np.exp(1j * theta)), z)
    ring_points = np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=-1).reshape(-1, 3)
    vertices = np.vstack([[0.0, 0.0, profile[0, 1]], ring_points, [0.0, 0.0, profile[-1, 1]]])
    return vertices, capped_ring_faces(len(rings), n_around)


def make_barrels(n: int = 24, seed: int = 0, rings: tuple[int, int] = (14, 22), pose: bool = True) -> list[Mesh]:
    """`n` random barrels standing on +z, the tap towards +x (before the optional random
    input pose: yaw, scale, translation). The body bulges symmetrically top-to-bottom; only
    the lid's knob (about 8 % of the height) tells top from bottom."""
    rng = np.random.default_rng(seed)
    shapes = []
    for i in range(n):
        height = rng.uniform(1.0, 1.4)
        end = rng.uniform(0.3, 0.4)
        bulge = rng.uniform(0.1, 0.25)
        knob_radius, knob_height = rng.uniform(0.08, 0.12), rng.uniform(0.06, 0.1) * height
        tap, ellipticity = rng.uniform(0.2, 0.3), rng.uniform(0.0, 0.05)
        body = np.linspace(0.0, height, int(rng.integers(rings[0], rings[1] + 1)))
        profile = np.concatenate([
            [[0.0, 0.0]],
            np.stack([end * (1.0 + bulge * np.sin(np.pi * body / height)), body], axis=1),
            [[knob_radius, height], [knob_radius, height + knob_height], [0.0, height + knob_height]],
        ])

        def radius_scale(theta, z, height=height, tap=tap, ellipticity=ellipticity):
            shaped = 1.0 + tap * np.exp(-(theta / 0.3) ** 2 - ((z / height - 0.5) / 0.08) ** 2)
            return shaped * (1.0 + ellipticity * np.cos(2.0 * theta))

        vertices, faces = _revolved_mesh(profile, radius_scale, rng, int(rng.integers(28, 40)))
        placement = random_placement(rng) if pose else ShapeTransform.identity()
        shapes.append(Mesh(placement.to_normalised(vertices), faces, name=f"barrel_{i:03d}"))
    return shapes


def make_cups(n: int = 12, seed: int = 0, taper: tuple[float, float] = (-0.2, 0.25), rings: tuple[int, int] = (8, 14),
              pose: bool = True) -> list[Mesh]:
    """`n` random thick-walled cups standing on +z, without handles: the outer radius runs
    linearly from (1 − t/2) to (1 + t/2) times the mid radius from bottom to rim, t drawn from
    `taper`, so with the default some walls lean in and some out (as bench/blender_mugs.py's
    mugs, whose walls defeat feature matches; core/correspond/features.py `worse_fits`).
    Before the optional random input pose (yaw, scale, translation)."""
    rng = np.random.default_rng(seed)
    shapes = []
    for i in range(n):
        radius, height = rng.uniform(0.8, 1.2), rng.uniform(1.4, 2.4)
        lean, wall, floor = rng.uniform(*taper), rng.uniform(0.10, 0.14), rng.uniform(0.12, 0.2)
        count = int(rng.integers(rings[0], rings[1] + 1))
        outer = lambda z: radius * (1.0 + lean * (z / height - 0.5))  # noqa: E731
        up, down = np.linspace(0.0, height, count), np.linspace(height, floor, count)
        profile = np.concatenate([[[0.0, 0.0]], np.stack([outer(up), up], axis=1),
                                  np.stack([outer(down) - wall, down], axis=1), [[0.0, floor]]])
        vertices, faces = _revolved_mesh(profile, lambda theta, z: np.ones_like(theta), rng,
                                         int(rng.integers(28, 40)))
        placement = random_placement(rng) if pose else ShapeTransform.identity()
        shapes.append(Mesh(placement.to_normalised(vertices), faces, name=f"cup_{i:03d}"))
    return shapes


def make_mugs(n: int = 10, seed: int = 0, closed: bool = True, taper: tuple[float, float] = (-0.25, 0.25),
              handle_height: tuple[float, float] = (0.45, 0.6), pose: bool = True) -> list[Mesh]:
    """`n` random mugs standing on +z, the handle towards +x: a body of revolution whose wall
    tapers by t drawn from `taper` (inward on some, outward on others), closed by flat caps
    at both ends (`closed`) or open at the top (inner wall and floor), and a handle as a
    second part: a torus arc centred at a height drawn from `handle_height` (fraction of the
    body's height), reaching into the wall. Before the optional random input pose."""
    rng = np.random.default_rng(seed)
    shapes = []
    for i in range(n):
        radius, height = rng.uniform(0.8, 1.2), rng.uniform(1.4, 2.4)
        lean, wall, floor = rng.uniform(*taper), rng.uniform(0.10, 0.14), rng.uniform(0.12, 0.2)
        outer = lambda z: radius * (1.0 + lean * (z / height - 0.5))  # noqa: E731
        up = np.linspace(0.0, height, 8)
        if closed:
            profile = np.concatenate([[[0.0, 0.0]], np.stack([outer(up), up], axis=1), [[0.0, height]]])
        else:
            down = np.linspace(height, floor, 8)
            profile = np.concatenate([[[0.0, 0.0]], np.stack([outer(up), up], axis=1),
                                      np.stack([outer(down) - wall, down], axis=1), [[0.0, floor]]])
        body, body_faces = _revolved_mesh(profile, lambda theta, z: np.ones_like(theta), rng,
                                          int(rng.integers(28, 40)))
        handle, handle_faces = _handle(rng, outer, height * rng.uniform(*handle_height), height)
        vertices = np.vstack([body, handle])
        faces = np.vstack([body_faces, handle_faces + len(body)])
        placement = random_placement(rng) if pose else ShapeTransform.identity()
        shapes.append(Mesh(placement.to_normalised(vertices), faces, name=f"mug_{i:03d}"))
    return shapes


def _handle(rng: np.random.Generator, outer, centre: float, height: float,
            around: int = 8, steps: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube swept along a half circle in the xz plane at +x, its ends in the wall
    (radius `outer(z)`) at `centre` ± its reach: the handle of `make_mugs`."""
    tube, reach = rng.uniform(0.05, 0.07), rng.uniform(0.22, 0.3) * height
    phis = 2 * np.pi * np.arange(around) / around
    rings = []
    for theta in np.linspace(-0.5 * np.pi, 0.5 * np.pi, steps + 1):
        z = centre + reach * np.sin(theta)
        point = np.array([outer(z) - 0.05 + 0.9 * reach * np.cos(theta), 0.0, z])
        normal = np.array([np.cos(theta), 0.0, np.sin(theta)])
        rings.append(point + tube * (np.cos(phis)[:, None] * normal + np.sin(phis)[:, None] * [0.0, 1.0, 0.0]))
    vertices = np.vstack(rings + [rings[0].mean(axis=0), rings[-1].mean(axis=0)])
    j = np.arange(around)
    faces = []
    for k in range(steps):
        a, b = k * around + j, (k + 1) * around + (j)
        a1, b1 = k * around + (j + 1) % around, (k + 1) * around + (j + 1) % around
        faces += [np.stack([a, b, b1], axis=1), np.stack([a, b1, a1], axis=1)]
    first, last = len(vertices) - 2, len(vertices) - 1
    faces.append(np.stack([np.full(around, first), j, (j + 1) % around], axis=1))
    faces.append(np.stack([np.full(around, last), steps * around + (j + 1) % around, steps * around + j], axis=1))
    return vertices, np.concatenate(faces)[:, ::-1]  # outward
