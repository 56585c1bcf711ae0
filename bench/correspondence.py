"""Correspondence benchmark: quality against ground truth, speed, and peers.

    python bench/correspondence.py [--quick]

Writes bench_output/correspondence.{json,txt}. Not part of the tests. Three parts:

1. Procedural vases (core/demo_data/, 5k–30k-vertex targets, varied triangulations):
   true error = mean distance landmark → ground-truth point / bounding-box diagonal, and
   time per shape, for: ours (groupwise); ours pairwise; without the bidirectional term;
   one α (no relaxation); snapping to vertices; no normal compatibility (the thesis's
   plain closest points); naive (bounding-box scaling + closest point); trimesh's
   nricp_amberg on the same pairs. Two error measures: "vs template" (landmark i must sit
   at the template landmark's surface coordinates (s, θ)), and "consensus" (landmark i must
   sit at the same (s, θ) on every shape; does not penalise moving away from the template,
   which groupwise re-estimation does by design).
2. 131 vases (the thesis's count), 800 landmarks, groupwise, 2 processes: wall time.
3. PSB (psb/* of the real collections, tests/shared_data.py; up axis y): label-transfer
   accuracy = share of landmarks whose
   part label matches the reference (template) shape's, and time per shape.

Parts 1 and 3 also measure the model quality of the landmarks (PPCA held-out
log-likelihood, Table 5.1 completion error, 5 folds). (Groupwise refinement after NICP had
rows and ablations here until it was removed: it won no class beyond run-to-run noise,
docs/results.md; the code before its removal is in git.)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes  # noqa: E402
from shapegen_core.correspond import (Anchors, CorrespondenceSettings, RegistrationProblem, correspond,  # noqa: E402
                                      register)
from shapegen_core.correspond.settings import DataTermSettings, IterationSettings, StiffnessSettings  # noqa: E402
from shapegen_core.evaluation.completion import hidden_coordinates, region_mask  # noqa: E402
from shapegen_core.evaluation.protocol import heldout_folds  # noqa: E402
from shapegen_core.models.ppca import PPCA  # noqa: E402
from shapegen_core.demo_data import PROFILE_BREAKS, make_vases  # noqa: E402
# face_labels: other benches import it from here
from psb_labels import face_labels  # noqa: E402
from shapegen_core.geometry import (AffineSolver, TargetSurface, data_blocks, knn_graph,  # noqa: E402
                                    registration_frame, stiffness_energy)
from shapegen_core.meshes.reading import read_folder  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUTPUT = ROOT / "bench_output"
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections
from shared_data import folder_or_exit  # noqa: E402

LANDMARKS = 800


# ---------------------------------------------------------------------------- errors
def error_vs_template(shapes, template_index, template_landmarks, points_input) -> np.ndarray:
    """Per shape: mean |p_i − shape point at the template landmark's (s, θ)| / diagonal."""
    st = shapes[template_index].surface_coordinates(template_landmarks.face_index, template_landmarks.barycentric)
    return np.array([np.linalg.norm(points_input[m] - shapes[m].points_at(st), axis=1).mean()
                     / shapes[m].mesh.bbox_diagonal() for m in range(len(shapes))])


def error_consensus(shapes, face_index, barycentric, points_input) -> np.ndarray:
    """Per shape: mean |p_i − shape point at landmark i's consensus (s, θ)| / diagonal.
    The consensus is robust: the median s, and θ the circular mean moved by the median
    wrapped deviation (one shape with a flipped landmark must not move everyone's)."""
    st = np.stack([shapes[m].surface_coordinates(face_index[m], barycentric[m]) for m in range(len(shapes))])
    mean_theta = np.angle(np.exp(1j * st[:, :, 1]).mean(axis=0))
    deviation = np.angle(np.exp(1j * (st[:, :, 1] - mean_theta)))
    consensus = np.stack([np.median(st[:, :, 0], axis=0), mean_theta + np.median(deviation, axis=0)], axis=1)
    return np.array([np.linalg.norm(points_input[m] - shapes[m].points_at(consensus), axis=1).mean()
                     / shapes[m].mesh.bbox_diagonal() for m in range(len(shapes))])


PARTS = ("base", "outer wall", "rim", "inner wall", "floor")


