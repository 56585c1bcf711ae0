"""Procedural shape classes with a known parametrisation (the demo's default data and the
test/benchmark fixtures with ground-truth correspondence).

Vases (`make_vases`): thick-walled jugs made by revolving a profile around z, with an
elliptical cross-section and a pouring lip. Every surface point has surface coordinates
(s, θ): s ∈ [0, 1] runs along the profile (bottom centre → base rim → outer wall up →
rim → inner wall down → inner floor centre) with the same breakpoints on every shape and
the belly and neck at fixed s along each wall (`_wall_height`); θ is the angle around the
axis measured from the lip. Equal (s, θ) on two vases is
their true correspondence, so correspondence error can be measured exactly
(docs/method.md §5 **beyond**).

Barrels (`make_barrels`): closed barrels nearly symmetric top-to-bottom (a bulging body, a
small knob on the lid, a tap at mid height giving the facing), for orientation tests and
benchmarks: their third moments along the axis are small, so a sign rule is noise there.

Cups (`make_cups`): thick-walled cups without handles whose straight walls lean in on some
and out on others, the geometry that defeats feature matches (core/correspond/features.py).

Mugs (`make_mugs`): mugs with a handle as a second part, walls tapering inward on some and
outward on others, closed at both ends (as an artist models a mug as a solid) or open at
the top; the orientation fixtures where a taper is all that tells top from bottom.

Meshes are triangulated differently on purpose: ring and segment counts, ring offsets and
quad diagonals vary per shape. Each shape is also placed in a random input pose (scale,
yaw, translation), so alignment has work to do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from .meshes.mesh import Mesh
from .preprocess import ShapeTransform

__all__ = ["VaseParameters", "ProceduralShape", "PartedShape", "make_vases", "make_barrels", "make_cups", "make_mugs",
           "make_handled_mugs", "make_quadrupeds", "vase_surface",
           "write_collection", "PROFILE_BREAKS"]

#: s-values where the profile changes part: base disk | outer wall | rim | inner wall | floor.
PROFILE_BREAKS = np.array([0.0, 0.12, 0.58, 0.64, 0.9, 1.0])


@dataclass(frozen=True)
class VaseParameters:
    """Shape parameters of one vase (units of the canonical, unposed shape)."""

    height: float
    base_radius: float
    belly_radius: float
    belly_level: float  # fraction of height
    neck_radius: float
    neck_level: float  # fraction of height
    lip_radius: float
    wall: float  # wall thickness
    ellipticity: float  # cross-section semi-axes r(1 + e), r(1 − e)
    spout: float  # lip bulge towards θ = 0
    floor_level: float = 0.08  # inner floor height, fraction of height

    def as_vector(self) -> np.ndarray:
        return np.array([self.height, self.base_radius, self.belly_radius, self.belly_level,
                         self.neck_radius, self.neck_level, self.lip_radius, self.wall,
                         self.ellipticity, self.spout, self.floor_level])

    @staticmethod
    def random(rng: np.random.Generator) -> "VaseParameters":
        belly = rng.uniform(0.28, 0.5)
        return VaseParameters(
            height=rng.uniform(0.9, 1.5),
            base_radius=rng.uniform(0.15, 0.28),
            belly_radius=belly,
            belly_level=rng.uniform(0.25, 0.5),
            neck_radius=rng.uniform(0.12, 0.6 * belly),
            neck_level=rng.uniform(0.72, 0.85),
            lip_radius=rng.uniform(0.16, 0.32),
            wall=rng.uniform(0.025, 0.04),
            ellipticity=rng.uniform(0.0, 0.12),
            spout=rng.uniform(0.12, 0.3),
        )


def _outer_radius(p: VaseParameters, t: np.ndarray) -> np.ndarray:
    """Outer wall radius at height fraction t ∈ [0, 1] (monotone cubic through the controls)."""
    knots = np.array([0.0, p.belly_level, p.neck_level, 1.0])
    radii = np.array([p.base_radius, p.belly_radius, p.neck_radius, p.lip_radius])
    return PchipInterpolator(knots, radii)(np.clip(t, 0.0, 1.0))


def _wall_height(p: VaseParameters, u: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """Height fraction t of wall coordinate u ∈ [0, 1], piecewise linear so that the
    profile's features sit at the same u on every vase: u = 1/3 is the belly, u = 2/3 the
    neck (the inner wall starts at the floor instead of the base). Equal surface
    coordinates therefore mean the same part (belly to belly), which is what a geometric
    correspondence can recover."""
    return np.interp(u, [0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0], [floor, p.belly_level, p.neck_level, 1.0])


def _profile(p: VaseParameters, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Profile point (radius, height) at profile coordinate s, and a weight in [0, 1] of how
    much the lip bulge applies there."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
    b = PROFILE_BREAKS
    r = np.empty_like(s)
    z = np.empty_like(s)
    floor_z = p.floor_level * p.height
    floor_t = p.floor_level
    seg = np.searchsorted(b, s, side="right") - 1
    seg = np.clip(seg, 0, 4)
    u = (s - b[seg]) / (b[seg + 1] - b[seg])
    # base disk: centre → base rim
    m = seg == 0
    r[m] = u[m] * p.base_radius
    z[m] = 0.0
    # outer wall: up
    m = seg == 1
    t = _wall_height(p, u[m])
    r[m] = _outer_radius(p, t)
    z[m] = t * p.height
    # rim: outer → inner edge
    m = seg == 2
    r[m] = p.lip_radius - u[m] * p.wall
    z[m] = p.height
    # inner wall: down to the floor
    m = seg == 3
    t = _wall_height(p, 1.0 - u[m], floor=floor_t)
    r[m] = _outer_radius(p, t) - p.wall
    z[m] = t * p.height
    # inner floor: edge → centre
    m = seg == 4
    r[m] = (1.0 - u[m]) * (_outer_radius(p, np.array([floor_t]))[0] - p.wall)
    z[m] = floor_z
    lip_weight = np.clip((z / p.height - p.neck_level) / (1.0 - p.neck_level), 0.0, 1.0) ** 2
    return r, z, lip_weight


def vase_surface(p: VaseParameters, s: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Canonical (unposed) surface point at surface coordinates (s, θ), shape (..., 3).

    The cross-section is an ellipse with semi-axes r(1 + e) and r(1 − e) in the
    eccentric-angle parametrisation (x = r(1+e) cos θ, y = r(1−e) sin θ), so an affine map
    between two sections keeps θ — equal θ is then a correspondence geometry can recover
    (with the polar angle, affine-consistent matches disagreed with the ground truth by
    0.41 % of the diagonal on average). The pouring lip scales the radius near θ = 0."""
    r, z, lip = _profile(p, s)
    theta = np.asarray(theta, dtype=np.float64)
    bulge = 1.0 + p.spout * lip * np.exp(-(np.angle(np.exp(1j * theta)) / 0.5) ** 2)
    rr = r * bulge
    x = rr * (1.0 + p.ellipticity) * np.cos(theta)
    y = rr * (1.0 - p.ellipticity) * np.sin(theta)
    return np.stack([x, y, np.broadcast_to(z, rr.shape)], axis=-1)


