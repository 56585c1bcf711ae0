"""Does a few-parameter, coarse-to-fine warp search (core/correspond/warps.py) follow the
objective's valley to the ground truth where landmark-wise descent stops? (issue 13, third
round)

    python bench/refine_warps.py [--sizes 40,16,6] [--seeds 11,1,2] [--terms default,attribute]
                                 [--kernels 4,8,16] [--iterations 15] [--jobs 2] [--peer]
                                 [--cache DIR]

Writes bench_output/refine_warps.{json,txt}. Not part of the tests. Procedural vases with
known truth (core/datasets.py; 800 landmarks, as bench/refine_objectives.py), NICP as the
start. For every collection (size × seed) and objective term:

* true error (vs template, % of the diagonal) at NICP and after the warp search, the
  objective E at NICP, at the ground truth and after, the number of E rows recorded, the
  wall time (and the load average: the machine is shared);
* `--peer`: the landmark-wise refinement (refine_population, 30 steps) in the same run;
* the smooth part of the truth: every shape's displacement NICP → truth fitted by least
  squares with the fields of K kernels (the warp search's own space; K = 8, 32, 64), put on
  the surfaces (closest compatible point), and E and the true error there. If E there is
  above E(NICP), no search in that space can reach the truth by lowering E.

Terms (each shape's similarity removed, as refine.py): default ½ log det(I + K/δ) of
positions + smooth normals, ρ = 0.001 (the shipped term); attribute: the per-landmark
variance of the smooth normals across shapes (ShapeWorks' attributes as a plain sum of
squares, ρ = 0.1; bench/refine_objectives.py).
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from shapegen_core.correspond import CorrespondenceSettings, refine_population  # noqa: E402
from shapegen_core.correspond.warps import _Stage, refine_warps, warp_basis  # noqa: E402
from shapegen_core.geometry import TargetSurface  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from refine_objectives import CANDIDATES, Collection, FeatureCompactness  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUTPUT = ROOT / "bench_output"
TERMS = {"default": CANDIDATES["default"], "attribute": CANDIDATES["attribute"]}


def collection(n: int, seed: int, cache: Path | None) -> Collection:
    """The NICP-corresponded collection (pickled in `cache` when given: NICP of 40 vases
    takes minutes)."""
    path = None if cache is None else cache / f"vases_{n}_{seed}.pkl"
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    built = Collection(n, seed)
    if path is not None:
        cache.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(built))
    return built


def smooth_truth(c: Collection, term: FeatureCompactness, n_kernels: int) -> tuple:
    """NICP + the least-squares fit of NICP → truth in the fields of `n_kernels` kernels,
    on the surfaces (closest point with a compatible normal; a landmark without one stays)."""
    state = c.state(c.start)
    mean_normals = (state.face_normals @ term.rotations.transpose(0, 2, 1)).mean(axis=0)
    mean_normals /= np.linalg.norm(mean_normals, axis=1, keepdims=True)
    basis = warp_basis(term.aligned(state.points).mean(axis=0), mean_normals, c.nicp.edges, n_kernels, 1.0)
    stage = _Stage(basis, term, state.face_normals)
    n, k = len(state.points), len(basis.centres)
    displacement = c.truth[0] - c.start[0]
    coefficients = np.zeros((n, k, 2))
    for m in range(n):
        unit = np.zeros((n, k, 2))
        columns = []
        for index in np.ndindex(k, 2):
            unit[(m, *index)] = 1.0
            columns.append(stage.field(unit)[m].ravel())
            unit[(m, *index)] = 0.0
        coefficients[m] = np.linalg.lstsq(np.stack(columns, axis=1), displacement[m].ravel(),
                                          rcond=None)[0].reshape(k, 2)
    moved = c.start[0] + stage.field(coefficients)
    placed = [TargetSurface(mesh.vertices, mesh.faces).closest(p, nm, 0.0)
              for mesh, p, nm in zip(c.meshes, moved, state.face_normals)]
    out = [np.stack([getattr(p, key) for p in placed]) for key in ("points", "face_index", "barycentric")]
    lost = ~np.isfinite(np.stack([p.distance for p in placed]))
    for array, start in zip(out, c.start):
        array[lost] = start[lost]
    return tuple(out)


def measure(c: Collection, name: str, kernels, iterations: int, jobs: int, peer: bool) -> dict:
    options = TERMS[name]
    term = FeatureCompactness(c.state(c.start), **options)
    energy = lambda where: float(term.evaluate(c.state(where))[0])  # noqa: E731
    settings = CorrespondenceSettings(refine="population", refine_iterations=iterations,
                                      refine_regulariser=options["regulariser"])
    make = lambda start: FeatureCompactness(start, **options)  # noqa: E731
    began = time.perf_counter()
    result = refine_warps(c.meshes, *c.start, settings, c.nicp.edges, kernels=kernels, jobs=jobs, compactness=make)
    row = {"error_nicp": c.error(c.start[0]), "error_warps": c.error(result.points),
           "E_nicp": energy(c.start), "E_truth": energy(c.truth),
           "E_warps": energy((result.points, result.face_index, result.barycentric)),
           "trace": result.trace[:, 0].tolist(), "seconds_warps": time.perf_counter() - began,
           "load": os.getloadavg()[0]}
    if peer:
        began = time.perf_counter()
        landmarkwise = refine_population(c.meshes, *c.start, CorrespondenceSettings(
            refine="population", refine_regulariser=options["regulariser"]), edges=c.nicp.edges, jobs=jobs,
            compactness=make)
        row.update(error_landmarkwise=c.error(landmarkwise.points), seconds_landmarkwise=time.perf_counter() - began,
                   E_landmarkwise=energy((landmarkwise.points, landmarkwise.face_index, landmarkwise.barycentric)))
    row["smooth_truth"] = {}
    for k in (8, 32, 64):
        where = smooth_truth(c, term, k)
        row["smooth_truth"][k] = {"E": energy(where), "error": c.error(where[0])}
    return row


def line(n: int, seed: int, name: str, r: dict) -> str:
    text = (f"N {n:2d} seed {seed:2d} {name:9s}: error NICP {r['error_nicp']:.3f} → warps {r['error_warps']:.3f}")
    if "error_landmarkwise" in r:
        text += f" (landmark-wise {r['error_landmarkwise']:.3f}, E {r['E_landmarkwise']:.2f}, " \
                f"{r['seconds_landmarkwise']:.0f} s)"
    text += (f"; E NICP {r['E_nicp']:.2f}, truth {r['E_truth']:.2f}, warps {r['E_warps']:.2f} "
             f"({len(r['trace'])} rows, {r['seconds_warps']:.0f} s, load {r['load']:.1f}); smooth part of the truth "
             + ", ".join(f"K={k}: E {v['E']:.2f} error {v['error']:.3f}" for k, v in r["smooth_truth"].items()))
    return text


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="40,16,6")
    parser.add_argument("--seeds", default="11,1,2")
    parser.add_argument("--terms", default="default,attribute")
    parser.add_argument("--kernels", default="4,8,16", help="kernels of the stages, coarse to fine")
    parser.add_argument("--iterations", type=int, default=15, help="L-BFGS iterations per stage")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--peer", action="store_true", help="also the landmark-wise refinement (refine.py)")
    parser.add_argument("--cache", type=Path, default=None, help="folder for the NICP collections (pickles)")
    args = parser.parse_args()
    OUTPUT.mkdir(exist_ok=True)
    kernels = [int(k) for k in args.kernels.split(",")]
    report, lines = {"kernels": kernels, "iterations": args.iterations, "rows": {}}, []
    for n in [int(s) for s in args.sizes.split(",")]:
        for seed in [int(s) for s in args.seeds.split(",")]:
            c = collection(n, seed, args.cache)
            for name in args.terms.split(","):
                r = measure(c, name, kernels, args.iterations, args.jobs, args.peer)
                report["rows"][f"{n} {seed} {name}"] = r
                lines.append(line(n, seed, name, r))
                print(lines[-1], flush=True)
                (OUTPUT / "refine_warps.json").write_text(json.dumps(report, indent=2))
                (OUTPUT / "refine_warps.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