def decompose(shapes, template_index, template_landmarks, face_index, barycentric) -> dict:
    """Where the vs-template error comes from (shapes other than the template, % of the
    diagonal): the profile part (landmark moved to its true θ, keeping its s) and the
    angular part (true s, its θ); the mean error per surface part (PROFILE_BREAKS, by the
    true s); and the median signed θ error (a rotation about the vase axis shows here).
    The sections use the eccentric angle (core/demo_data/), so an affine map between
    two sections keeps θ: the angular ground truth is affine-consistent by construction."""
    t = template_index
    st_true = shapes[t].surface_coordinates(template_landmarks.face_index, template_landmarks.barycentric)
    part = np.clip(np.searchsorted(PROFILE_BREAKS, st_true[:, 0], side="right") - 1, 0, len(PARTS) - 1)
    out = {"total": [], "profile (s)": [], "angle (θ)": [], "median signed Δθ (deg)": []}
    per_part = []
    for m, shape in enumerate(shapes):
        if m == t:
            continue
        diagonal = shape.mesh.bbox_diagonal()
        truth = shape.points_at(st_true)
        st = shape.surface_coordinates(face_index[m], barycentric[m])
        error = lambda pts: np.linalg.norm(pts - truth, axis=1) / diagonal  # noqa: E731
        total = error(shape.points_at(st))
        out["total"].append(100 * total.mean())
        out["profile (s)"].append(100 * error(shape.points_at(np.c_[st[:, 0], st_true[:, 1]])).mean())
        out["angle (θ)"].append(100 * error(shape.points_at(np.c_[st_true[:, 0], st[:, 1]])).mean())
        out["median signed Δθ (deg)"].append(float(np.degrees(np.median(np.angle(np.exp(1j * (st[:, 1] - st_true[:, 1])))))))
        per_part.append([100 * total[part == k].mean() if (part == k).any() else np.nan for k in range(len(PARTS))])
    summary = {k: float(np.mean(v)) for k, v in out.items()}
    summary["per part"] = dict(zip(PARTS, np.nanmean(np.array(per_part), axis=0).tolist()))
    summary["landmark share per part"] = dict(zip(PARTS, [float(np.mean(part == k)) for k in range(len(PARTS))]))
    return summary


# ---------------------------------------------------------------------------- methods (pairwise)
class PairwiseFrame:
    """The template's landmarks, k-NN graph and normals in its registration frame (zero
    mean, unit RMS radius), and `register` of that template onto any shape of `prepared`."""

    def __init__(self, prepared, template_index: int, k_neighbours: int):
        lm = prepared.landmarks[template_index]
        self.prepared = prepared
        self.centre, self.scale = registration_frame(lm.points)
        self.template = self.frame(lm.points)
        self.edges = knn_graph(lm.points, k_neighbours)
        self.normals = prepared.shapes[template_index].mesh.face_normals()[lm.face_index]

    def frame(self, points) -> np.ndarray:
        return (np.asarray(points) - self.centre) / self.scale

    def surface(self, m: int) -> TargetSurface:
        mesh = self.prepared.shapes[m].mesh
        return TargetSurface(self.frame(mesh.vertices), mesh.faces)

    def register(self, m: int, settings, surface: TargetSurface | None = None, **options):
        """Template → shape m (`options`: register's anchors, initial_points)."""
        mesh, target_lm = self.prepared.shapes[m].mesh, self.prepared.landmarks[m]
        return register(RegistrationProblem(self.template, self.edges, surface or self.surface(m),
                                            self.frame(target_lm.points), settings, self.normals,
                                            mesh.face_normals()[target_lm.face_index], **options))


def pairwise(**groups) -> CorrespondenceSettings:
    """Pairwise registration (no groupwise round) with the given settings groups."""
    return CorrespondenceSettings(groupwise_rounds=0, **groups)


def ours_pairwise(prepared, template_index, settings):
    """Register the template to every shape; returns (points, face, bary, seconds per shape)."""
    pair = PairwiseFrame(prepared, template_index, settings.stiffness.k_neighbours)
    points, faces, barys = [], [], []
    start = time.perf_counter()
    for m in range(len(prepared)):
        result = pair.register(m, settings)
        points.append(result.placed.points * pair.scale + pair.centre)
        faces.append(result.placed.face_index)
        barys.append(result.placed.barycentric)
    seconds = (time.perf_counter() - start) / len(prepared)
    return np.stack(points), np.stack(faces), np.stack(barys), seconds


