"""Classes built from parts (`PartedShape`): mugs with a handle (`make_handled_mugs`) and
four-legged animals (`make_quadrupeds`), each part the image of a map (u, v) → R³ with its
ground truth, so correspondence error can be measured exactly as on the vases."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..meshes.mesh import Mesh
from ..preprocess import ShapeTransform
from .revolved import capped_ring_faces
from .vases import random_placement


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
    return vertices, capped_ring_faces(len(levels), n_around, rng), uv


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
    placement = random_placement(rng) if pose else ShapeTransform.identity()
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
