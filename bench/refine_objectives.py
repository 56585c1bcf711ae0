"""Which population objective has the procedural class's ground truth as its optimum?
(groupwise refinement beyond the thesis)

    python bench/refine_objectives.py [--seeds 11,1,2,3,4] [--sizes 6,16,40] [--no-starts]

Writes bench_output/refine_objectives.{json,txt}. Not part of the tests. On procedural
vases (core/demo_data/, known (s, θ) correspondence; seed-11-style sets of 6 shapes,
800 landmarks, as `bench/correspondence.py --quick`), for every candidate objective:

* E at the NICP landmarks, at the ground truth (every shape's landmarks at the template
  landmarks' (s, θ)) and at the refined landmarks (refine_population from NICP with the
  candidate in place of the compactness term): a good objective has E(truth) < E(NICP)
  and descent that moves towards the truth (true error falls);
* the true error (vs template, % of the bounding-box diagonal) before and after;
* E along the straight path NICP → truth (5 steps, each point put back on its surface)
  and the cosine between the descent direction at NICP (tangent, smooth fields) and the
  displacement NICP → truth: whether the truth is reachable by local descent at all.

Candidates (all with each shape's similarity removed, as refine.py):
  default      ½ log det(I + K/δ) of positions + smooth normals, ρ = 0.001 (the shipped term)
  positions    the same on positions only (Kotcheff & Taylor's determinant, regularised)
  mdl          Davies et al.'s description length in Thodberg's simplified form,
               Σ_k [1 + log(λ_k/δ)] for λ_k ≥ δ, λ_k/δ below, positions + normals, ρ = 0.01
  normals      ½ log det(I + K/δ) of the smooth normals alone
  attribute    per-landmark variance of the normals across shapes (ShapeWorks' "attributes"
               used as a sum of squares: ½ tr K / δ, no log), ρ = 0.1
  annealed     the default term, descended with ρ 0.1 → 0.03 → 0.01 → 0.001 (coarse to fine)

Then (`--sizes`) the default and positions terms at N = 6, 16, 40 shapes (seed 11): does
the truth become the better optimum as the population grows? And (unless --no-starts)
NICP started from every shape as template, keeping the start with the lowest default E.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes  # noqa: E402
from shapegen_core.correspond import CorrespondenceSettings, correspond, refine_population  # noqa: E402
from shapegen_core.correspond.objective import CompactnessTerm, compactness, regulariser_variance  # noqa: E402
from shapegen_core.correspond.refine import _tangent, landmark_state, smooth_basis  # noqa: E402
from shapegen_core.demo_data import make_vases  # noqa: E402
from shapegen_core.geometry import TargetSurface  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from correspondence import error_vs_template  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUTPUT = ROOT / "bench_output"
LANDMARKS = 800
REFINED = CorrespondenceSettings.from_dict({"refinement": {"method": "population"}})


# ---------------------------------------------------------------------------- candidate terms
def mode_cost(features: np.ndarray, delta: float, cost: str) -> tuple[float, np.ndarray]:
    """A cost of the population's modes (eigenvalues λ_k of the N × N dual Gram matrix K of
    the centred feature vectors) and its gradient (N, F, 3): "logdet" ½ Σ log(1 + λ/δ);
    "mdl" ½ Σ f(λ), f = 1 + log(λ/δ) for λ ≥ δ, λ/δ below (C¹ at δ; Thodberg's form of
    Davies et al.'s description length); "variance" ½ Σ λ / δ."""
    if cost == "logdet":
        return compactness(features, delta)
    n = len(features)
    y = features.reshape(n, -1)
    y = y - y.mean(axis=0)
    if cost == "variance":
        return 0.5 * float(np.sum(y**2)) / (n - 1) / delta, (y / (n - 1) / delta).reshape(features.shape)
    eigenvalues, vectors = np.linalg.eigh(y @ y.T / (n - 1))
    eigenvalues = np.maximum(eigenvalues, np.finfo(float).tiny)
    above = eigenvalues >= delta
    value = np.where(above, 1.0 + np.log(eigenvalues / delta), eigenvalues / delta)
    slope = np.where(above, 1.0 / eigenvalues, 1.0 / delta)  # ∂f/∂λ; ∂λ_k/∂Y = 2 v_k v_kᵀ Y / (n − 1)
    gradient = (vectors * slope) @ vectors.T @ y / (n - 1)
    return 0.5 * float(np.sum(value)), gradient.reshape(features.shape)


class FeatureCompactness(CompactnessTerm):
    """`mode_cost` of [w_p · positions, w_n · r · normals] (similarity removed as in
    CompactnessTerm; r the RMS landmark radius; δ = L (ρ r)²)."""

    def __init__(self, start, position_weight: float, normal_weight: float, cost: str, regulariser: float):
        super().__init__(start, regulariser, "similarity")
        self.position_weight, self.cost = position_weight, cost
        self.radius = float(np.sqrt(np.mean(np.sum(self.aligned(start.points) ** 2, axis=2))))
        self.normal_scale = normal_weight * self.radius
        self.delta = regulariser_variance(self.aligned(start.points), regulariser)

    def evaluate(self, state):
        n_landmarks = state.points.shape[1]
        parts = []
        if self.position_weight:
            parts.append(self.position_weight * self.aligned(state.points))
        if self.normal_scale:
            parts.append(self.normal_scale * state.normals @ self.rotations.transpose(0, 2, 1))
        value, grad_z = mode_cost(np.concatenate(parts, axis=1), self.delta, self.cost)
        grad_x = np.zeros_like(state.points)
        if self.position_weight:
            grad_p = self.position_weight * self.scales[:, None, None] * grad_z[:, :n_landmarks] @ self.rotations
            grad_x += grad_p - grad_p.mean(axis=1, keepdims=True)
            grad_z = grad_z[:, n_landmarks:]
        if self.normal_scale:
            grad_n = self.normal_scale * grad_z @ self.rotations
            grad_x += np.einsum("mlij,mli->mlj", state.normal_jacobians, grad_n)
        return value, grad_x


CANDIDATES = {
    "default": dict(position_weight=1.0, normal_weight=1.0, cost="logdet", regulariser=0.001),
    "positions": dict(position_weight=1.0, normal_weight=0.0, cost="logdet", regulariser=0.001),
    "mdl": dict(position_weight=1.0, normal_weight=1.0, cost="mdl", regulariser=0.01),
    "normals": dict(position_weight=0.0, normal_weight=1.0, cost="logdet", regulariser=0.001),
    "attribute": dict(position_weight=0.0, normal_weight=1.0, cost="variance", regulariser=0.1),
}
ANNEAL = (0.1, 0.03, 0.01, 0.001)


def term_maker(options: dict):
    return lambda start: FeatureCompactness(start, **options)


# ---------------------------------------------------------------------------- one collection
class Collection:
    """Procedural vases prepared, NICP-corresponded, with their ground-truth landmarks."""

    def __init__(self, n: int, seed: int, template: str | None = None, prepared=None, shapes=None):
        self.shapes = shapes or make_vases(n, seed=seed, resolution=(65, 130))
        self.prepared = prepared or prepare_meshes([s.mesh for s in self.shapes],
                                                   PrepareSettings(n_landmarks=LANDMARKS, seed=0))
        self.meshes = [s.mesh for s in self.prepared.shapes]
        self.nicp = correspond(self.prepared, CorrespondenceSettings(), template=template, jobs=1)
        self.t = self.nicp.names.index(self.nicp.template_name)
        lm = self.prepared.landmarks[self.t]
        st = self.shapes[self.t].surface_coordinates(lm.face_index, lm.barycentric)
        self.start = (self.nicp.points, self.nicp.face_index, self.nicp.barycentric)
        self.truth = self.on_surfaces([s.transform.to_normalised(self.shapes[m].points_at(st))
                                       for m, s in enumerate(self.prepared.shapes)])

    def on_surfaces(self, points) -> tuple:
        placed = [TargetSurface(mesh.vertices, mesh.faces).closest(p) for mesh, p in zip(self.meshes, points)]
        return tuple(np.stack([getattr(p, k) for p in placed]) for k in ("points", "face_index", "barycentric"))

    def error(self, points) -> float:
        """True error vs template, % of the diagonal (bench/correspondence.py)."""
        pin = np.stack([s.transform.to_input(p) for s, p in zip(self.prepared.shapes, points)])
        return 100 * float(error_vs_template(self.shapes, self.t, self.prepared.landmarks[self.t], pin).mean())

    def state(self, where):
        return landmark_state(self.meshes, *where)

    def refine(self, make_term, regulariser: float = 0.001, start=None):
        settings = CorrespondenceSettings.from_dict({"refinement": {"method": "population", "regulariser": regulariser}})
        return refine_population(self.meshes, *(start or self.start), settings, edges=self.nicp.edges,
                                 compactness=make_term)


def diagnose(collection: Collection, options: dict, anneal: bool = False) -> dict:
    """E at NICP / truth / refined, true errors, E along the path NICP → truth, and the
    cosine of the descent direction at NICP with the displacement to the truth."""
    c = collection
    term = FeatureCompactness(c.state(c.start), **options)
    energy = lambda where: float(term.evaluate(c.state(where))[0])  # noqa: E731
    where, steps = c.start, 0
    for rho in (ANNEAL if anneal else (options["regulariser"],)):
        refined = c.refine(term_maker({**options, "regulariser": rho}), rho, where)
        where, steps = (refined.points, refined.face_index, refined.barycentric), steps + len(refined.trace) - 1
    path = [energy(c.on_surfaces((1 - a) * c.start[0] + a * c.truth[0])) for a in np.linspace(0, 1, 6)]
    start_state = c.state(c.start)
    _, gradient = term.evaluate(start_state)
    basis = smooth_basis(c.nicp.edges, c.start[0].shape[1], REFINED.refinement.smooth_fields)
    direction = _tangent(np.einsum("lk,mkd->mld", basis, np.einsum("lk,mld->mkd", basis,
                                                                     _tangent(gradient, start_state.face_normals))),
                         start_state.face_normals)
    displacement = c.truth[0] - c.start[0]
    cosine = float(np.sum(-direction * displacement) / np.linalg.norm(direction) / np.linalg.norm(displacement))
    return {"error_nicp": c.error(c.start[0]), "error_refined": c.error(where[0]), "E_nicp": energy(c.start),
            "E_truth": energy(c.truth), "E_refined": energy(where), "steps": steps, "path": path,
            "cosine_descent_truth": cosine}


def summary_line(name: str, rows: list[dict]) -> str:
    before = np.mean([r["error_nicp"] for r in rows])
    after = np.mean([r["error_refined"] for r in rows])
    improved = sum(r["error_refined"] < r["error_nicp"] for r in rows)
    truth_below = sum(r["E_truth"] < r["E_nicp"] for r in rows)
    below_truth = sum(r["E_refined"] < r["E_truth"] for r in rows)
    monotone = sum(bool(np.all(np.diff(r["path"]) < 0)) for r in rows)
    cosine = np.mean([r["cosine_descent_truth"] for r in rows])
    return (f"{name:10s} error {before:.3f} → {after:.3f} % (lower on {improved}/{len(rows)} seeds); "
            f"E(truth) < E(NICP) {truth_below}/{len(rows)}; refined below the truth {below_truth}/{len(rows)}; "
            f"path NICP → truth descending {monotone}/{len(rows)}; cos(descent, truth − NICP) {cosine:.3f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="11,1,2,3,4")
    parser.add_argument("--sizes", default="6,16,40", help="population sizes of the N-dependence (seed 11)")
    parser.add_argument("--no-starts", action="store_true", help="skip NICP from every template")
    args = parser.parse_args()
    OUTPUT.mkdir(exist_ok=True)
    lines, report = [], {"load_average_start": os.getloadavg()[0]}

    def log(text: str) -> None:
        print(text, flush=True)
        lines.append(text)

    seeds = [int(s) for s in args.seeds.split(",") if s]
    collections = {seed: Collection(6, seed) for seed in seeds}
    log(f"== candidates, 6 vases × {len(seeds)} seeds ({seeds}), {LANDMARKS} landmarks")
    report["candidates"] = {}
    for name, options in [*CANDIDATES.items(), ("annealed", CANDIDATES["default"])]:
        rows = [diagnose(collections[seed], options, anneal=name == "annealed") for seed in seeds]
        report["candidates"][name] = dict(zip(map(str, seeds), rows))
        log(summary_line(name, rows))
        for seed, r in zip(seeds, rows):
            log(f"    seed {seed:2d}: error {r['error_nicp']:.3f} → {r['error_refined']:.3f}; E NICP "
                f"{r['E_nicp']:.3f}, truth {r['E_truth']:.3f}, refined {r['E_refined']:.3f} ({r['steps']} steps); "
                "path " + " ".join(f"{e:.2f}" for e in r["path"]))

    report["sizes"] = {}
    for n in [int(s) for s in args.sizes.split(",") if s]:
        start = time.perf_counter()
        collection = collections[11] if n == 6 and 11 in collections else Collection(n, 11)
        for name in ("default", "positions"):
            r = diagnose(collection, CANDIDATES[name])
            report["sizes"][f"{n} {name}"] = r
            log(f"N = {n:2d} {name:9s}: error {r['error_nicp']:.3f} → {r['error_refined']:.3f}; E NICP "
                f"{r['E_nicp']:.2f}, truth {r['E_truth']:.2f}, refined {r['E_refined']:.2f} ({r['steps']} steps); "
                "path " + " ".join(f"{e:.2f}" for e in r["path"]) + f"; cos {r['cosine_descent_truth']:.3f}")
        log(f"    ({time.perf_counter() - start:.0f} s, load {os.getloadavg()[0]:.1f})")

    if not args.no_starts:
        report["starts"] = {}
        picked, default, best = [], [], []
        for seed in seeds:
            base = collections[seed]
            errors, energies = [], []
            for name in base.nicp.names:
                c = Collection(6, seed, template=name, prepared=base.prepared, shapes=base.shapes)
                term = FeatureCompactness(c.state(c.start), **CANDIDATES["default"])
                errors.append(c.error(c.start[0]))
                energies.append(float(term.evaluate(c.state(c.start))[0]) / c.start[0].shape[1])
            picked.append(errors[int(np.argmin(energies))])
            default.append(base.error(base.start[0]))
            best.append(min(errors))
            report["starts"][str(seed)] = {"errors": errors, "E_per_landmark": energies}
            log(f"starts seed {seed:2d}: error per template " + " ".join(f"{e:.2f}" for e in errors)
                + f"; default template {default[-1]:.2f}, lowest-E start {picked[-1]:.2f}, best {best[-1]:.2f}")
        log(f"starts: mean error default template {np.mean(default):.3f}, lowest-E start {np.mean(picked):.3f}, "
            f"best possible {np.mean(best):.3f} %")
    report["load_average_end"] = os.getloadavg()[0]
    (OUTPUT / "refine_objectives.json").write_text(json.dumps(report, indent=2))
    (OUTPUT / "refine_objectives.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