def naive_baseline(prepared, template_index):
    """Bounding-box scaling of the template landmarks onto each shape + closest point."""
    lm = prepared.landmarks[template_index]
    lo, hi = prepared.shapes[template_index].mesh.bounds()
    points, faces, barys = [], [], []
    start = time.perf_counter()
    for shape in prepared.shapes:
        tlo, thi = shape.mesh.bounds()
        moved = tlo + (lm.points - lo) * (thi - tlo) / (hi - lo)
        placed = TargetSurface(shape.mesh.vertices, shape.mesh.faces).closest(moved)
        points.append(placed.points)
        faces.append(placed.face_index)
        barys.append(placed.barycentric)
    seconds = (time.perf_counter() - start) / len(prepared)
    return np.stack(points), np.stack(faces), np.stack(barys), seconds


def nricp_baseline(prepared, template_index, targets):
    """trimesh.registration.nricp_amberg deforming the template mesh onto each target;
    landmarks follow their triangle (barycentrics), then go to the closest target point."""
    import trimesh
    from trimesh.registration import nricp_amberg

    template = prepared.shapes[template_index].mesh
    lm = prepared.landmarks[template_index]
    source = trimesh.Trimesh(template.vertices, template.faces, process=False)
    out = {}
    for m in targets:
        mesh = prepared.shapes[m].mesh
        target = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        start = time.perf_counter()
        deformed = nricp_amberg(source, target)
        moved = np.einsum("nk,nkd->nd", lm.barycentric, deformed[template.faces[lm.face_index]])
        placed = TargetSurface(mesh.vertices, mesh.faces).closest(moved)
        out[m] = (placed.points, placed.face_index, placed.barycentric, time.perf_counter() - start)
    return out


# ---------------------------------------------------------------------------- why the error stays high
def pinned_stiffness_energy(template_points, edges, positions, settings, weight: float = 1e3) -> float:
    """E_s (4.27) of the affines that carry every template point to `positions` (pinned by
    a data weight far above α², at the last α of the schedule): how much the NICP
    objective dislikes a given correspondence, whatever the optimiser does."""
    n = len(template_points)
    blocks, rhs = data_blocks(template_points, np.arange(n), positions, np.full(n, weight), n)
    affines = AffineSolver(edges, n, settings.stiffness.gamma).solve(settings.alphas[-1], blocks, rhs)
    return stiffness_energy(affines, edges, settings.stiffness.gamma)


