"""Blender workflow benchmark: not a test.

    python bench/blender_sliders.py [--rings 275] [--landmarks 300] [--drags 200]

Runs headless on the bpy module with the built extension (dist/*.zip, `make build`)
installed into a throwaway user folder, then measures:

1. **Main-thread stalls while a fit runs.** Six procedural vases of ~100k vertices each
   are fitted through the real Fit operator (a worker process); the main thread polls the
   job like the UI timer does (`jobs.poll_job`, here every 10 ms instead of 100 ms, to
   sample more polls). Reported: the longest single poll while the job runs (target
   ≤ 50 ms) and, separately, the final poll that applies the result (loads the model file
   and packs it into the .blend).
2. **Slider updates on a ≥100k-vertex live object**, for every model type: the time of one
   `scene.shapegen.latents[k].value = v` assignment, which runs the update callback
   (features(z) @ mesh basis, then `foreach_set` of the position attribute and
   `mesh.update()`). Target ≤ 16 ms. Also: time to build the live object (one-off:
   factorisation of the linear mesher and the K × 3V mesh basis).

Writes bench_output/blender_sliders.{json,txt}.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="shapegen-bench-user-")

import bpy  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

from demo import install_extension  # noqa: E402  (the demo's install: dist/ zip, enabled, checked)

MODULE = "bl_ext.user_default.shapegen"


def module(name: str):
    return importlib.import_module(f"{MODULE}.{name}")


def stats(values_ms: list[float]) -> dict:
    a = np.asarray(values_ms)
    return {"n": int(a.size), "median_ms": float(np.median(a)), "p95_ms": float(np.percentile(a, 95)),
            "max_ms": float(a.max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rings", type=int, default=275, help="vertex rings per vase (275: ~100k vertices)")
    parser.add_argument("--shapes", type=int, default=6)
    parser.add_argument("--landmarks", type=int, default=300)
    parser.add_argument("--drags", type=int, default=200, help="slider assignments timed per model type")
    parser.add_argument("--output", type=Path, default=ROOT / "bench_output")
    args = parser.parse_args()

    install_extension(bpy)
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    datasets, convert = module("core.demo_data"), module("shapegen_addon.convert")
    jobs, store, latent = module("shapegen_addon.jobs"), module("shapegen_addon.store"), module(
        "shapegen_addon.latent")
    models = module("core.models")

    scene = bpy.context.scene
    settings = scene.shapegen
    collection = bpy.data.collections.new("vases")
    scene.collection.children.link(collection)
    shapes = datasets.make_vases(args.shapes, seed=2, resolution=(args.rings, args.rings))
    for shape in shapes:
        collection.objects.link(bpy.data.objects.new(
            shape.name, convert.mesh_data_from_arrays(shape.name, shape.mesh.vertices, shape.mesh.faces)))
    settings.source_collection = collection
    settings.prepare.n_landmarks = args.landmarks
    settings.fit.model = "ppca"
    settings.fit.latent_dim = 3
    counts = [s.mesh.n_vertices for s in shapes]
    print(f"{args.shapes} vases, {min(counts)}-{max(counts)} vertices; fitting in a worker ...", flush=True)

    # ---- 1. stalls of the polling loop while the fit runs
    start = time.perf_counter()
    t = time.perf_counter()
    bpy.ops.shapegen.fit(extra_settings=json.dumps({"jobs": 1, "correspondence": {"groupwise_rounds": 0}}))
    launch_ms = 1000 * (time.perf_counter() - t)
    polls, apply_ms, status = [], None, None
    while True:
        t = time.perf_counter()
        status = jobs.poll_job()
        dt = 1000 * (time.perf_counter() - t)
        if status is not None and status.finished:
            apply_ms = dt
            break
        polls.append(dt)
        time.sleep(0.01)
    fit_seconds = time.perf_counter() - start
    if settings.job_state != "DONE":
        sys.exit(f"fit failed: {settings.job_message}")
    print(f"fit done in {fit_seconds:.1f} s; {len(polls)} polls, longest {max(polls):.2f} ms; "
          f"apply {apply_ms:.1f} ms", flush=True)
    model_bytes = len(store.model_bytes(settings.model_text))

    # ---- 2. sliders, every model type (same correspondence, models fitted in-process)
    fitted = store.get_model(scene)
    Y = fitted.training_matrix()
    template = max(range(len(fitted.meshes)), key=lambda i: fitted.meshes[i].n_vertices)
    sliders = {}
    folder = Path(tempfile.mkdtemp(prefix="shapegen-bench-"))
    for kind in ("ppca", "gplvm", "bgplvm"):
        if kind == "ppca":
            shape_model = fitted
        else:
            shape_model = module("core.app.shape_model").GenerativeShapeModel(
                fitted.meshes, fitted.correspondence, models.MODEL_TYPES[kind](n_components=3).fit(Y),
                settings=fitted.settings)
            path = shape_model.save(folder / f"vases_{kind}.npz")
            bpy.ops.shapegen.load_model(filepath=str(path))
        t = time.perf_counter()
        bpy.ops.shapegen.explore(template=fitted.names[template])
        build_s = time.perf_counter() - t
        live = settings.live_object
        rng = np.random.default_rng(0)
        times = []
        for i in range(args.drags):
            value = float(rng.uniform(-2.5, 2.5))
            item = settings.latents[i % len(settings.latents)]
            t = time.perf_counter()
            item.value = value
            times.append(1000 * (time.perf_counter() - t))
        mesher = latent._MESHERS[(store.model_id(scene), template)]
        z = latent.current_latent(scene)
        t = time.perf_counter()
        for _ in range(20):
            flat = mesher.flat_vertices(z)
        compute_ms = 1000 * (time.perf_counter() - t) / 20
        t = time.perf_counter()
        for _ in range(20):
            latent.write_positions(live.data, flat)
        write_ms = 1000 * (time.perf_counter() - t) / 20
        sliders[kind] = {"vertices": len(live.data.vertices), "basis_rows": int(mesher.basis.shape[0]),
                         "build_live_object_s": build_s, "compute_ms": compute_ms, "foreach_set_update_ms": write_ms,
                         **stats(times)}
        print(f"{kind}: {sliders[kind]}", flush=True)
        bpy.ops.shapegen.explore_bake()

    result = {
        "machine": {"python": sys.version.split()[0], "bpy": bpy.app.version_string, "cpus": os.cpu_count(),
                    "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")},
        "fit": {"shapes": args.shapes, "vertices": [min(counts), max(counts)], "landmarks": args.landmarks,
                "seconds": fit_seconds, "launch_ms": launch_ms, "polls": stats(polls), "apply_result_ms": apply_ms,
                "packed_model_mb": model_bytes / 1e6},
        "sliders": sliders,
        "targets": {"slider_update_ms": 16, "longest_stall_ms": 50},
    }
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "blender_sliders.json").write_text(json.dumps(result, indent=2))
    lines = [f"Blender workflow benchmark (bpy {bpy.app.version_string}, {os.cpu_count()} CPUs)",
             f"fit: {args.shapes} vases {min(counts)}-{max(counts)} vertices, {args.landmarks} landmarks, "
             f"{fit_seconds:.1f} s in a worker",
             f"  starting the fit (operator, writes the meshes): {launch_ms:.1f} ms",
             f"  polls while running: {len(polls)}, median {result['fit']['polls']['median_ms']:.3f} ms, "
             f"longest {result['fit']['polls']['max_ms']:.2f} ms (target <= 50 ms)",
             f"  applying the result (load + pack {model_bytes / 1e6:.1f} MB): {apply_ms:.1f} ms"]
    for kind, s in sliders.items():
        lines.append(f"slider {kind}: {s['vertices']} vertices, K={s['basis_rows']}: median {s['median_ms']:.2f} ms, "
                     f"p95 {s['p95_ms']:.2f} ms, max {s['max_ms']:.2f} ms (target <= 16 ms); "
                     f"compute {s['compute_ms']:.2f} ms + write {s['foreach_set_update_ms']:.2f} ms; "
                     f"live object built in {s['build_live_object_s']:.2f} s")
    (args.output / "blender_sliders.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    import addon_utils

    addon_utils.disable(MODULE, default_set=True)


if __name__ == "__main__":
    main()
