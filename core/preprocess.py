"""Alignment and scaling of a shape collection, every transform recorded (thesis §3.4).

Each shape gets one similarity transform, stored as a 4×4 matrix `M` with
``normalised = M @ [x, 1]`` (``M = [s R | t]``, R a proper rotation, s > 0). Its inverse
is exact, so every later result (landmarks, samples) maps back to each input's own
coordinates: `ShapeTransform.to_input`.

Steps, in order (`prepare_collection`):

1. Up axis: the input axis named by `up_axis` becomes +z.
2. Horizontal PCA (`align="pca"`): the first principal axis of the x–y spread becomes x,
   sign by the rule "the heavier third moment goes to +x" (skewness of x positive).
3. Consensus (`align="consensus"`, default): the orientation of every shape is made to
   agree with the collection. Each shape has 24 candidate poses: any of its six axis
   directions turned up, the horizontal PCA (and sign rule) redone in that upright frame,
   then a quarter turn k·90° about z; candidate 0 is its step-2 pose. Each shape keeps
   the candidate with the smallest symmetric Chamfer distance to a reference shape (the
   medoid); then the majority decides: if most shapes had to leave their own pose to
   match the reference, the reference was the odd one out and is replaced by a member of
   that majority (see `_consensus_rotations`). This fixes shapes whose file uses another
   up axis, and shapes that are upside down or facing backwards, which a per-shape sign
   rule cannot decide (a vase's third moment flips with small details), while the
   orientation most input files agree on is kept.
4. Floor at z = 0 and centring (`centre`: "centroid" of the x–y surface spread,
   "highest" vertex, or "none").
5. Scale (`scale`): "variance" — every shape gets the same total surface variance
   (tr Cov over the surface, exact triangle integrals); "bbox" — the same axis-aligned
   bounding-box volume; "none". The common value is the geometric mean of the
   collection's measures, so units stay those of the inputs.

Moments are exact surface integrals (uniform density over the surface), so neither mesh
resolution nor interior vertices bias them (method.md §1 **beyond**).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from .errors import CollectionError, MeshError
from .mesh import Mesh

__all__ = [
    "ShapeTransform",
    "PreparedShape",
    "prepare_collection",
    "surface_moments",
    "scale_measure",
    "UP_AXES",
    "ALIGN_MODES",
    "SCALE_MODES",
    "CENTRE_MODES",
]

UP_AXES = ("x", "y", "z", "-x", "-y", "-z")
ALIGN_MODES = ("consensus", "pca", "none")
SCALE_MODES = ("variance", "bbox", "none")
CENTRE_MODES = ("centroid", "highest", "none")

#: Points per shape for the Chamfer comparison in the consensus step.
CONSENSUS_POINTS = 1500
#: Shapes considered when choosing the reference (medoid); evenly spaced over the sorted set.
CONSENSUS_MEDOID_CANDIDATES = 12
#: Rounds of "match everyone to the reference, let the majority orientation pick a new
#: reference" (`_consensus_rotations`).
CONSENSUS_MAX_ROUNDS = 3
#: A candidate pose must beat the shape's own (sign-rule) pose by this relative Chamfer
#: margin to replace it (`_prefer_own_pose`).
CONSENSUS_MARGIN = 0.05
#: Steps 5-6 of `_consensus_rotations`: a shape is compared with this many nearest shapes
#: of the panel; a changed pose pays this relative penalty in the consistency energy.
CONSENSUS_NEIGHBOURS = 2
#: Up to this many shapes, every shape is in the panel of steps 5-6 (else the medoid candidates).
CONSENSUS_PANEL = 40
CONSENSUS_NEIGHBOUR_MARGIN = 0.15
CONSENSUS_MAX_SWEEPS = 5
#: Legendre polynomials in height used by the facing signature (`_facing_signature`).
FACING_ORDER = 5


@dataclass(frozen=True)
class ShapeTransform:
    """Similarity transform input → normalised frame: ``y = scale * R @ x + t``."""

    rotation: np.ndarray  # (3, 3) proper rotation
    scale: float
    translation: np.ndarray  # (3,)

    @property
    def matrix(self) -> np.ndarray:
        """4×4 homogeneous matrix of the forward transform."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def to_normalised(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        return self.scale * points @ self.rotation.T + self.translation

    def to_input(self, points: np.ndarray) -> np.ndarray:
        """Exact inverse: ``x = R^T (y - t) / scale``."""
        points = np.asarray(points, dtype=np.float64)
        return ((points - self.translation) @ self.rotation) / self.scale

    def then(self, rotation=None, scale=1.0, translation=None) -> "ShapeTransform":
        """Compose: apply self, then ``y -> scale * rotation @ y + translation``."""
        rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        translation = np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
        return ShapeTransform(
            rotation @ self.rotation,
            float(scale * self.scale),
            scale * rotation @ self.translation + translation,
        )

    @staticmethod
    def identity() -> "ShapeTransform":
        return ShapeTransform(np.eye(3), 1.0, np.zeros(3))

    @staticmethod
    def from_matrix(matrix: np.ndarray) -> "ShapeTransform":
        matrix = np.asarray(matrix, dtype=np.float64)
        if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
            raise ValueError(f"transform matrix must be a finite 4×4 array, got {matrix.shape}")
        linear = matrix[:3, :3]
        scale = float(np.cbrt(np.linalg.det(linear)))
        if scale <= 0:
            raise ValueError("transform matrix is not a proper similarity (det <= 0)")
        rotation = linear / scale
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-8):
            raise ValueError("transform matrix is not a similarity (rotation part not orthonormal)")
        return ShapeTransform(rotation, scale, matrix[:3, 3].copy())