@dataclass(frozen=True)
class ProceduralShape:
    """A generated shape: its mesh in the input pose plus what is known about it."""

    mesh: Mesh  # input coordinates (posed)
    params: VaseParameters
    vertex_st: np.ndarray  # (V, 2) surface coordinates (s, θ) of every vertex
    pose: ShapeTransform  # canonical → input coordinates
    meta: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.mesh.name

    def surface_coordinates(self, face_index: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
        """(s, θ) of surface points given by face and barycentrics, (n, 2).

        θ is interpolated on the unit circle so faces across θ = ±π are handled."""
        corners = self.vertex_st[self.mesh.faces[face_index]]  # (n, 3, 2)
        s = np.einsum("nk,nk->n", barycentric, corners[..., 0])
        c = np.einsum("nk,nk->n", barycentric, np.cos(corners[..., 1]))
        si = np.einsum("nk,nk->n", barycentric, np.sin(corners[..., 1]))
        return np.stack([s, np.arctan2(si, c)], axis=1)

    def points_at(self, st: np.ndarray) -> np.ndarray:
        """Input-frame surface points of this shape at surface coordinates st (n, 2)."""
        st = np.asarray(st, dtype=np.float64)
        return self.pose.to_normalised(vase_surface(self.params, st[:, 0], st[:, 1]))


def _ring_levels(rng: np.random.Generator, n_rings: int) -> np.ndarray:
    """Profile coordinates of the vertex rings: every part breakpoint plus jittered
    interior levels, a share of n_rings per part proportional to its s-length."""
    levels = [PROFILE_BREAKS[1:-1]]
    widths = np.diff(PROFILE_BREAKS)
    for lo, hi, w in zip(PROFILE_BREAKS[:-1], PROFILE_BREAKS[1:], widths):
        k = max(2, int(round(n_rings * w)))
        inner = np.linspace(lo, hi, k + 1)[1:-1]
        inner = inner + rng.uniform(-0.3, 0.3, inner.shape) * (hi - lo) / k
        levels.append(inner)
    return np.unique(np.concatenate(levels))


def _vase_mesh(p: VaseParameters, rng: np.random.Generator, n_rings: int, n_around: int):
    """Triangulate the surface of revolution: pole vertices at s = 0 and s = 1, rings in
    between with per-ring angular offsets and random quad diagonals."""
    levels = _ring_levels(rng, n_rings)
    offsets = rng.uniform(0, 2 * np.pi / n_around, len(levels))
    theta = 2 * np.pi * np.arange(n_around)[None, :] / n_around + offsets[:, None]
    theta = np.angle(np.exp(1j * theta))  # wrap to (−π, π]
    st = [np.array([[0.0, 0.0]])]
    for k, s in enumerate(levels):
        st.append(np.stack([np.full(n_around, s), theta[k]], axis=1))
    st.append(np.array([[1.0, 0.0]]))
    st = np.concatenate(st)
    vertices = vase_surface(p, st[:, 0], st[:, 1])

    faces = []
    ring = lambda k: 1 + k * n_around + np.arange(n_around)  # noqa: E731
    first, last = ring(0), ring(len(levels) - 1)
    top = len(st) - 1
    j = np.arange(n_around)
    # bottom pole fan (outward normal points down: ring order reversed)
    faces.append(np.stack([np.zeros(n_around, int), first[(j + 1) % n_around], first[j]], axis=1))
    for k in range(len(levels) - 1):
        a, b = ring(k), ring(k + 1)
        a0, a1, b0, b1 = a[j], a[(j + 1) % n_around], b[j], b[(j + 1) % n_around]
        flip = rng.random(n_around) < 0.5
        t1 = np.where(flip[:, None], np.stack([a0, a1, b1], 1), np.stack([a0, a1, b0], 1))
        t2 = np.where(flip[:, None], np.stack([a0, b1, b0], 1), np.stack([a1, b1, b0], 1))
        faces.extend([t1, t2])
    faces.append(np.stack([np.full(n_around, top), last[j], last[(j + 1) % n_around]], axis=1))
    return vertices, np.concatenate(faces), st


def make_vases(
    n: int = 24,
    seed: int = 0,
    resolution: tuple[int, int] = (40, 90),
    pose: bool = True,
) -> list[ProceduralShape]:
    """`n` random vases, each with its own triangulation and (optionally) input pose.

    resolution: range of the number of vertex rings along the profile; the number around
    is about 1.3 × that, so a shape has roughly 2,000–10,000 vertices at the default.
    """
    rng = np.random.default_rng(seed)
    shapes = []
    for i in range(n):
        params = VaseParameters.random(rng)
        n_rings = int(rng.integers(resolution[0], resolution[1] + 1))
        n_around = int(round(n_rings * rng.uniform(1.1, 1.5)))
        vertices, faces, st = _vase_mesh(params, rng, n_rings, n_around)
        placement = _random_placement(rng) if pose else ShapeTransform.identity()
        mesh = Mesh(placement.to_normalised(vertices), faces, name=f"vase_{i:03d}")
        shapes.append(ProceduralShape(mesh, params, st, placement))
    return shapes


def _random_placement(rng: np.random.Generator) -> ShapeTransform:
    """Random yaw about z, scale in [0.5, 2] and translation in [-1, 1]³."""
    yaw = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ShapeTransform(rotation, float(rng.uniform(0.5, 2.0)), rng.uniform(-1, 1, 3))


def _capped_ring_faces(count: int, n_around: int, rng: np.random.Generator | None = None) -> np.ndarray:
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
    return vertices, _capped_ring_faces(len(rings), n_around)


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
        placement = _random_placement(rng) if pose else ShapeTransform.identity()
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
        placement = _random_placement(rng) if pose else ShapeTransform.identity()
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
        placement = _random_placement(rng) if pose else ShapeTransform.identity()
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


def write_collection(shapes, folder: str | Path, file_format: str = "obj") -> list[Path]:
    """Write the shapes' meshes into `folder` as `<name>.<format>`; returns the paths."""
    from .meshes.reading import write_mesh

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return [write_mesh(s.mesh, folder / f"{s.name}.{file_format}") for s in shapes]


# ---------------------------------------------------------------------------- classes built from parts
@dataclass(frozen=True)
class PartedShape:
    """A generated shape made of parts, each the image of a map (u, v) → R³ with u ∈ [0, 1]
    from one pole to the other and v ∈ (−π, π] around (`_part_mesh`), with its ground
    truth: equal (part, u, v) on two shapes of a class is their true correspondence. Same
    interface as ProceduralShape (`surface_coordinates`, `points_at`), so a benchmark
    measures the true error of either the same way."""

    mesh: Mesh  # input coordinates (posed)
    parts: tuple  # one canonical surface map per part: (u, v) arrays → (..., 3)
    vertex_coordinates: np.ndarray  # (V, 3) part, u, v of every vertex (v NaN at a pole: any angle)
    pose: ShapeTransform  # canonical → input coordinates

    @property
    def name(self) -> str:
        return self.mesh.name

    def surface_coordinates(self, face_index: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
        """(part, u, v) of surface points given by face and barycentrics, (n, 3). A face
        never spans two parts; v is interpolated on the unit circle, a pole's corner not
        counted (its angle is arbitrary)."""
        corners = self.vertex_coordinates[self.mesh.faces[face_index]]  # (n, 3, 3)
        u = np.einsum("nk,nk->n", barycentric, corners[..., 1])
        angle = corners[..., 2]
        pole = np.isnan(angle)
        c = np.einsum("nk,nk->n", barycentric, np.where(pole, 0.0, np.cos(angle)))
        s = np.einsum("nk,nk->n", barycentric, np.where(pole, 0.0, np.sin(angle)))
        return np.stack([corners[:, 0, 0], u, np.arctan2(s, c)], axis=1)

    def points_at(self, coordinates: np.ndarray) -> np.ndarray:
        """Input-frame surface points of this shape at (part, u, v) rows (n, 3)."""
        coordinates = np.asarray(coordinates, dtype=np.float64)
        points = np.empty((len(coordinates), 3))
        for k, surface in enumerate(self.parts):
            mine = coordinates[:, 0] == k
            points[mine] = surface(coordinates[mine, 1], np.nan_to_num(coordinates[mine, 2]))
        return self.pose.to_normalised(points)


def _part_mesh(surface, rng: np.random.Generator, breaks, n_rings: int,
               n_around: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate the part `surface(u, v)` as `_vase_mesh` does a vase: pole vertices at
    u = 0 and u = 1, rings at every break of `breaks` and jittered levels between, each ring
    with its own angular offset, random quad diagonals. Returns canonical vertices, faces
    (outward when (∂/∂v, ∂/∂u) is a right-handed turn about the outward normal, as for a
    surface of revolution about +z) and the (u, v) of every vertex (v NaN at the poles)."""
    breaks = np.asarray(breaks, dtype=np.float64)
    levels = [breaks[1:-1]]
    for lo, hi in zip(breaks[:-1], breaks[1:]):
        k = max(2, int(round(n_rings * (hi - lo))))
        inner = np.linspace(lo, hi, k + 1)[1:-1]
        levels.append(inner + rng.uniform(-0.3, 0.3, inner.shape) * (hi - lo) / k)
    levels = np.unique(np.concatenate(levels))
    theta = 2 * np.pi * np.arange(n_around)[None, :] / n_around + rng.uniform(0, 2 * np.pi / n_around, (len(levels), 1))
    theta = np.angle(np.exp(1j * theta))
    uv = np.concatenate([[[0.0, np.nan]], np.stack([np.repeat(levels, n_around), theta.ravel()], axis=1),
                         [[1.0, np.nan]]])
    vertices = surface(uv[:, 0], np.nan_to_num(uv[:, 1]))
    return vertices, _capped_ring_faces(len(levels), n_around, rng), uv


#: u-values where a tube (`_tube`) changes part: start cap | wall | end cap
TUBE_BREAKS = (0.0, 0.1, 0.9, 1.0)


def _tube(centre, radius, reference):
    """Surface map (u, v) → R³ of a closed tube around the curve `centre(a)` (a ∈ [0, 1] →
    (n, 3)) with radius `radius(a)` and flat caps (TUBE_BREAKS): the start cap's centre is
    u = 0, its rim u = 0.1, the wall runs to u = 0.9, the end cap to its centre u = 1. The
    angle v is measured from `reference` (any direction never along the curve) turned about
    the tangent t, so (n₁, n₂, t) is right-handed and the faces of `_part_mesh` face out."""
    cap = TUBE_BREAKS[1]

    def surface(u, v):
        u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
        a = np.clip((u - cap) / (1.0 - 2.0 * cap), 0.0, 1.0)
        rho = np.clip(np.minimum(u, 1.0 - u) / cap, 0.0, 1.0)
        step = 1e-4
        tangent = centre(np.minimum(a + step, 1.0)) - centre(np.maximum(a - step, 0.0))
        tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
        n1 = reference - np.sum(reference * tangent, axis=-1, keepdims=True) * tangent
        n1 /= np.linalg.norm(n1, axis=-1, keepdims=True)
        n2 = np.cross(tangent, n1)
        ring = np.cos(v)[..., None] * n1 + np.sin(v)[..., None] * n2
        return centre(a) + (rho * radius(a))[..., None] * ring

    return surface


def _line(start, end):
    """The curve a ↦ start + a (end − start), for `_tube`."""
    start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    return lambda a: start + np.asarray(a, dtype=np.float64)[..., None] * (end - start)


def _parted_shape(parts, resolutions, rng: np.random.Generator, pose: bool, name: str) -> PartedShape:
    """Mesh every part (surface, breaks) of `parts` at its (rings, around) of `resolutions`
    into one mesh of separate closed components, and place it in a random input pose."""
    vertices, faces, coordinates, offset = [], [], [], 0
    for k, ((surface, breaks), (n_rings, n_around)) in enumerate(zip(parts, resolutions)):
        part_vertices, part_faces, uv = _part_mesh(surface, rng, breaks, n_rings, n_around)
        vertices.append(part_vertices)
        faces.append(part_faces + offset)
        coordinates.append(np.column_stack([np.full(len(uv), float(k)), uv]))
        offset += len(part_vertices)
    placement = _random_placement(rng) if pose else ShapeTransform.identity()
    mesh = Mesh(placement.to_normalised(np.vstack(vertices)), np.vstack(faces), name=name)
    return PartedShape(mesh, tuple(surface for surface, _ in parts), np.vstack(coordinates), placement)


#: u-values where a handled mug's body changes part: base | outer wall | rim | inner wall | floor
MUG_BREAKS = (0.0, 0.1, 0.5, 0.55, 0.9, 1.0)


def make_handled_mugs(n: int = 12, seed: int = 0, resolution: tuple[int, int] = (30, 50),
                      handle_height: tuple[float, float] = (0.35, 0.65), pose: bool = True) -> list[PartedShape]:
    """`n` random open mugs with a handle and ground truth (PartedShape): a thick-walled body
    of revolution about +z whose straight wall leans in on some and out on others (as
    make_mugs), and a handle, a tube along a half ellipse at +x whose centre sits at a
    height drawn from `handle_height` (fraction of the body's height) and reaches into the
    wall: a feature at a shape-specific height. The body's coordinates follow the profile
    (MUG_BREAKS: wall points at equal height fractions correspond), the handle's its arc.
    resolution: range of the body's ring count (about 1.4 × as many around)."""
    rng = np.random.default_rng(seed)
    shapes = []
    for i in range(n):
        radius, height = rng.uniform(0.8, 1.2), rng.uniform(1.4, 2.4)
        lean, wall, floor = rng.uniform(-0.25, 0.25), rng.uniform(0.08, 0.12), rng.uniform(0.1, 0.18) * height
        centre, reach = rng.uniform(*handle_height) * height, rng.uniform(0.22, 0.3) * height
        out_reach, tube = rng.uniform(0.7, 1.0) * reach, rng.uniform(0.05, 0.08)
        outer = lambda z, radius=radius, height=height, lean=lean: radius * (1.0 + lean * (z / height - 0.5))  # noqa: E731

        def body(u, v, outer=outer, height=height, wall=wall, floor=floor):
            b = MUG_BREAKS
            segment = np.clip(np.searchsorted(b, u, side="right") - 1, 0, 4)
            w = (u - np.take(b, segment)) / np.diff(b)[segment]
            z = np.choose(segment, [0.0 * w, w * height, height + 0.0 * w, height - w * (height - floor), floor + 0.0 * w])
            r = np.choose(segment, [w * outer(0.0), outer(z), outer(height) - w * wall, outer(z) - wall,
                                    (1.0 - w) * (outer(floor) - wall)])
            return np.stack([r * np.cos(v), r * np.sin(v), z], axis=-1)

        def arc(a, outer=outer, centre=centre, reach=reach, out_reach=out_reach):
            phi = np.pi * (np.asarray(a, dtype=np.float64) - 0.5)
            z = centre + reach * np.sin(phi)
            return np.stack([outer(z) - 0.05 + out_reach * np.cos(phi), 0.0 * z, z], axis=-1)

        rings = int(rng.integers(resolution[0], resolution[1] + 1))
        handle = _tube(arc, lambda a, tube=tube: np.full(np.shape(a), tube), np.array([0.0, 1.0, 0.0]))
        shapes.append(_parted_shape([(body, MUG_BREAKS), (handle, TUBE_BREAKS)],
                                    [(rings, int(round(1.4 * rings))), (rings, max(10, rings // 3))],
                                    rng, pose, f"handled_mug_{i:03d}"))
    return shapes


#: where a quadruped's legs meet its body, (x / half width, y / half length)
LEG_PLACES = ((0.55, 0.6), (-0.55, 0.6), (0.55, -0.6), (-0.55, -0.6))


def make_quadrupeds(n: int = 12, seed: int = 0, resolution: tuple[int, int] = (30, 45),
                    pose: bool = True) -> list[PartedShape]:
    """`n` random four-legged animals with ground truth (PartedShape), a class that is not a
    body of revolution: a rounded-box body (a superellipsoid, exponent 0.6, long along +y,
    proportions drawn per shape), four legs standing on z = 0 at LEG_PLACES, a neck at the
    front ending in a wider head, a tail at the back. Neck and tail are raised by angles
    drawn per shape, so they move like limbs in another pose. The body's coordinates are
    its superellipsoid angles (equal angles are an affine map between two bodies, so
    geometry can recover them); every tube's follow its centre line (`_tube`).
    resolution: range of the body's ring count (about 1.4 × as many around)."""
    rng = np.random.default_rng(seed)
    exponent = 0.6
    power = lambda x: np.sign(x) * np.abs(x) ** exponent  # noqa: E731
    shapes = []
    for i in range(n):
        length, width, depth = rng.uniform(1.2, 2.0), rng.uniform(0.4, 0.7), rng.uniform(0.4, 0.7)
        legs, leg_radius = rng.uniform(0.5, 1.0), rng.uniform(0.05, 0.09)
        neck, neck_angle, head = rng.uniform(0.4, 0.8), np.radians(rng.uniform(25, 75)), rng.uniform(0.12, 0.2)
        tail, tail_angle = rng.uniform(0.3, 0.7), np.radians(rng.uniform(-20, 60))
        middle = legs + 0.3 * depth

        def body(u, v, length=length, width=width, depth=depth, middle=middle):
            eta = np.pi * (np.asarray(u, dtype=np.float64) - 0.5)
            ring = power(np.cos(eta))
            return np.stack([0.5 * width * ring * power(np.cos(v)), 0.5 * length * ring * power(np.sin(v)),
                             middle + 0.5 * depth * power(np.sin(eta))], axis=-1)

        down = np.array([1.0, 0.0, 0.0])
        parts = [(body, (0.0, 1.0))]
        for x, y in LEG_PLACES:
            top = [x * 0.5 * width, y * 0.5 * length, middle]
            leg = _tube(_line(top, [top[0], top[1], 0.0]),
                        lambda a, r=leg_radius: r * (1.0 - 0.3 * np.asarray(a)), down)
            parts.append((leg, TUBE_BREAKS))
        neck_start = np.array([0.0, 0.4 * length, middle + 0.2 * depth])
        neck_end = neck_start + neck * np.array([0.0, np.cos(neck_angle), np.sin(neck_angle)])
        neck_radius = 0.35 * min(width, depth)
        swell = lambda a, r=neck_radius, h=head: r + (h - r) * np.clip((np.asarray(a) - 0.6) / 0.4, 0, 1) ** 2  # noqa: E731
        parts.append((_tube(_line(neck_start, neck_end), swell, down), TUBE_BREAKS))
        tail_start = np.array([0.0, -0.45 * length, middle + 0.1 * depth])
        tail_end = tail_start + tail * np.array([0.0, -np.cos(tail_angle), np.sin(tail_angle)])
        parts.append((_tube(_line(tail_start, tail_end), lambda a: 0.04 * (1.0 - 0.5 * np.asarray(a)), down),
                      TUBE_BREAKS))
        rings = int(rng.integers(resolution[0], resolution[1] + 1))
        tube_resolution = (max(10, rings // 2), max(10, rings // 3))
        shapes.append(_parted_shape(parts, [(rings, int(round(1.4 * rings)))] + [tube_resolution] * 6,
                                    rng, pose, f"quadruped_{i:03d}"))
    return shapes