def objective_diagnosis(shapes, prepared, template_index, log, band: float = 0.03) -> dict:
    """Two measurements of whether the NICP objective itself can reach the ground truth
    (pairwise, template → every other shape, registration frame):

    * stiffness energy of our correspondence vs of the ground truth, each pinned exactly;
      truth / ours > 1 means the method's objective prefers what it found;
    * an oracle: the landmarks at the belly and neck (wall coordinate within `band` of 1/3
      and 2/3, the smooth features) get their TRUE positions as `Anchors` (weight 1000):
      the error that remains is what NICP's smooth interpolation between perfectly placed
      features costs;
    * started AT the ground truth (`initial_points`), 30 iterations at the last α (and at
      α = 1): how far the method walks away from the truth on its own."""
    settings = CorrespondenceSettings(groupwise_rounds=0)
    pair = PairwiseFrame(prepared, template_index, settings.stiffness.k_neighbours)
    template, edges = pair.template, pair.edges
    lm = prepared.landmarks[template_index]
    st = shapes[template_index].surface_coordinates(lm.face_index, lm.barycentric)
    b = PROFILE_BREAKS
    wall = np.where((st[:, 0] > b[1]) & (st[:, 0] < b[2]), (st[:, 0] - b[1]) / (b[2] - b[1]),
                    np.where((st[:, 0] > b[3]) & (st[:, 0] < b[4]), 1 - (st[:, 0] - b[3]) / (b[4] - b[3]), np.nan))
    anchored = (np.abs(wall - 1 / 3) < band) | (np.abs(wall - 2 / 3) < band)
    part = np.clip(np.searchsorted(PROFILE_BREAKS, st[:, 0], side="right") - 1, 0, len(PARTS) - 1)
    ratios, free_err, oracle_err, oracle_parts = [], [], [], []
    from_truth = {alpha: [] for alpha in (settings.alphas[-1], 1.0)}
    for m, shape in enumerate(prepared.shapes):
        if m == template_index:
            continue
        truth = pair.frame(shape.transform.to_normalised(shapes[m].points_at(st)))
        surface = pair.surface(m)
        free = pair.register(m, settings, surface).placed.points
        oracle = pair.register(m, settings, surface,
                               anchors=Anchors(np.flatnonzero(anchored), truth[anchored], 1e3)).placed.points
        ratios.append(pinned_stiffness_energy(template, edges, truth, settings)
                      / pinned_stiffness_energy(template, edges, free, settings))
        diagonal = shapes[m].mesh.bbox_diagonal() * shape.transform.scale / pair.scale  # input diagonal, frame units
        free_err.append(100 * np.linalg.norm(free - truth, axis=1)[~anchored].mean() / diagonal)
        error = np.linalg.norm(oracle - truth, axis=1) / diagonal
        oracle_err.append(100 * error[~anchored].mean())
        oracle_parts.append([100 * error[part == k].mean() for k in range(len(PARTS))])
        for alpha, errors in from_truth.items():
            stay = CorrespondenceSettings(
                groupwise_rounds=0, stiffness=StiffnessSettings(alpha_start=alpha, alpha_end=alpha, alpha_steps=1),
                iterations=IterationSettings(tolerance=0.0, max_iterations_per_alpha=30, max_iterations=30))
            walked = pair.register(m, stay, surface, initial_points=truth).placed.points
            errors.append(100 * np.linalg.norm(walked - truth, axis=1).mean() / diagonal)
    out = {"energy_truth_over_ours": [float(r) for r in ratios], "anchored_landmarks": int(anchored.sum()),
           "unanchored_error_free_pct": float(np.mean(free_err)), "unanchored_error_oracle_pct": float(np.mean(oracle_err)),
           "oracle_error_per_part_pct": dict(zip(PARTS, np.mean(oracle_parts, axis=0).tolist())),
           "started_at_truth_error_pct": {f"alpha {a:g}": float(np.mean(e)) for a, e in from_truth.items()}}
    log(f"objective check (pairwise): stiffness energy of the ground truth / of ours = "
        + ", ".join(f"{r:.1f}" for r in ratios) + " (> 1: NICP's objective prefers ours)")
    log(f"oracle: {int(anchored.sum())} belly/neck landmarks anchored at their TRUE positions: error of the other "
        f"landmarks {np.mean(oracle_err):.2f} % (free {np.mean(free_err):.2f} %); per part "
        + ", ".join(f"{k} {v:.2f}" for k, v in out["oracle_error_per_part_pct"].items()))
    log("started at the ground truth, 30 iterations: error "
        + ", ".join(f"{k} → {v:.2f} %" for k, v in out["started_at_truth_error_pct"].items()))
    return out


# ---------------------------------------------------------------------------- model quality
def model_quality(landmark_matrix: np.ndarray, folds: int = 5, seed: int = 0, meshes=None) -> dict:
    """PPCA (80 % rule) on the landmark rows, k-fold: mean held-out log-likelihood per shape
    and the Table 5.1 completion error of the middle third along z (hidden landmarks chosen
    on the training mean), mean over held-out shapes (core/evaluation's protocol).

    Both compare landmarks with landmarks, so they reward a correspondence whose landmarks
    vary little, right or wrong (sliding along walls makes a population compact). With
    `meshes` (each shape's mesh in the landmarks' frame) also `completion_surface_pct`,
    which asks the held-out SURFACE instead: the completed hidden landmarks' mean distance
    to the held-out shape's surface and the shape's own hidden landmarks' mean distance to
    the nearest completed one, averaged, in % of its bounding-box diagonal. Two
    correspondences of the same shapes are compared on the same geometry."""
    Y = np.asarray(landmark_matrix, dtype=np.float64)
    scores, errors, surface = [], [], []
    for test in heldout_folds(len(Y), folds, seed):
        train = np.setdiff1d(np.arange(len(Y)), test)
        model = PPCA().fit(Y[train])
        scores.extend(model.log_likelihood(Y[test]))
        hidden_landmarks = region_mask(Y[train].mean(axis=0).reshape(-1, 3), "middle")
        hidden = hidden_coordinates(hidden_landmarks)
        observed = np.tile(~hidden, (len(test), 1))
        completed = model.complete(np.where(observed, Y[test], np.nan), observed)
        errors.extend(np.sum((completed[:, hidden] - Y[test][:, hidden]) ** 2, axis=1))
        if meshes is not None:
            for row, m in zip(completed, test):
                surface.append(completion_on_surface(row.reshape(-1, 3)[hidden_landmarks],
                                                     Y[m].reshape(-1, 3)[hidden_landmarks], meshes[m]))
    quality = {"heldout_log_likelihood": float(np.mean(scores)), "completion_error_middle": float(np.mean(errors))}
    if meshes is not None:
        quality["completion_surface_pct"] = float(np.mean(surface))
    return quality