@dataclass(frozen=True)
class PreparedShape:
    """A shape in the normalised frame with the transform from its input frame."""

    mesh: Mesh  # normalised coordinates
    transform: ShapeTransform
    orientation_changed: bool = False  # consensus picked a different orientation than PCA

    @property
    def name(self) -> str:
        return self.mesh.name


# ---------------------------------------------------------------------------- moments
def surface_moments(mesh: Mesh) -> tuple[float, np.ndarray, np.ndarray]:
    """Exact area, mean and covariance of the uniform distribution on the surface.

    For a triangle with corners a, b, c and area A: ∫x dA = A (a+b+c)/3 and
    ∫x xᵀ dA = A/12 (a aᵀ + b bᵀ + c cᵀ + s sᵀ), s = a + b + c.
    """
    tri = mesh.triangles
    areas = mesh.face_areas()
    total = float(areas.sum())
    if total <= 0:
        raise MeshError(f"{mesh.name or 'mesh'}: surface area is zero")
    s = tri.sum(axis=1)
    mean = (areas[:, None] * s).sum(axis=0) / (3.0 * total)
    second = np.einsum("f,fki,fkj->ij", areas, tri, tri) + np.einsum("f,fi,fj->ij", areas, s, s)
    second /= 12.0 * total
    cov = second - np.outer(mean, mean)
    return total, mean, 0.5 * (cov + cov.T)


def _third_central_moment(mesh: Mesh, axis: np.ndarray, centre: np.ndarray) -> float:
    """Exact surface mean of f³ for the linear function f(x) = axis · (x − centre).

    Over a triangle with corner values f1, f2, f3: mean f³ = (Σ f_i³ + Σ_{i≠j} f_i² f_j
    + f1 f2 f3) / 10.
    """
    f = (mesh.triangles - centre) @ axis  # (F, 3)
    f1, f2, f3 = f[:, 0], f[:, 1], f[:, 2]
    cubic = (
        f1**3 + f2**3 + f3**3
        + f1**2 * (f2 + f3) + f2**2 * (f1 + f3) + f3**2 * (f1 + f2)
        + f1 * f2 * f3
    ) / 10.0
    areas = mesh.face_areas()
    return float((areas * cubic).sum() / areas.sum())


