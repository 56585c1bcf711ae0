"""Vases (`make_vases`): thick-walled jugs made by revolving a profile around z, with an
elliptical cross-section and a pouring lip, and their ground truth: every surface point has
surface coordinates (s, θ) (see the package's docstring), so correspondence error can be
measured exactly."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import PchipInterpolator

from ..meshes.mesh import Mesh
from ..preprocess import ShapeTransform


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
        placement = random_placement(rng) if pose else ShapeTransform.identity()
        mesh = Mesh(placement.to_normalised(vertices), faces, name=f"vase_{i:03d}")
        shapes.append(ProceduralShape(mesh, params, st, placement))
    return shapes


def random_placement(rng: np.random.Generator) -> ShapeTransform:
    """Random yaw about z, scale in [0.5, 2] and translation in [-1, 1]³."""
    yaw = rng.uniform(-np.pi, np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return ShapeTransform(rotation, float(rng.uniform(0.5, 2.0)), rng.uniform(-1, 1, 3))