def completion_on_surface(completed: np.ndarray, own: np.ndarray, mesh) -> float:
    """`model_quality`'s surface measure for one held-out shape: completed points (K, 3) to
    its surface and its own hidden landmarks `own` (K, 3) to the nearest completed point,
    mean distances averaged, in % of the mesh's bounding-box diagonal."""
    to_surface = TargetSurface(mesh.vertices, mesh.faces).closest(completed).distance.mean()
    to_completed = cKDTree(completed).query(own)[0].mean()
    return float(100 * (to_surface + to_completed) / 2 / mesh.bbox_diagonal())


# ---------------------------------------------------------------------------- part 1
def procedural(quick: bool, log) -> dict:
    n = 6 if quick else 16
    shapes = make_vases(n, seed=11, resolution=(65, 130))
    vertices = [s.mesh.n_vertices for s in shapes]
    log(f"\n== procedural vases: {n} shapes, {min(vertices)}–{max(vertices)} vertices, {LANDMARKS} landmarks")
    start = time.perf_counter()
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=LANDMARKS, seed=0))
    log(f"prepare: {time.perf_counter() - start:.1f} s")
    to_input = lambda pts: np.stack([s.transform.to_input(p) for s, p in zip(prepared.shapes, pts)])  # noqa: E731

    start = time.perf_counter()
    group = correspond(prepared, CorrespondenceSettings(), jobs=1)
    group_seconds = (time.perf_counter() - start) / n
    t = group.names.index(group.template_name)
    template_lm = prepared.landmarks[t]
    rows = {}

    def record(name, points, faces, barys, seconds):
        pin = to_input(points)
        vs = error_vs_template(shapes, t, template_lm, pin)
        cons = error_consensus(shapes, faces, barys, pin)
        rows[name] = {"error_vs_template_pct": 100 * float(vs.mean()), "error_consensus_pct": 100 * float(cons.mean()),
                      "seconds_per_shape": float(seconds)}
        log(f"{name:34s} vs-template {100 * vs.mean():6.3f} %   consensus {100 * cons.mean():6.3f} %   "
            f"{seconds:7.2f} s/shape")

    record("ours (groupwise, jobs=1)", group.points, group.face_index, group.barycentric, group_seconds)
    variants = {
        "ours pairwise": CorrespondenceSettings(groupwise_rounds=0),
        "- bidirectional term (λ=0)": pairwise(data_term=DataTermSettings(bidirectional_weight=0.0)),
        "- relaxation (one α = 5)": pairwise(stiffness=StiffnessSettings(alpha_steps=1)),
        "- surface (snap to vertices)": pairwise(data_term=DataTermSettings(snap_to_vertices=True)),
        "- normals (plain closest points)": pairwise(data_term=DataTermSettings(normal_max_angle=None)),
        "thesis Alg. 3 (update_template)": pairwise(iterations=IterationSettings(update_template=True)),
    }
    for name, settings in variants.items():
        record(name, *ours_pairwise(prepared, t, settings))
    naive_points = naive_baseline(prepared, t)
    record("naive (bbox + closest point)", *naive_points)

    diagnosis = {"ours (groupwise)": decompose(shapes, t, template_lm, group.face_index, group.barycentric),
                 "naive": decompose(shapes, t, template_lm, naive_points[1], naive_points[2])}
    log("error decomposition (vs template, % of the diagonal, shapes other than the template):")
    for name, d in diagnosis.items():
        log(f"  {name:18s} total {d['total']:.3f}: profile (s) part {d['profile (s)']:.3f}, angle (θ) part "
            f"{d['angle (θ)']:.3f}, median signed Δθ {d['median signed Δθ (deg)']:+.2f}°; per part "
            + ", ".join(f"{k} {v:.2f}" for k, v in d["per part"].items()))
    d = diagnosis["ours (groupwise)"]
    log("  landmark share per part: "
        + ", ".join(f"{k} {100 * v:.0f} %" for k, v in d["landmark share per part"].items()))

    pairs = [m for m in range(n) if m != t][: (2 if quick else 4)]
    log(f"nricp_amberg on {len(pairs)} pairs (template {prepared.shapes[t].mesh.n_vertices} vertices) ...")
    theirs = nricp_baseline(prepared, t, pairs)
    ours_same = ours_pairwise(prepared, t, CorrespondenceSettings(groupwise_rounds=0))
    st = shapes[t].surface_coordinates(template_lm.face_index, template_lm.barycentric)
    err = lambda m, p: np.linalg.norm(prepared.shapes[m].transform.to_input(p) - shapes[m].points_at(st), axis=1).mean() / shapes[m].mesh.bbox_diagonal()  # noqa: E731
    nricp_err = np.mean([err(m, theirs[m][0]) for m in pairs])
    nricp_time = np.mean([theirs[m][3] for m in pairs])
    ours_err = np.mean([err(m, ours_same[0][m]) for m in pairs])
    rows["nricp_amberg (same pairs)"] = {"error_vs_template_pct": 100 * float(nricp_err), "seconds_per_shape": float(nricp_time)}
    rows["ours pairwise (same pairs)"] = {"error_vs_template_pct": 100 * float(ours_err), "seconds_per_shape": float(ours_same[3])}
    log(f"{'nricp_amberg (same pairs)':34s} vs-template {100 * nricp_err:6.3f} %   {nricp_time:7.2f} s/shape")
    log(f"{'ours pairwise (same pairs)':34s} vs-template {100 * ours_err:6.3f} %   {ours_same[3]:7.2f} s/shape")

    naive = rows["naive (bbox + closest point)"]["error_vs_template_pct"]
    ours = rows["ours (groupwise, jobs=1)"]
    ratios = {
        "speedup_vs_nricp": float(nricp_time / ours_same[3]),
        "error_ratio_nricp_over_ours": float(nricp_err / ours_err),
        "naive_over_ours_vs_template": float(naive / ours["error_vs_template_pct"]),
        "naive_over_ours_consensus": float(rows["naive (bbox + closest point)"]["error_consensus_pct"] / ours["error_consensus_pct"]),
    }
    log("ratios: " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()))
    log(f"targets: ≤ 1 s/shape (ours pairwise {ours_same[3]:.2f} s); ≥ 20× nricp ({ratios['speedup_vs_nricp']:.1f}×) "
        f"at ≤ its error ({ratios['error_ratio_nricp_over_ours']:.2f}); error ≤ 0.4 % "
        f"({ours['error_vs_template_pct']:.2f} %); ≥ 4× below naive ({ratios['naive_over_ours_vs_template']:.2f}×)")
    objective = objective_diagnosis(shapes, prepared, t, log)
    quality = model_quality(group.landmark_matrix())
    log_quality("procedural", quality, log)
    return {"shapes": n, "vertices": [min(vertices), max(vertices)], "methods": rows, "ratios": ratios,
            "outliers": int(group.outliers.sum()), "diagnosis": diagnosis, "objective": objective,
            "model_quality": quality}


