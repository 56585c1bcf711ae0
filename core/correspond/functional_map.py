"""Intrinsic, pose-invariant start of non-rigid ICP (**beyond** the thesis;
docs/method.md, "Intrinsic start").

Closest points cannot follow a limb that moved: the template's paw lands on whatever part
of the shape is nearest. Here the template is matched to a shape by the Laplace–Beltrami
eigenfunctions of both surfaces (core/geometry/spectral.py), which bending does not change.
A point map π (template vertex → shape vertex) and a functional map C (k × k: how the
shape's first k eigenfunctions read on the template, C = Φ_Tᵀ M_T Φ_S[π]) determine each
other; the steps:

1. **Coarse candidates.** For a near-isometry C is nearly orthogonal and, at low
   frequencies, nearly block-diagonal. Two sources of candidates for its first few rows:
   the sign patterns of the first SIGN_FUNCTIONS non-constant eigenfunctions (an
   eigenfunction is known up to its sign) whose point maps best match the wave kernel
   signatures (a pose-invariant description of every point's neighbourhood at many
   scales); and orthogonal Procrustes fits of the signatures' spectral coefficients, one
   block per run of close eigenvalues (whose eigenfunctions may swap or mix between two
   shapes), with the directions the signatures say least about tried both ways.
2. **Orientation and facing** (map_orientation.py). A body is nearly symmetric left–right
   and, at low frequencies, front–back, so the map's left–right mirror, its front–back
   flip and both at once (a half turn) match the signatures about as well as the map
   itself. Every candidate is refined by ZoomOut to ORIENTATION_FUNCTIONS and kept only
   when it keeps the surface's orientation by the orientation-preserving term of Ren et
   al. 2018 (BCICP: the operator ⟨n, ∇f × ∇·⟩ of corresponding descriptors f commutes
   with C; a mirror or a flip reverses its sign; `orientation_score` above
   MIN_ORIENTATION) and, where template and shape lie in a frame the collection shares
   (`shared_frame`: Prepare's), when it keeps their facing (`facing_agreement` above
   MIN_FACING: no half turn). There, closest points in that frame give one more
   candidate. Among the kept, the one whose operators commute best (the highest score)
   wins: measured on TOSCA, choosing the least signature error instead left dog and cat
   0.3 points worse, the centaur 0.7 better. Where none passes, the caller reaches the shape through others
   (start.relayed_starts, `relayed_map`) and, last, by the share of template triangles
   whose images face out (`by_triangles`, `triangle_share`).
3. **ZoomOut** (Melzi et al. 2019): C is re-estimated from the point map and the point map
   from C with more eigenfunctions each time (one at a time up to FINE_FUNCTIONS, where
   the map's layout is decided, then FINE_STEP), from a few (smooth, pose-free) to
   ZOOM_FUNCTIONS, so the map gets finer without leaving the coarse map's basin. Each C
   is projected to the nearest orthogonal matrix (`functional_map`). C is estimated on
   a mass-weighted sample of the template's vertices, matched into a sample of the
   shape's, which keeps a 5k-vertex pair to about a second; the landmarks are matched
   into all of the shape's vertices.
4. The template's landmarks are carried to the shape by the final map (each by its nearest
   template vertex); non-rigid ICP then starts from there (groupwise.py).

Where the spectrum cannot be trusted the start says so and the caller falls back to closest
points: a mesh whose largest part holds less than MIN_PART_SHARE of its area (the low
eigenfunctions then describe how parts are split, not shape), an eigen-solve that fails, no
map that passes the tests nor the last resort."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.spectral import Spectrum, SpectrumError, laplace_beltrami_spectrum, wave_kernel_signature
from .map_orientation import DESCRIPTOR_CHANNELS, DESCRIPTOR_FUNCTIONS, facing_agreement, orientation_operators, \
    orientation_score

__all__ = ["SpectralShape", "SpectralStart", "spectral_shape", "spectral_start", "spectral_map", "relayed_map",
           "shape_operators", "triangle_share", "zoom_out", "SPECTRUM_SIZE"]

#: eigenpairs computed per shape; ZoomOut ends at ZOOM_FUNCTIONS of them
SPECTRUM_SIZE = 40
ZOOM_FUNCTIONS = 40
#: the coarse maps C are COARSE_FUNCTIONS square; consecutive eigenvalues within BLOCK_RATIO
#: form one block of C; the AMBIGUOUS_DIRECTIONS directions the signatures say least about
#: are tried both ways (2^AMBIGUOUS_DIRECTIONS candidates), each refined to
#: ORIENTATION_FUNCTIONS and tested for orientation
COARSE_FUNCTIONS = 8
BLOCK_RATIO = 1.2
AMBIGUOUS_DIRECTIONS = 2
#: and the SIGN_CANDIDATES best sign patterns of the first SIGN_FUNCTIONS non-constant ones
SIGN_FUNCTIONS = 6
SIGN_CANDIDATES = 3
ORIENTATION_FUNCTIONS = 16
#: ZoomOut adds one eigenfunction per step up to FINE_FUNCTIONS, then FINE_STEP per step
FINE_FUNCTIONS = 20
FINE_STEP = 3
#: the final ZoomOut estimates C on SAMPLE_VERTICES template vertices (a mass-weighted
#: sample: C is an integral over the template) matched into SHAPE_VERTICES of the shape's;
#: sign patterns are scored on SEARCH_VERTICES; candidates are refined (TRIAL_STEP
#: eigenfunctions per step) and compared on TRIAL_VERTICES matched into TRIAL_TARGETS
SAMPLE_VERTICES = 1500
SHAPE_VERTICES = 2500
SEARCH_VERTICES = 400
TRIAL_VERTICES = 1000
TRIAL_TARGETS = 2000
TRIAL_STEP = 2
#: the last resort where no map passes those tests (poses too far apart for the descriptors
#: to correspond, a shape Prepare turned without a flag): a map keeps the orientation when
#: the images of more than this share of ORIENTATION_FACES template triangles face the way
#: the shape's normals do (the test used before the operator's; it held on the TOSCA
#: animals, mirrors at 0.25–0.37, but not between different people)
MIN_TRIANGLE_SHARE = 0.6
ORIENTATION_FACES = 600
#: the best kept candidates taken through the final ZoomOut in turn until one still passes
FINAL_TRIES = 2
#: the closest-point candidate (shared frame) enters ZoomOut at this many eigenfunctions
EXTRINSIC_FUNCTIONS = 4
#: the largest part must hold at least this share of a mesh's area
MIN_PART_SHARE = 0.9
#: a map keeps the orientation when its `orientation_score` exceeds this (measured on TOSCA
#: people at ORIENTATION_FUNCTIONS: right maps +0.37 to +1, mirrors and flips −0.5 to −1,
#: maps right on some parts and mirrored on others −0.5 to +0.5; 0.5 left the man whose
#: right map scored +0.37 to closest points, 8 % of the diagonal off)
MIN_ORIENTATION = 0.3
#: and its facing when its `facing_agreement` exceeds this (a turn of less than 90°; half
#: turns measured at −0.9 to −1, right maps +0.65 to +1)
MIN_FACING = 0.0
#: log-energies of the wave kernel signature
SIGNATURE_ENERGIES = 40


@dataclass(frozen=True)
class SpectralShape:
    """A mesh with what matching needs of it: its spectrum (on its largest part), the wave
    kernel signature and the vertex normals of that part."""

    vertices: np.ndarray  # (n, 3) the part's vertices (the mesh's own coordinates)
    spectrum: Spectrum
    signature: np.ndarray  # (n, SIGNATURE_ENERGIES)
    normals: np.ndarray  # (n, 3) area-weighted vertex normals

    @property
    def faces(self) -> np.ndarray:
        return self.spectrum.faces


def spectral_shape(vertices: np.ndarray, faces: np.ndarray, k: int = SPECTRUM_SIZE) -> SpectralShape:
    """The spectrum, signature and normals of a mesh; raises SpectrumError (module
    docstring) when its largest part is too small a share of it or the solve fails."""
    spectrum = laplace_beltrami_spectrum(vertices, faces, k)
    if spectrum.largest_part_share < MIN_PART_SHARE:
        raise SpectrumError(f"its largest of {spectrum.parts} parts holds {100 * spectrum.largest_part_share:.0f} % "
                            f"of the area (at least {100 * MIN_PART_SHARE:.0f} % needed)")
    points = np.asarray(vertices, dtype=np.float64)[spectrum.vertices]
    corners = points[spectrum.faces]
    face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # area-weighted
    normals = np.zeros_like(points)
    for corner in range(3):
        np.add.at(normals, spectrum.faces[:, corner], face_normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    return SpectralShape(points, spectrum, wave_kernel_signature(spectrum, SIGNATURE_ENERGIES), normals)


@dataclass(frozen=True)
class SpectralStart:
    """Where the template's landmarks start on one shape, or why the spectrum was not trusted."""

    points: np.ndarray | None  # (L, 3) in the shape's coordinates; None: fall back to closest points
    message: str  # what was done or why not (per-shape message of the correspondence)
    normals: np.ndarray | None = None  # (L, 3) the shape's vertex normals there
    orientation: float = float("nan")  # the map's orientation score (map_orientation.py: +1 kept, −1 reversed)
    signature_error: float = float("nan")  # mean signature distance of matched points
    signature_vertices: np.ndarray | None = None  # (n, 3) the shape's (part's) vertices, its coordinates
    signature: np.ndarray | None = None  # (n, E) their wave kernel signatures
    facing: float = float("nan")  # its facing agreement in the shared frame (NaN: no shared frame)
    c: np.ndarray | None = None  # the map (shape → template coefficients), for relays through this shape
    spectral: SpectralShape | None = None  # the shape's spectrum and descriptors, for relays to and through it


