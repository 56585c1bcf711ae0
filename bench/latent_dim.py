"""The automatic latent dimension (80 % rule) on real and procedural classes, per fold.

    python bench/latent_dim.py [--data vases,psb:Airplane,psb:Cup,psb:Fish,psb:Vase] [--folds 5]
                               [--landmarks 800] [--seed 0]

For each class: our pipeline (prepare_meshes + correspond, cached in bench_output/) gives the
landmark matrix Y (N, 3L); for the whole collection and for the training part of each of the
`--folds` folds of `evaluation.protocol.heldout_folds` it prints the latent dimension each model
picks when none is given (PPCA, GP-LVM, Bayesian GP-LVM: the dimension is chosen before their
optimisation starts, so the GP-LVMs run one iteration only), and beside it the rule as it was
before it counted the unshrunk variance ("shrunk": the running sum of the Ledoit-Wolf shrunk spectrum over the
unshrunk total), and the Ledoit-Wolf shrinkage ("LW"). Writes bench_output/latent_dim.json.

Data (--data, comma-separated):
  vases        `make_vases(20, seed)` (procedural, z up)
  psb:<Class>  every mesh of that PSB class (tests/shared_data.py; 20 shapes, y up)
Target: automatic dimension <= 8 on every class and fold (the former rule jumped between 2 and 19).
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
from shapegen_core.correspond import Correspondence, CorrespondenceSettings, correspond  # noqa: E402
from shapegen_core.evaluation.protocol import heldout_folds  # noqa: E402
from shapegen_core.preprocess.landmarks import DEFAULT_LANDMARKS  # noqa: E402
from shapegen_core.models import MODEL_TYPES, make_model  # noqa: E402
from shapegen_core.models.base import ledoit_wolf_shrinkage, principal_axes, shrunk_spectrum  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # shared_data: the real collections
from shared_data import folder_or_exit  # noqa: E402

BENCH_OUTPUT = Path(__file__).resolve().parents[1] / "bench_output"
DEFAULT_DATA = "vases,psb:Airplane,psb:Cup,psb:Fish,psb:Vase"


def landmark_matrix(data: str, n_landmarks: int, seed: int) -> np.ndarray:
    """Y (N, 3L) of one class through our pipeline; the correspondence is cached."""
    tag = f"vases20_seed{seed}" if data == "vases" else f"psb_{data[4:]}"
    path = BENCH_OUTPUT / f"latent_dim_corr_{tag}_L{n_landmarks}.npz"
    if not path.exists():
        start = time.perf_counter()
        if data == "vases":
            from shapegen_core.demo_data import make_vases
            meshes, up_axis = [s.mesh for s in make_vases(20, seed=seed)], "z"
        elif data.startswith("psb:"):
            from shapegen_core.meshes.reading import read_folder
            meshes, up_axis = read_folder(folder_or_exit("psb", data[4:])), "y"
        else:
            raise SystemExit(f"unknown --data {data!r} (vases, psb:<Class>)")
        prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=n_landmarks, up_axis=up_axis, seed=0))
        BENCH_OUTPUT.mkdir(exist_ok=True)
        correspond(prepared, CorrespondenceSettings(), jobs=1).save(path)
        print(f"  {data}: corresponded in {time.perf_counter() - start:.0f} s -> {path.name}", flush=True)
    return Correspondence.load(path).landmark_matrix()


def shrunk_rule(Y: np.ndarray, fraction: float = 0.8) -> int:
    """The former rule: shrunk spectrum's running sum over the unshrunk total, <= N - 1."""
    Yc = Y - Y.mean(0)
    _, eigvals, _ = principal_axes(Yc)
    spectrum, _ = shrunk_spectrum(eigvals, Yc.shape[1], ledoit_wolf_shrinkage(Yc))
    q = int(np.searchsorted(np.cumsum(spectrum) / eigvals.sum(), fraction - 1e-12) + 1)
    return max(1, min(q, Yc.shape[0] - 1))


def automatic_dims(Y: np.ndarray) -> dict[str, float]:
    """Latent dimension of each model fitted on Y without one, the former rule's, and the
    Ledoit-Wolf shrinkage."""
    dims = {"shrinkage": ledoit_wolf_shrinkage(Y - Y.mean(0)), "shrunk": shrunk_rule(Y)}
    for name in MODEL_TYPES:
        options = {} if name == "ppca" else {"max_iter": 1}
        dims[name] = make_model(name, **options).fit(Y).latent_dim
    return dims


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=DEFAULT_DATA, help=f"comma-separated classes (default {DEFAULT_DATA})")
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--landmarks", type=int, default=DEFAULT_LANDMARKS)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    report = {}
    print(f"{'class':<14}{'part':<8}{'N':>4} {'LW':>5}  {'shrunk':>6} {'ppca':>5} {'gplvm':>6} {'bgplvm':>7}")
    for data in args.data.split(","):
        Y = landmark_matrix(data, args.landmarks, args.seed)
        n = len(Y)
        parts = [("all", np.arange(n))]
        parts += [(f"fold {k + 1}", np.setdiff1d(np.arange(n), held))
                  for k, held in enumerate(heldout_folds(n, args.folds, args.seed))]
        report[data] = {}
        for label, rows in parts:
            dims = automatic_dims(Y[rows])
            report[data][label] = {"n": int(len(rows)), **dims}
            print(f"{data:<14}{label:<8}{len(rows):>4} {dims['shrinkage']:>5.2f}  {dims['shrunk']:>6} {dims['ppca']:>5} "
                  f"{dims['gplvm']:>6} {dims['bgplvm']:>7}", flush=True)
    BENCH_OUTPUT.mkdir(exist_ok=True)
    (BENCH_OUTPUT / "latent_dim.json").write_text(json.dumps(report, indent=1))
    largest = max(d[m] for parts in report.values() for d in parts.values() for m in MODEL_TYPES)
    print(f"largest automatic dimension: {largest} (target <= 8)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