def scale_measure(mesh: Mesh, mode: str) -> float:
    """The size a scaling mode equalises: total surface variance, or bounding-box volume."""
    if mode == "variance":
        _, _, cov = surface_moments(mesh)
        return float(np.trace(cov))
    if mode == "bbox":
        lo, hi = mesh.bounds()
        return float(np.prod(hi - lo))
    raise ValueError(f"unknown scale mode {mode!r}; choose from {SCALE_MODES}")


# ---------------------------------------------------------------------------- rotations
def _up_rotation(up_axis: str) -> np.ndarray:
    """Proper rotation taking the named input axis to +z."""
    if up_axis not in UP_AXES:
        raise ValueError(f"unknown up axis {up_axis!r}; choose from {UP_AXES}")
    sign = -1.0 if up_axis.startswith("-") else 1.0
    axis = "xyz".index(up_axis[-1])
    up = np.zeros(3)
    up[axis] = sign
    if axis == 2:
        return np.diag([1.0, sign, sign])  # z: identity; -z: 180° about x
    # new z = up; new x = the next input axis cyclically (x->y->z), y completes right-handed
    new_x = np.zeros(3)
    new_x[(axis + 1) % 3] = 1.0
    new_y = np.cross(up, new_x)
    return np.stack([new_x, new_y, up])  # rows: input -> output basis


def _axis_rotations() -> np.ndarray:
    """The 24 proper rotations that map coordinate axes onto coordinate axes."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            r = np.zeros((3, 3))
            r[np.arange(3), perm] = signs
            if np.linalg.det(r) > 0:
                out.append(r)
    # identity first so ties keep the unrotated frame
    out.sort(key=lambda r: -np.trace(r))
    return np.stack(out)


AXIS_ROTATIONS = _axis_rotations()


def _horizontal_pca_rotation(mesh: Mesh) -> np.ndarray:
    """Rotation about z putting the main axis of the x–y spread on x, with +x the side of
    the positive third moment (deterministic sign rule)."""
    _, mean, cov = surface_moments(mesh)
    evals, evecs = np.linalg.eigh(cov[:2, :2])
    main = np.array([evecs[0, 1], evecs[1, 1], 0.0])  # largest eigenvalue last
    if _third_central_moment(mesh, main, mean) < 0:
        main = -main
    c, s = main[0], main[1]
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _principal_frame_rotation(mesh: Mesh) -> np.ndarray:
    """Proper rotation whose rows are the 3-D principal axes (largest variance first),
    each signed so its third moment is positive (last one fixed by handedness)."""
    _, mean, cov = surface_moments(mesh)
    evals, evecs = np.linalg.eigh(cov)
    axes = evecs[:, ::-1].T.copy()
    for k in range(2):
        if _third_central_moment(mesh, axes[k], mean) < 0:
            axes[k] = -axes[k]
    axes[2] = np.cross(axes[0], axes[1])
    return axes


def _rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle of a rotation matrix, in degrees."""
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))