def landmark_signatures(template: SpectralShape, template_points: np.ndarray) -> np.ndarray:
    """(L, E) the signatures of the template's landmarks (at their nearest template vertex)."""
    return template.signature[cKDTree(template.vertices).query(np.asarray(template_points, dtype=np.float64))[1]]


def nearest_rows(queries: np.ndarray, rows: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Index of the nearest row of `rows` for every row of `queries` (Euclidean). In up to
    8 dimensions by a k-d tree; above, by blocks of squared distances in single precision
    (a dense product beats a tree in tens of dimensions; nearest neighbours of spectral
    coordinates need no more digits)."""
    if rows.shape[1] <= 8:
        return cKDTree(rows).query(queries)[1]
    queries, rows = queries.astype(np.float32), rows.astype(np.float32)
    norms = (rows**2).sum(axis=1)
    out = np.empty(len(queries), dtype=np.int64)
    for start in range(0, len(queries), chunk):
        block = queries[start:start + chunk]
        out[start:start + chunk] = np.argmin(norms[None, :] - 2.0 * block @ rows.T, axis=1)
    return out


def _sample(spectral: SpectralShape, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(vertex indices, weights) of a random vertex sample (seeded) whose weights integrate
    like the mesh's mass matrix (all vertices when it has at most `count`)."""
    mass = spectral.spectrum.mass
    if len(mass) <= count:
        return np.arange(len(mass)), mass
    chosen = np.random.default_rng(seed).choice(len(mass), count, replace=False)
    return chosen, mass[chosen] * (mass.sum() / mass[chosen].sum())


def functional_map(template: SpectralShape, shape: SpectralShape, sample: np.ndarray, weights: np.ndarray,
                   matches: np.ndarray, k: int) -> np.ndarray:
    """C (k × k): Φ_Tᵀ M_T Φ_S[π] over the sample — the shape's eigenfunction j, pulled back
    to the template by the point map π (`matches`: shape vertex of every sampled template
    vertex), in the template's eigenbasis (column j) — replaced by the nearest orthogonal
    matrix (U Vᵀ of its SVD). A near-isometry's C is orthogonal; a point map that sends
    many template points to one shape point (as the coarse maps of the first steps do)
    gives a rank-deficient C whose next point map collapses further, and the orthogonal
    projection stops that (measured: ZoomOut from the true cat map drifted to 6 % of the
    diagonal without it, 3 % with it)."""
    c = template.spectrum.vectors[sample, :k].T @ (weights[:, None] * shape.spectrum.vectors[matches, :k])
    u, _, vt = np.linalg.svd(c)
    return u @ vt


def point_map(template: SpectralShape, shape: SpectralShape, vertices: np.ndarray, c: np.ndarray,
              targets: np.ndarray | None = None) -> np.ndarray:
    """The point map of C: template vertex i goes to the shape vertex (among `targets`, all
    by default) whose k spectral coordinates are nearest Φ_T[i] C (a delta at i, carried by
    C, read on the shape)."""
    k = len(c)
    rows = shape.spectrum.vectors[:, :k] if targets is None else shape.spectrum.vectors[targets, :k]
    nearest = nearest_rows(template.spectrum.vectors[vertices, :k] @ c, rows)
    return nearest if targets is None else targets[nearest]


def zoom_out(template: SpectralShape, shape: SpectralShape, matches: np.ndarray, sample: np.ndarray,
             weights: np.ndarray, k_from: int, k_to: int, targets: np.ndarray | None = None, coarse_step: int = 1
             ) -> tuple[np.ndarray, np.ndarray]:
    """ZoomOut (Melzi et al. 2019): alternately C from the point map of the sample, then
    the point map from C, with k growing from `k_from` to `k_to` (by one up to
    FINE_FUNCTIONS: the coarse steps decide the map; by FINE_STEP beyond); matches go to
    `targets` (shape vertices; all by default). Returns (the sample's final matches, the
    last C)."""
    c = None
    schedule = sorted({*range(k_from, min(k_to, FINE_FUNCTIONS), coarse_step),
                       *range(max(k_from, FINE_FUNCTIONS), k_to, FINE_STEP), k_to})
    for k in schedule:
        c = functional_map(template, shape, sample, weights, matches, k)
        matches = point_map(template, shape, sample, c, targets)
    return matches, c


def shape_operators(spectral: SpectralShape, k: int) -> np.ndarray:
    """(d, k, k) the orientation operators (map_orientation.py) of a shape's descriptors on
    its first k eigenfunctions: the DESCRIPTOR_CHANNELS of its wave kernel signature,
    smoothed by projection onto its first DESCRIPTOR_FUNCTIONS eigenfunctions (the same
    band on both shapes, so they correspond). Measured: smoother descriptors (8
    eigenfunctions) separate the true map from TOSCA's standing dog to a sitting one from
    its mirror better (+0.73 against −0.73; +0.11 against −0.16 at 16) but let maps that
    are wrong in parts pass too (TOSCA centaur and horse lost 4–8 points of error)."""
    basis = spectral.spectrum.vectors[:, :k]
    smooth = min(DESCRIPTOR_FUNCTIONS, k)
    descriptors = spectral.spectrum.vectors[:, :smooth] @ spectral.spectrum.project(
        spectral.signature[:, list(DESCRIPTOR_CHANNELS)], smooth)
    return orientation_operators(spectral.vertices, spectral.faces, basis, descriptors)


def _closest_in_frame(template: SpectralShape, shape: SpectralShape, vertices: np.ndarray, targets: np.ndarray
                      ) -> np.ndarray:
    """Shape vertex (among `targets`) nearest each template vertex of `vertices` in their
    shared frame, both centred on their mass centre and scaled to unit RMS radius."""
    def normalised(spectral: SpectralShape) -> np.ndarray:
        share = spectral.spectrum.mass / spectral.spectrum.mass.sum()
        centred = spectral.vertices - share @ spectral.vertices
        return centred / np.sqrt(share @ (centred**2).sum(axis=1))
    return targets[cKDTree(normalised(shape)[targets]).query(normalised(template)[vertices])[1]]


def triangle_share(template: SpectralShape, shape: SpectralShape, c: np.ndarray) -> float:
    """Area share of ORIENTATION_FACES template triangles (seeded) whose images under the
    point map of `c`, taken in the order of their corners, face the way the shape's
    normals do there (degenerate images do not vote): about 1 for a map that keeps the
    surface's orientation, about 0 for a mirror, when the map is right vertex by vertex."""
    voters = template.faces[np.random.default_rng(2).choice(len(template.faces), min(ORIENTATION_FACES,
                                                                                    len(template.faces)), replace=False)]
    corners, corner_index = np.unique(voters, return_inverse=True)
    triangle_images = point_map(template, shape, corners, c)[corner_index.reshape(voters.shape)]
    images = shape.vertices[triangle_images]  # (F, 3, 3)
    normal = np.cross(images[:, 1] - images[:, 0], images[:, 2] - images[:, 0])
    size = np.linalg.norm(normal, axis=1)
    agree = np.einsum("fd,fd->f", normal, shape.normals[triangle_images].sum(axis=1)) > 0
    voting = size > 0
    return float(size[voting & agree].sum() / size[voting].sum()) if voting.any() else float("nan")


def _signature_error(template: SpectralShape, shape: SpectralShape, sample: np.ndarray, weights: np.ndarray,
                     matches: np.ndarray) -> float:
    difference = template.signature[sample] - shape.signature[matches]
    return float(weights @ (difference**2).sum(axis=1) / weights.sum())


def _eigen_blocks(template_values: np.ndarray, shape_values: np.ndarray) -> list[np.ndarray]:
    """Runs of consecutive eigenvalues closer than BLOCK_RATIO on either shape: their
    eigenfunctions may swap or mix between the two shapes, so C is fitted per run."""
    blocks, current = [], [0]
    for j in range(1, len(template_values)):
        close = any(values[j] < BLOCK_RATIO * values[j - 1] for values in (template_values, shape_values))
        if close and j > 1:
            current.append(j)
        else:
            blocks.append(np.array(current))
            current = [j]
    blocks.append(np.array(current))
    return blocks


def _sign_candidates(template: SpectralShape, shape: SpectralShape, sample: np.ndarray, weights: np.ndarray,
                     k: int) -> list[np.ndarray]:
    """The SIGN_CANDIDATES diagonal coarse maps C = diag(±1) (k × k) whose point maps fit
    the signatures best: for a near-isometry without close eigenvalues C is nearly
    diagonal, each eigenfunction known up to its sign (the constant one keeps it). All
    2^(k−1) patterns are scored on the sample (a k-d tree of the shape's spectral
    coordinates)."""
    patterns = np.array(list(product((1.0, -1.0), repeat=k - 1)))  # (P, k − 1)
    rows = template.spectrum.vectors[sample, 1:k]
    _, matches = cKDTree(shape.spectrum.vectors[:, 1:k]).query((patterns[:, None, :] * rows[None]).reshape(-1, k - 1))
    difference = template.signature[sample][None] - shape.signature[matches.reshape(len(patterns), len(sample))]
    errors = (difference**2).sum(axis=2) @ weights
    return [np.diag(np.r_[1.0, patterns[p]]) for p in np.argsort(errors, kind="stable")[:SIGN_CANDIDATES]]


def _descriptor_candidates(template: SpectralShape, shape: SpectralShape, k: int) -> list[np.ndarray]:
    """Candidate coarse maps C (k × k). C should carry the shape's signatures onto the
    template's: C A_S ≈ A_T, A the signatures' coefficients on the first k eigenfunctions.
    Per run of close eigenvalues (`_eigen_blocks`) the best orthogonal C is the Procrustes
    solution U Vᵀ of A_T A_Sᵀ = U Σ Vᵀ. A direction whose singular value is small has no
    say from the signatures (an eigenfunction that is odd under the left–right mirror
    integrates to ~0 against every symmetric signature): the AMBIGUOUS_DIRECTIONS weakest
    are tried both ways, 2^AMBIGUOUS_DIRECTIONS candidates."""
    a_t = template.spectrum.project(template.signature, k)
    a_s = shape.spectrum.project(shape.signature, k)
    scale = np.linalg.norm(a_t) * np.linalg.norm(a_s)
    parts, strengths = [], []
    for block in _eigen_blocks(template.spectrum.values[:k], shape.spectrum.values[:k]):
        u, sigma, vt = np.linalg.svd(a_t[block] @ a_s[block].T)
        parts.append((block, u, vt))
        strengths.extend((sigma[i] / scale, len(parts) - 1, i) for i in range(len(block)))
    weakest = sorted(strengths)[:AMBIGUOUS_DIRECTIONS]
    candidates = []
    for flips in product((1.0, -1.0), repeat=len(weakest)):
        c = np.zeros((k, k))
        signs = [np.ones(len(block)) for block, _, _ in parts]
        for flip, (_, part, direction) in zip(flips, weakest):
            signs[part][direction] = flip
        for (block, u, vt), sign in zip(parts, signs):
            c[np.ix_(block, block)] = (u * sign) @ vt
        candidates.append(c)
    return candidates


@dataclass(frozen=True)
class _Tested:
    """A map C (shape → template coefficients) with the tests it is chosen by."""

    c: np.ndarray
    signature_error: float
    orientation: float
    facing: float

    def kept(self, shared_frame: bool) -> bool:
        return self.orientation > MIN_ORIENTATION and (not shared_frame or self.facing > MIN_FACING)

    def said(self, shared_frame: bool) -> str:
        return f"orientation {self.orientation:+.2f}" + (f", facing {self.facing:+.2f}" if shared_frame else "")


def _tested(template: SpectralShape, shape: SpectralShape, c: np.ndarray, matches: np.ndarray, sample: np.ndarray,
            weights: np.ndarray, operators: tuple[np.ndarray, np.ndarray], shared_frame: bool) -> _Tested:
    """`c` (k × k, k ≥ the operators' size) and the point map of `sample` it gave, tested."""
    k = operators[0].shape[1]
    facing = (facing_agreement(template.vertices[sample], shape.vertices[matches], weights) if shared_frame
              else float("nan"))
    return _Tested(c, _signature_error(template, shape, sample, weights, matches),
                   orientation_score(*operators, c[:k, :k]), facing)


def spectral_map(template: SpectralShape, shape: SpectralShape, shared_frame: bool = False,
                 by_triangles: bool = False) -> tuple[_Tested | None, str]:
    """The map from the template to the shape (C of ZOOM_FUNCTIONS, tested) or None, and
    what was done: coarse candidates, orientation and facing, ZoomOut (module docstring).
    `shared_frame`: template and shape lie in one frame that the collection shares
    (Prepare's), so their facing is evidence. The final map is tested again (ZoomOut may
    drift); the FINAL_TRIES kept candidates with the highest orientation scores are taken
    to the end in turn.
    `by_triangles`: the last resort (MIN_TRIANGLE_SHARE) instead of those tests."""
    sample, weights = _sample(template, SAMPLE_VERTICES)
    targets, _ = _sample(shape, SHAPE_VERTICES)
    trial, trial_weights = _sample(template, TRIAL_VERTICES, seed=3)
    trial_targets, _ = _sample(shape, TRIAL_TARGETS, seed=3)
    k_orient = min(ORIENTATION_FUNCTIONS, len(shape.spectrum.values), len(template.spectrum.values))
    operators = shape_operators(template, k_orient), shape_operators(shape, k_orient)
    search, search_weights = _sample(template, SEARCH_VERTICES, seed=1)
    starts = [(point_map(template, shape, trial, c, trial_targets), len(c) + 1)
              for c in (_sign_candidates(template, shape, search, search_weights, SIGN_FUNCTIONS + 1)
                        + _descriptor_candidates(template, shape, COARSE_FUNCTIONS))]
    if shared_frame:
        starts.append((_closest_in_frame(template, shape, trial, trial_targets), EXTRINSIC_FUNCTIONS))
    refined = []
    for matches, k_from in starts:
        matches, c = zoom_out(template, shape, matches, trial, trial_weights, k_from, k_orient, trial_targets,
                              TRIAL_STEP)
        refined.append(_tested(template, shape, c, matches, trial, trial_weights, operators, shared_frame))
    if by_triangles:
        shares = [triangle_share(template, shape, r.c) for r in refined]
        kept = [i for i, share in enumerate(shares) if share > MIN_TRIANGLE_SHARE]
        if not kept:
            return None, f"no spectral map keeps {100 * MIN_TRIANGLE_SHARE:.0f} % of the triangles facing out " \
                         f"either (the best {100 * max(shares):.0f} %)"
        best = min(kept, key=lambda i: refined[i].signature_error)
        chosen, share = refined[best], shares[best]
        matches, c = zoom_out(template, shape, point_map(template, shape, sample, chosen.c, targets), sample, weights,
                              k_orient, min(ZOOM_FUNCTIONS, len(shape.spectrum.values), len(template.spectrum.values)),
                              targets)
        return (_tested(template, shape, c, matches, sample, weights, operators, False),
                f"spectral start by the triangles' orientation ({100 * share:.0f} % facing out)")
    kept = sorted((r for r in refined if r.kept(shared_frame)), key=lambda r: -r.orientation)
    tests = "orientation" + " and the facing" * shared_frame
    if not kept:
        best = max(refined, key=lambda r: r.orientation + (r.facing if shared_frame else 0.0))
        return None, f"no spectral map that keeps the {tests} among {len(refined)} candidates " \
                     f"(the best: {best.said(shared_frame)})"
    k_end = min(ZOOM_FUNCTIONS, len(shape.spectrum.values), len(template.spectrum.values))
    for chosen in kept[:FINAL_TRIES]:
        matches, c = zoom_out(template, shape, point_map(template, shape, sample, chosen.c, targets), sample, weights,
                              k_orient, k_end, targets)
        final = _tested(template, shape, c, matches, sample, weights, operators, shared_frame)
        if final.kept(shared_frame):
            return final, f"spectral start ({final.said(shared_frame)})"
    return None, f"the spectral map lost the {tests} on refinement ({final.said(shared_frame)})"


def relayed_map(template: SpectralShape, via: SpectralShape, via_map: np.ndarray, shape: SpectralShape,
                shared_frame: bool = False) -> tuple[_Tested | None, str]:
    """The map from the template to the shape through another shape of the collection
    (`via`, whose map from the template `via_map` passed the tests): the via → shape map
    (`spectral_map`) composed with it (C_T←S = C_T←V C_V←S: pull back twice), then
    ZoomOut on the template and the shape from ORIENTATION_FUNCTIONS (the composition's
    errors add; refining on the pair itself removes them) and tested again."""
    second, message = spectral_map(via, shape, shared_frame)
    if second is None:
        return None, message
    k = min(len(via_map), len(second.c))
    sample, weights = _sample(template, SAMPLE_VERTICES)
    targets, _ = _sample(shape, SHAPE_VERTICES)
    k_orient = min(ORIENTATION_FUNCTIONS, k)
    matches = point_map(template, shape, sample, via_map[:k, :k] @ second.c[:k, :k], targets)
    matches, c = zoom_out(template, shape, matches, sample, weights, k_orient, k, targets)
    operators = shape_operators(template, k_orient), shape_operators(shape, k_orient)
    final = _tested(template, shape, c, matches, sample, weights, operators, shared_frame)
    if not final.kept(shared_frame):
        return None, f"the relayed map does not keep the orientation{' and the facing' * shared_frame} " \
                     f"({final.said(shared_frame)})"
    return final, f"spectral start through {{via}} ({final.said(shared_frame)})"


def spectral_start(template: SpectralShape, template_points: np.ndarray, shape: SpectralShape,
                   shared_frame: bool = False, via: tuple[str, SpectralShape, np.ndarray] | None = None,
                   by_triangles: bool = False) -> SpectralStart:
    """Where the template's landmarks (`template_points`, (L, 3) on the template's surface,
    in its coordinates) start on the shape, by `spectral_map` (or, with `via` = (name,
    shape, its map from the template), by `relayed_map`; `by_triangles`: the last
    resort of `spectral_map`). Points are returned in the
    shape's coordinates (at its vertices); `SpectralStart.c` holds the map."""
    if via is None:
        found, message = spectral_map(template, shape, shared_frame, by_triangles)
    else:
        found, message = relayed_map(template, via[1], via[2], shape, shared_frame)
        message = message.replace("{via}", via[0])
    if found is None:
        return SpectralStart(None, message, spectral=shape)
    _, nearest = cKDTree(template.vertices).query(np.asarray(template_points, dtype=np.float64))
    landmark_matches = point_map(template, shape, nearest, found.c)
    return SpectralStart(shape.vertices[landmark_matches], message, shape.normals[landmark_matches],
                         found.orientation, found.signature_error, shape.vertices, shape.signature, found.facing,
                         found.c, shape)
