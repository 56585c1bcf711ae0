"""Samples that never break: the quality gate on 200 samples per class.

    python bench/samples.py [--data vases,mugs,psb:Airplane,psb:Cup,psb:Fish,psb:Vase] [-n 200]
                            [--alpha A] [--stiffer F] [--seed 0]

For each class a Bayesian GP-LVM with the automatic latent dimension is fitted with the
default settings (cached in bench_output/samples/<class>.npz; the meshing stiffness is
`DeformSettings().final_alpha` unless --alpha is given, applied to the cached model), then
`n` samples are drawn exactly as `shapegen sample --seed 0` draws them (core/generate/sampling.py:
sample i from seed i, meshed on the nearest template by the linear fast path) and gated:

* broken before: samples whose first mesh fails the gate, by criterion (a sample failing
  two criteria counts under both);
* re-meshed: of those, how many passed on the next-nearest templates (same draw);
* stiffer: how many passed on those templates meshed at twice the final α (same draw);
* redrawn: samples that needed new seeds, and the number of redraws;
* broken after: samples still failing after every redraw (target 0).

Data (--data, comma-separated):
  vases        `make_vases(20, seed=0)` (procedural, z up)
  mugs         bench/blender_mugs.py `mug_meshes()`: 14 Blender-made mugs (quads, n-gon caps,
               a handle as a second part, UVs, a material, one mirrored), read as Blender's
               Prepare reads them
  psb:<Class>  every mesh of that PSB class (tests/shared_data.py; 20 shapes, y up)
Writes bench_output/samples.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from shapegen_core.preprocess.collection import PrepareSettings  # noqa: E402
from shapegen_core.generate.deform import DeformSettings  # noqa: E402
from shapegen_core.meshes.mesh import Mesh  # noqa: E402
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.app.pipeline import fit_meshes  # noqa: E402
from shapegen_core.generate.quality import CRITERIA, QualitySettings  # noqa: E402
from shapegen_core.generate.sampling import gated_samples  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUTPUT = ROOT / "bench_output"
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections
from shared_data import folder_or_exit  # noqa: E402
DEFAULT_DATA = "vases,mugs,psb:Airplane,psb:Cup,psb:Fish,psb:Vase"


def class_meshes(data: str) -> tuple[list[Mesh], str]:
    """The meshes of one class and its up axis."""
    if data == "vases":
        from shapegen_core.demo_data import make_vases

        return [s.mesh for s in make_vases(20, seed=0)], "z"
    if data == "mugs":
        sys.path.insert(0, str(ROOT / "bench"))
        from blender_mugs import mug_meshes

        return [Mesh(vertices, faces, name=name) for name, vertices, faces in mug_meshes()], "z"
    if data.startswith("psb:"):
        from shapegen_core.meshes.reading import read_folder

        return read_folder(folder_or_exit("psb", data[4:])), "y"
    raise SystemExit(f"unknown --data {data!r} (vases, mugs, psb:<Class>)")


def class_model(data: str) -> GenerativeShapeModel:
    """The class's fitted model (default settings), cached."""
    path = OUTPUT / "samples" / f"{data.replace(':', '_')}.npz"
    if path.exists():
        return GenerativeShapeModel.load(path)
    start = time.perf_counter()
    meshes, up_axis = class_meshes(data)
    model = fit_meshes(meshes, FitSettings(prepare=PrepareSettings(up_axis=up_axis)), jobs=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.save(path)
    print(f"  {data}: fitted {model.model_type} Q={model.latent_dim} in {time.perf_counter() - start:.0f} s "
          f"-> {path.relative_to(ROOT)}", flush=True)
    return model


def with_stiffness(model: GenerativeShapeModel, alpha: float) -> GenerativeShapeModel:
    """The model meshing with final α `alpha` (a new model object: caches start empty)."""
    settings = replace(model.settings, deform=replace(model.settings.deform, final_alpha=alpha))
    return GenerativeShapeModel(model.meshes, model.correspondence, model.model, settings, model.metadata,
                                training_latents=model.training_latents(), latent_units=model.latent_units())


def gate_class(data: str, n: int, seed: int, alpha: float, stiffer: float) -> dict:
    model = with_stiffness(class_model(data), alpha)
    start = time.perf_counter()
    samples = gated_samples(model, n, seed, settings=QualitySettings(stiffer_remesh=stiffer))
    seconds = time.perf_counter() - start
    first_failed = [s for s in samples if s.rejected]
    first_reasons = Counter()
    for s in first_failed:
        first_try = [r for r in s.rejected if r.seed == s.rejected[0].seed and r.template == s.rejected[0].template]
        first_reasons.update({reason.split(":", 1)[0] for reason in first_try[0].reasons})
    redrawn = [s for s in samples if s.redraws]
    entry = {
        "class": data, "model": model.model_type, "latent_dim": model.latent_dim, "final_alpha": alpha,
        "samples": n, "faces": int(np.median([m.n_faces for m in model.meshes])),
        "broken_before": len(first_failed), "broken_before_by": {c: first_reasons.get(c, 0) for c in CRITERIA},
        "remeshed_on_another_template": sum(1 for s in first_failed if not s.redraws and not s.stiffer),
        "meshed_stiffer": sum(1 for s in first_failed if not s.redraws and s.stiffer), "redrawn_samples": len(redrawn),
        "redraws": int(sum(s.redraws for s in samples)),
        "broken_after": int(sum(not s.quality.ok for s in samples)),
        "max_flipped": int(max(s.quality.flipped for s in samples)),
        "max_edge_stretch": float(max(s.quality.edge_stretch for s in samples)),
        "max_self_intersections": int(max(s.quality.self_intersections for s in samples)),
        "max_extent_ratio": float(max(s.quality.extent_ratio for s in samples)),
        "ms_per_sample": 1000 * seconds / n,
    }
    by = ", ".join(f"{c} {k}" for c, k in entry["broken_before_by"].items() if k) or "-"
    print(f"{data:>13} Q={entry['latent_dim']} α={alpha:g}: broken before {entry['broken_before']:>3}/{n} ({by}); "
          f"re-meshed {entry['remeshed_on_another_template']}, stiffer {entry['meshed_stiffer']}, "
          f"redrawn {entry['redrawn_samples']} "
          f"({entry['redraws']} redraws); broken after {entry['broken_after']}; "
          f"{entry['ms_per_sample']:.0f} ms/sample", flush=True)
    return entry


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=DEFAULT_DATA)
    parser.add_argument("-n", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--alpha", type=float, default=DeformSettings().final_alpha,
                        help="meshing stiffness final α (default: the DeformSettings default)")
    parser.add_argument("--stiffer", type=float, default=QualitySettings().stiffer_remesh,
                        help="QualitySettings.stiffer_remesh (1: no stiffer re-mesh)")
    args = parser.parse_args()
    load = os.getloadavg()[0]
    print(f"quality gate on {args.n} samples per class (load average {load:.1f} on {os.cpu_count()} cores)")
    results = [gate_class(data, args.n, args.seed, args.alpha, args.stiffer) for data in args.data.split(",")]
    OUTPUT.mkdir(exist_ok=True)
    out = OUTPUT / "samples.json"
    out.write_text(json.dumps({"load_average": load, "results": results}, indent=2))
    broken = sum(r["broken_after"] for r in results)
    print(f"broken after the gate: {broken} (target 0) -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