def _normalised_samples(mesh: Mesh, rotation: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Surface samples, rotated, centred at the surface centroid, unit total variance."""
    _, mean, cov = surface_moments(mesh)
    pts = mesh.sample_surface(n, np.random.default_rng(seed)).points
    pts = (pts - mean) @ rotation.T / np.sqrt(np.trace(cov))
    return pts


# ---------------------------------------------------------------------------- main entry
def prepare_collection(
    meshes: Sequence[Mesh],
    up_axis: str = "z",
    align: str = "consensus",
    centre: str = "centroid",
    scale: str = "variance",
    seed: int = 0,
    progress: Callable[[float, str], None] | None = None,
) -> list[PreparedShape]:
    """Align and scale a collection of meshes (see module docstring for the steps)."""
    if align not in ALIGN_MODES:
        raise ValueError(f"unknown align mode {align!r}; choose from {ALIGN_MODES}")
    if centre not in CENTRE_MODES:
        raise ValueError(f"unknown centre mode {centre!r}; choose from {CENTRE_MODES}")
    if scale not in SCALE_MODES:
        raise ValueError(f"unknown scale mode {scale!r}; choose from {SCALE_MODES}")
    meshes = list(meshes)
    if not meshes:
        raise CollectionError("the collection is empty: nothing to prepare")
    report = progress or (lambda fraction, message: None)

    up = _up_rotation(up_axis)
    rotations: list[np.ndarray] = []
    for mesh in meshes:
        rotation = up
        if align in ("pca", "consensus"):
            upright = mesh.with_vertices(mesh.vertices @ up.T)
            rotation = _horizontal_pca_rotation(upright) @ up
        rotations.append(rotation)
    report(0.2, "principal axes")

    changed = [False] * len(meshes)
    if align == "consensus" and len(meshes) > 1:
        rotations, changed = _consensus_rotations(meshes, rotations, seed, report, up)
    report(0.8, "floor, centre and scale")

    transforms = []
    for mesh, rotation in zip(meshes, rotations):
        # only vertices that belong to a face count (an unused stray vertex is no surface)
        rotated = mesh.vertices[np.unique(mesh.faces)] @ rotation.T
        shift = np.zeros(3)
        shift[2] = -rotated[:, 2].min()
        if centre == "centroid":
            _, mean, _ = surface_moments(mesh)
            shift[:2] = -(rotation @ mean)[:2]
        elif centre == "highest":
            shift[:2] = -rotated[int(np.argmax(rotated[:, 2])), :2]
        transforms.append(ShapeTransform(rotation, 1.0, shift))

    if scale != "none":
        measures = []
        for mesh, transform in zip(meshes, transforms):
            value = scale_measure(mesh.with_vertices(transform.to_normalised(mesh.vertices)), scale)
            if not np.isfinite(value) or value <= 0:
                raise MeshError(
                    f"{mesh.name or 'mesh'}: cannot scale by {scale}: the measure is {value} "
                    "(a flat or degenerate shape)"
                )
            measures.append(value)
        measures = np.asarray(measures)
        target = float(np.exp(np.mean(np.log(measures))))
        power = 0.5 if scale == "variance" else 1.0 / 3.0
        transforms = [
            t.then(scale=(target / m) ** power) for t, m in zip(transforms, measures)
        ]

    prepared = [
        PreparedShape(mesh.with_vertices(t.to_normalised(mesh.vertices)), t, c)
        for mesh, t, c in zip(meshes, transforms, changed)
    ]
    report(1.0, "prepared")
    return prepared


def _candidate_poses(mesh: Mesh, up: np.ndarray) -> np.ndarray:
    """The 24 candidate orientations of one shape, (24, 3, 3), index 0 = its PCA pose.

    Candidate 4·d + k: the axis d of the up-rotated frame (+z, -z, +x, -x, +y, -y) is
    turned to +z, the horizontal PCA with its sign rule is redone in that upright frame
    (so a shape lying on its side still gets its own principal horizontal axis on x), then
    a turn of k·90° about z. Every candidate is built from the shape's own moments, so the
    choice between them is the only thing the collection decides.
    """
    _, mean, cov = surface_moments(mesh)
    poses = []
    for d in range(6):
        tilt = _TILTS[d] @ up
        c2 = (tilt @ cov @ tilt.T)[:2, :2]
        _, evecs = np.linalg.eigh(c2)
        main = np.array([evecs[0, 1], evecs[1, 1], 0.0])
        if _third_central_moment(mesh, tilt.T @ main, mean) < 0:
            main = -main
        yaw = np.array([[main[0], main[1], 0.0], [-main[1], main[0], 0.0], [0.0, 0.0, 1.0]])
        for k in range(4):
            poses.append(_QUARTER_TURNS[k] @ yaw @ tilt)
    return np.stack(poses)


def _quarter_turns() -> np.ndarray:
    out = []
    for k in range(4):
        c, s = np.round(np.cos(k * np.pi / 2)), np.round(np.sin(k * np.pi / 2))
        out.append(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
    return np.stack(out)


def _tilts() -> np.ndarray:
    """Proper rotations taking +z, -z, +x, -x, +y, -y (in that order) to +z."""
    return np.stack([
        np.eye(3),
        np.diag([1.0, -1.0, -1.0]),
        np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
        np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
        np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
        np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    ])


_QUARTER_TURNS = _quarter_turns()
_TILTS = _tilts()


def _consensus_rotations(meshes, pca_rotations, seed, report, up=None):
    """Orient every shape like the collection (module docstring, step 3).

    1. Each shape gets 24 candidate poses (`_candidate_poses`; candidate 0 is its PCA pose).
    2. A reference: the medoid of up to CONSENSUS_MEDOID_CANDIDATES shapes under the
       rotation-minimised symmetric Chamfer distance (samples centred, unit variance).
    3. Every shape takes the candidate closest to the reference in its chosen pose,
       keeping its own pose when that is within CONSENSUS_MARGIN (`_prefer_own_pose`).
    4. Majority rule: the input orientation most shapes share wins. If the most common
       choice (up direction first, then the quarter turn among those) is not candidate 0,
       the reference was the odd one out (e.g. written upside down); the reference is
       replaced by the shape of that majority group closest to it, in its own PCA pose,
       and step 3 is repeated (at most CONSENSUS_MAX_ROUNDS times).
    5. Neighbours: a varied class (bowls and tall jugs in one "Vase" folder) fools a single
       reference: a bowl on its side resembles a jug more than an upright bowl does. So
       the pose of 3-4 is only a proposal: starting from everyone's own pose, each shape
       takes its proposed pose when that lowers its cost to its CONSENSUS_NEIGHBOURS
       nearest panel shapes (all shapes up to CONSENSUS_PANEL, in their current poses),
       a changed pose paying 1 + CONSENSUS_NEIGHBOUR_MARGIN; sweeps repeat until nothing
       moves (at most CONSENSUS_MAX_SWEEPS). A bowl then stays with the upright bowls.
       Known limit: a group of CONSENSUS_NEIGHBOURS or more shapes that share one wrong
       pose keeps it (they are each other's neighbours), e.g. two PSB teapots written
       z-up among y-up vases, two of four lying PSB dolphins.
    6. Facing: each shape takes the half turn about z its nearest panel shapes prefer by
       more than CONSENSUS_MARGIN. Below that (a spout moves the cost by well under 1 %,
       less than sampling noise) the half turn is decided by its odd-part signature
       (exact surface moments ∫x P_b(z), ∫y P_b(z)) against the rest of the collection
       (`_agree_on_facing`).
    """
    n = len(meshes)
    up = np.eye(3) if up is None else up
    poses = [_candidate_poses(m, up) for m in meshes]
    samples, trees = [], []
    for i, mesh in enumerate(meshes):
        _, mean, cov = surface_moments(mesh)
        pts = mesh.sample_surface(CONSENSUS_POINTS, np.random.default_rng(seed + i)).points
        pts = (pts - mean) / np.sqrt(np.trace(cov))
        samples.append(pts)
        trees.append(cKDTree(pts))

    def costs(j: int, i: int, pose_i: np.ndarray) -> np.ndarray:
        """Chamfer cost of each candidate pose of shape j against shape i in pose_i."""
        ref = samples[i] @ pose_i.T
        ref_tree = cKDTree(ref)
        out = np.empty(len(poses[j]))
        for c, pose in enumerate(poses[j]):
            d_ji, _ = ref_tree.query(samples[j] @ pose.T)
            d_ij, _ = trees[j].query(ref @ pose)  # reference brought into j's input frame
            out[c] = np.mean(d_ji**2) + np.mean(d_ij**2)
        return out

    candidates = np.unique(np.linspace(0, n - 1, min(n, CONSENSUS_MEDOID_CANDIDATES)).round().astype(int))
    dist = np.zeros((len(candidates), len(candidates)))
    for a, b in itertools.combinations(range(len(candidates)), 2):
        dist[a, b] = dist[b, a] = costs(candidates[b], candidates[a], poses[candidates[a]][0]).min()
    reference = int(candidates[int(np.argmin(dist.sum(axis=1)))])
    report(0.4, f"reference shape {meshes[reference].name}")

    choice = np.zeros(n, dtype=int)
    cost_to_ref = np.zeros(n)
    for round_ in range(CONSENSUS_MAX_ROUNDS):
        for j in range(n):
            if j == reference:
                choice[j], cost_to_ref[j] = 0, 0.0
                continue
            c = costs(j, reference, poses[reference][0])
            choice[j] = _prefer_own_pose(c)
            cost_to_ref[j] = c[choice[j]]
            report(0.4 + 0.4 * (round_ * n + j + 1) / (CONSENSUS_MAX_ROUNDS * n), f"orienting {meshes[j].name}")
        tilt = choice // 4
        top_tilt = _mode(tilt)
        turns = choice[tilt == top_tilt] % 4
        top = 4 * top_tilt + _mode(turns)
        if top == 0:
            break
        group = np.flatnonzero(choice == top)
        reference = int(group[np.argmin(cost_to_ref[group])])
        report(0.4, f"reference shape {meshes[reference].name} (majority orientation)")

    # 5. neighbours (step 5 of the docstring): the reference's answer against everyone's own
    panel = list(range(n)) if n <= CONSENSUS_PANEL else [int(i) for i in candidates]

    def pair_cost(j: int, pose_j: np.ndarray, i: int, pose_i: np.ndarray) -> float:
        ref = samples[i] @ pose_i.T
        d_ji, _ = cKDTree(ref).query(samples[j] @ pose_j.T)
        d_ij, _ = trees[j].query(ref @ pose_j)
        return float(np.mean(d_ji**2) + np.mean(d_ij**2))

    def near_cost(j: int, pose_j: np.ndarray, state: np.ndarray) -> float:
        c = sorted(pair_cost(j, pose_j, i, poses[i][state[i]]) for i in panel if i != j)
        return float(np.mean(c[:CONSENSUS_NEIGHBOURS]))

    proposal, choice = choice, np.zeros(n, dtype=int)
    for _ in range(CONSENSUS_MAX_SWEEPS):
        moved = False
        for j in np.flatnonzero(proposal != 0):
            other = proposal[j] if choice[j] == 0 else 0
            current = near_cost(j, poses[j][choice[j]], choice) * (1.0 + CONSENSUS_NEIGHBOUR_MARGIN * (choice[j] != 0))
            alternative = near_cost(j, poses[j][other], choice) * (1.0 + CONSENSUS_NEIGHBOUR_MARGIN * (other != 0))
            if alternative < current:
                choice[j] = other
                moved = True
        if not moved:
            break
    # 6. facing (step 6): a half turn about z by the neighbours, else the odd-part signature
    ambiguous = np.zeros(n, dtype=bool)
    flipped = choice.copy()
    for j in range(n):
        half = 4 * (choice[j] // 4) + (choice[j] % 4 + 2) % 4
        keep = near_cost(j, poses[j][choice[j]], choice)
        turn = near_cost(j, poses[j][half], choice)
        if turn * (1.0 + CONSENSUS_MARGIN) < keep:
            flipped[j] = half
        elif turn <= keep * (1.0 + CONSENSUS_MARGIN):
            ambiguous[j] = True
    choice = _agree_on_facing(flipped, meshes, poses, ambiguous)

    rotations = [pca_rotations[j] if choice[j] == 0 else poses[j][choice[j]] for j in range(n)]
    changed = [bool(choice[j] != 0) for j in range(n)]
    return rotations, changed


def _triangle_quadrature() -> tuple[np.ndarray, np.ndarray]:
    """Collapsed 4×4 Gauss rule on the unit triangle: (xi, eta) points and weights summing
    to 1 (fraction of the triangle's area); exact for polynomials up to degree 6."""
    g, w = np.polynomial.legendre.leggauss(4)
    g, w = (g + 1.0) / 2.0, w / 2.0
    u, v = np.meshgrid(g, g, indexing="ij")
    weights = 2.0 * (np.outer(w, w) * (1.0 - u)).ravel()
    return np.stack([u.ravel(), (v * (1.0 - u)).ravel()], axis=1), weights


_QUAD_POINTS, _QUAD_WEIGHTS = _triangle_quadrature()


def _facing_signature(mesh: Mesh, rotation: np.ndarray) -> np.ndarray:
    """Odd part of a posed shape under a half turn about z, exact (no sampling noise):
    ∫ x P_b(ẑ) dA and ∫ y P_b(ẑ) dA over the surface for Legendre P_0..P_{FACING_ORDER-1}
    in the height ẑ ∈ [−1, 1], centred at the surface centroid, unit total variance.
    A half turn about z negates it; a shape symmetric under that turn has zero."""
    area, mean, cov = surface_moments(mesh)
    tri = (mesh.triangles - mean) @ rotation.T / np.sqrt(np.trace(cov))
    pts = (tri[:, None, 0]
           + _QUAD_POINTS[None, :, :1] * (tri[:, None, 1] - tri[:, None, 0])
           + _QUAD_POINTS[None, :, 1:] * (tri[:, None, 2] - tri[:, None, 0])).reshape(-1, 3)
    weights = (mesh.face_areas()[:, None] * _QUAD_WEIGHTS[None, :]).ravel() / area
    lo, hi = tri[..., 2].min(), tri[..., 2].max()
    height = 2.0 * (pts[:, 2] - lo) / max(hi - lo, 1e-12) - 1.0
    basis = np.polynomial.legendre.legvander(height, FACING_ORDER - 1)  # (n, order)
    return np.concatenate([(weights * pts[:, 0]) @ basis, (weights * pts[:, 1]) @ basis])


def _agree_on_facing(choice: np.ndarray, meshes, poses, movable=None) -> np.ndarray:
    """Flip shapes (those `movable`, default all) by a half turn about z (candidate
    k <-> k + 2) while that makes their facing signature agree better with the sum of
    everyone else's; at most 10 sweeps."""
    choice = choice.copy()
    n = len(choice)
    movable = np.ones(n, dtype=bool) if movable is None else movable
    signature = np.stack([_facing_signature(meshes[j], poses[j][choice[j]]) for j in range(n)])
    for _ in range(10):
        flipped = False
        for j in np.flatnonzero(movable):
            others = signature.sum(axis=0) - signature[j]
            if float(signature[j] @ others) < 0.0:
                choice[j] = 4 * (choice[j] // 4) + (choice[j] % 4 + 2) % 4
                signature[j] = -signature[j]
                flipped = True
        if not flipped:
            break
    return choice


def _prefer_own_pose(cost: np.ndarray, margin: float | None = None) -> int:
    """Index of the chosen candidate: the cheapest, unless the shape's own pose (candidate
    0), or else the same up direction with no quarter turn, is within CONSENSUS_MARGIN of
    it. Chamfer differences below that are sampling noise and shape variation (a vase's
    spout moves the cost by well under 1 %), where the sign rule is the better judge."""
    best = int(np.argmin(cost))
    limit = (1.0 + (CONSENSUS_MARGIN if margin is None else margin)) * cost[best]
    if cost[0] <= limit:
        return 0
    same_up = 4 * (best // 4)
    return same_up if cost[same_up] <= limit else best


def _mode(values: np.ndarray) -> int:
    """Most common value; ties go to the smallest (candidate 0 = keep the input's pose)."""
    counts = np.bincount(values)
    return int(np.argmax(counts))