def log_quality(label: str, quality: dict, log) -> None:
    log(f"{label}: PPCA held-out log-likelihood / shape {quality['heldout_log_likelihood']:.1f}; completion error "
        f"(middle third) {quality['completion_error_middle']:.4g}")


# ---------------------------------------------------------------------------- part 2
def collection_timing(quick: bool, log) -> dict:
    n = 30 if quick else 131
    shapes = make_vases(n, seed=21)
    start = time.perf_counter()
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=LANDMARKS, seed=0))
    prepare_seconds = time.perf_counter() - start
    start = time.perf_counter()
    result = correspond(prepared, CorrespondenceSettings(), jobs=2)
    seconds = time.perf_counter() - start
    load = os.getloadavg()[0]
    log(f"\n== {n} vases, {LANDMARKS} landmarks, groupwise, 2 processes: correspond {seconds:.1f} s "
        f"(target ≤ 120 s for 131), prepare {prepare_seconds:.1f} s, outliers {int(result.outliers.sum())}; "
        f"load average {load:.1f}")
    return {"shapes": n, "correspond_seconds": seconds, "prepare_seconds": prepare_seconds,
            "outliers": int(result.outliers.sum()), "load_average": load}


# ---------------------------------------------------------------------------- part 3
def psb(quick: bool, log) -> dict:
    out = {}
    landmarks = 400 if quick else LANDMARKS
    log(f"\n== PSB label transfer ({landmarks} landmarks, groupwise, 2 processes)")
    for folder in sorted(p for p in folder_or_exit("psb").iterdir() if p.is_dir()):
        meshes = read_folder(folder)
        if quick:
            meshes = meshes[:8]
        labels = {m.name: face_labels(folder / f"{m.name}.off", m) for m in meshes}
        prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=landmarks, up_axis="y", seed=0))
        start = time.perf_counter()
        result = correspond(prepared, CorrespondenceSettings(), jobs=2)
        seconds = (time.perf_counter() - start) / len(meshes)
        ref = result.names.index(result.template_name)
        ref_labels = labels[result.template_name][result.face_index[ref]]
        accuracy = [np.mean(labels[name][result.face_index[m]] == ref_labels)
                    for m, name in enumerate(result.names) if m != ref]
        plain = correspond(prepared, CorrespondenceSettings(data_term=DataTermSettings(normal_max_angle=None)),
                           template=result.template_name, jobs=2)
        plain_ref = labels[result.template_name][plain.face_index[ref]]
        plain_accuracy = [np.mean(labels[name][plain.face_index[m]] == plain_ref)
                          for m, name in enumerate(plain.names) if m != ref]
        lm = prepared.landmarks[ref]
        lo, hi = prepared.shapes[ref].mesh.bounds()
        naive = []
        for m, shape in enumerate(prepared.shapes):
            if m == ref:
                continue
            tlo, thi = shape.mesh.bounds()
            placed = TargetSurface(shape.mesh.vertices, shape.mesh.faces).closest(tlo + (lm.points - lo) * (thi - tlo) / (hi - lo))
            naive.append(np.mean(labels[shape.name][placed.face_index] == labels[result.template_name][lm.face_index]))
        quality = model_quality(result.landmark_matrix())
        out[folder.name] = {"accuracy": float(np.mean(accuracy)), "accuracy_plain_closest": float(np.mean(plain_accuracy)),
                            "naive_accuracy": float(np.mean(naive)), "seconds_per_shape": seconds,
                            "shapes": len(meshes), "outliers": int(result.outliers.sum()),
                            "accuracy_per_shape": [float(a) for a in accuracy],
                            "naive_accuracy_per_shape": [float(a) for a in naive], "model_quality": quality}
        log_quality(folder.name, quality, log)
        log(f"{folder.name:10s} label transfer {100 * np.mean(accuracy):5.1f} % (plain closest points "
            f"{100 * np.mean(plain_accuracy):5.1f} %, naive {100 * np.mean(naive):5.1f} %), "
            f"{seconds:.2f} s/shape, {int(result.outliers.sum())} outlier(s), template {result.template_name}")
    return out


def console_log() -> tuple[Callable[[str], None], list[str]]:
    """A log that prints every line at once and keeps them all (the .txt report)."""
    lines: list[str] = []

    def log(text: str) -> None:
        print(text, flush=True)
        lines.append(text)

    return log, lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer shapes (a few minutes)")
    parser.add_argument("--parts", default="1,2,3", help="which parts to run (default all)")
    args = parser.parse_args()
    OUTPUT.mkdir(exist_ok=True)
    log, lines = console_log()
    report = {"quick": args.quick, "cpu_count": os.cpu_count(), "python": sys.version.split()[0],
              "numpy": np.__version__}
    parts = args.parts.split(",")
    if "3" in parts:
        folder_or_exit("psb")  # before parts 1 and 2 run (--parts 1,2 runs without it)
    if "1" in parts:
        report["procedural"] = procedural(args.quick, log)
    if "2" in parts:
        report["collection"] = collection_timing(args.quick, log)
    if "3" in parts:
        report["psb"] = psb(args.quick, log)
    (OUTPUT / "correspondence.json").write_text(json.dumps(report, indent=2))
    (OUTPUT / "correspondence.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
