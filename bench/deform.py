"""Meshing benchmark: speed of decode → mesh, mass generation, and mesh quality
on real data. Not part of the test suite; run `python bench/deform.py [--quick]`.

1. decode + mesh on a ~100k-vertex template, per sample after setup, two ways:
   landmarks path (decode → LinearMeshMap.vertices) and the model basis path
   (mesh = V(mean) + features(z) @ mesh basis, precomputed once).
2. 1000 samples of a ~20k-vertex template written as OBJ.
3. PSB Fish and Airplane (the real collections, tests/shared_data.py; up axis y): fit
   BGP-LVM, sample, mesh;
   flipped triangles (face normal against the normal the local affine predicts), edge-length
   distortion against the template, landmark fit residual, and the distance between the
   linear fast path and the full stiffness relaxation.
Results: bench_output/deform.json and printed lines.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from shapegen_core.demo_data import make_vases  # noqa: E402
from shapegen_core.geometry import apply_affines  # noqa: E402
from shapegen_core.meshes.reading import read_folder  # noqa: E402
from shapegen_core.meshes.mesh import Mesh  # noqa: E402
from shapegen_core.preprocess.collection import PrepareSettings  # noqa: E402
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.shape_model import GenerativeShapeModel
from shapegen_core.app.pipeline import fit_meshes  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections
from shared_data import folder_or_exit  # noqa: E402


def subdivide_to(mesh: Mesh, target_vertices: int) -> Mesh:
    """Midpoint-subdivide (trimesh) until the mesh has at least `target_vertices`."""
    import trimesh

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    while len(tm.vertices) < target_vertices:
        v, f = trimesh.remesh.subdivide(tm.vertices, tm.faces)
        tm = trimesh.Trimesh(v, f, process=False)
    return Mesh(tm.vertices, tm.faces, name=mesh.name)


def with_template_mesh(model: GenerativeShapeModel, index: int, mesh: Mesh) -> GenerativeShapeModel:
    meshes = list(model.meshes)
    meshes[index] = mesh
    return GenerativeShapeModel(meshes, model.correspondence, model.model, model.settings,
                                model.metadata)


def timed(fn, repeat: int) -> float:
    """Median seconds per call."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def _index_nearest_after_subdivision(model: GenerativeShapeModel, target: int) -> int:
    """The training mesh whose 4^k-fold subdivision lands closest to `target` vertices."""
    def reachable(n: int) -> int:
        while n < 0.75 * target:
            n *= 4
        return n

    return int(np.argmin([abs(reachable(m.n_vertices) - target) for m in model.meshes]))


def speed(model: GenerativeShapeModel, results: dict, quick: bool) -> None:
    index = _index_nearest_after_subdivision(model, 100_000)
    big = with_template_mesh(model, index, subdivide_to(model.meshes[index], 75_000))
    name = big.names[index]
    start = time.perf_counter()
    linear = big.linear_map(index)
    setup = time.perf_counter() - start
    rng = np.random.default_rng(0)
    z = big.model.sample_latents(1, rng)

    def landmarks_path():
        return linear.vertices(big.decode(z)[0])

    mean_vertices = linear.vertices(big.model.mean_.reshape(-1, 3))
    basis = big.model.decode_basis()
    mesh_basis = linear.linear_part(basis.reshape(len(basis), -1, 3)).reshape(len(basis), -1)

    def basis_path():
        return mean_vertices.ravel() + big.model.decode_features(z)[0] @ mesh_basis

    np.testing.assert_allclose(basis_path().reshape(-1, 3), landmarks_path(), atol=1e-8)
    repeat = 20 if quick else 100
    t_landmarks, t_basis = timed(landmarks_path, repeat), timed(basis_path, repeat)
    results["decode_mesh_100k"] = {
        "template": name, "vertices": big.meshes[index].n_vertices, "landmarks": big.n_landmarks,
        "setup_s": setup, "landmarks_path_ms": 1000 * t_landmarks, "basis_path_ms": 1000 * t_basis,
        "basis_terms": int(len(basis)), "target_ms": 5.0,
    }
    print(f"decode+mesh, {big.meshes[index].n_vertices} vertices, {big.n_landmarks} landmarks: setup {setup:.2f} s; "
          f"landmarks path {1000 * t_landmarks:.2f} ms, basis path ({len(basis)} terms) {1000 * t_basis:.2f} ms "
          f"per sample (target ≤ 5 ms)")

    # 1000 samples of a ~20k-vertex template as OBJ, through the CLI as a pipeline runs it
    import subprocess

    index = _index_nearest_after_subdivision(model, 20_000)
    name = model.names[index]
    mid = with_template_mesh(model, index, subdivide_to(model.meshes[index], 15_000))
    count = 200 if quick else 1000
    with tempfile.TemporaryDirectory() as folder:
        model_path = Path(folder) / "model.npz"
        mid.save(model_path)
        shapegen = Path(sys.executable).parent / "shapegen"
        start = time.perf_counter()
        subprocess.run([str(shapegen), "sample", str(model_path), "-n", str(count), "-o", str(Path(folder) / "out"),
                        "--template", name, "--format", "obj"], check=True, capture_output=True)
        seconds = time.perf_counter() - start
        written = len(list((Path(folder) / "out").glob("*.obj")))
    results["mass_generation"] = {"samples": count, "written": written, "vertices": mid.meshes[index].n_vertices,
                                  "seconds": seconds, "s_per_1000": seconds * 1000 / count, "target_s_per_1000": 30.0,
                                  "jobs": os.cpu_count()}
    print(f"shapegen sample -n {count}, template {mid.meshes[index].n_vertices} vertices, OBJ: {seconds:.1f} s "
          f"({seconds * 1000 / count:.1f} s per 1000 incl. model load; target ≤ 30 s)")


def quality(model: GenerativeShapeModel, label: str, n_samples: int, results: dict) -> None:
    """Flipped triangles, edge distortion, landmark residual, fast vs relaxed path."""
    rng = np.random.default_rng(0)
    samples, _ = model.sample(n_samples, rng)
    flipped, distortion, residual, fast_vs_full = [], [], [], []
    for lm in samples:
        index = model.choose_template(lm, None)
        deformer = model.deformer(index)
        template = model.meshes[index]
        affines = deformer.fit(lm, "single")
        vertices = model.linear_map(index).vertices(lm)
        mesh = template.with_vertices(vertices)
        # expected normal: cofactor of the blended linear part at each face's centroid
        blocks = affines.reshape(-1, 4, 3)
        blend = deformer.blend.tocsr()
        weights = blend[:, 3::4]  # V × L weights (times homogeneous 1)
        face_weights = (weights[template.faces[:, 0]] + weights[template.faces[:, 1]] + weights[template.faces[:, 2]]) / 3
        linear = np.einsum("fl,lab->fab", face_weights.toarray(), blocks[:, :3, :]).transpose(0, 2, 1)  # F × 3 × 3
        cof = np.linalg.det(linear)[:, None, None] * np.linalg.inv(linear).transpose(0, 2, 1)
        expected = np.einsum("fab,fb->fa", cof, template.face_normals_unnormalised())
        actual = mesh.face_normals_unnormalised()
        flipped.append(float(np.mean(np.einsum("fa,fa->f", expected, actual) <= 0)))
        edges = template.edges_unique()
        before = np.linalg.norm(template.vertices[edges[:, 0]] - template.vertices[edges[:, 1]], axis=1)
        after = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
        log_ratio = np.log(np.maximum(after, 1e-12) / before)
        distortion.append(float(np.std(log_ratio)))
        nodes_after = deformer.from_frame(apply_affines(blocks, deformer.nodes_in_frame))
        diagonal = mesh.bbox_diagonal()
        residual.append(float(np.linalg.norm(nodes_after - lm, axis=1).mean() / diagonal))
        relaxed = deformer.deform(lm, "relax").vertices
        fast_vs_full.append(float(np.linalg.norm(relaxed - vertices, axis=1).mean() / diagonal))
    entry = {
        "samples": n_samples,
        "flipped_triangles_percent_mean": 100 * float(np.mean(flipped)),
        "flipped_triangles_percent_max": 100 * float(np.max(flipped)),
        "edge_log_ratio_std_mean": float(np.mean(distortion)),
        "landmark_residual_percent_of_diagonal": 100 * float(np.mean(residual)),
        "fast_vs_relaxed_percent_of_diagonal": 100 * float(np.mean(fast_vs_full)),
        "final_alpha": model.deform_settings.final_alpha,
    }
    results[f"quality_{label}"] = entry
    print(f"{label}: flipped triangles {entry['flipped_triangles_percent_mean']:.3f} % (max "
          f"{entry['flipped_triangles_percent_max']:.3f} %; target ≤ 0.1 %), edge log-ratio std "
          f"{entry['edge_log_ratio_std_mean']:.3f}, landmark residual {entry['landmark_residual_percent_of_diagonal']:.2f} % "
          f"of diagonal, fast path vs full relaxation {entry['fast_vs_relaxed_percent_of_diagonal']:.3f} % of diagonal")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats and samples")
    parser.add_argument("--landmarks", type=int, default=800)
    args = parser.parse_args()
    psb = {cls: folder_or_exit("psb", cls) for cls in ("Fish", "Airplane")}  # before any work
    out = ROOT / "bench_output"
    out.mkdir(exist_ok=True)
    results: dict = {}

    start = time.perf_counter()
    vases = make_vases(12, seed=0)
    model = fit_meshes([v.mesh for v in vases], FitSettings(prepare=PrepareSettings(n_landmarks=args.landmarks), model="bgplvm"), jobs=2)
    print(f"procedural vases: fitted {model.model_type} Q={model.latent_dim} in {time.perf_counter() - start:.1f} s")
    speed(model, results, args.quick)
    quality(model, "procedural vases", 5 if args.quick else 20, results)

    for cls, folder in psb.items():
        start = time.perf_counter()
        model = fit_meshes(read_folder(folder), FitSettings(
            prepare=PrepareSettings(n_landmarks=args.landmarks, up_axis="y"), model="bgplvm"), jobs=2)
        print(f"PSB {cls}: fitted {model.model_type} Q={model.latent_dim} in {time.perf_counter() - start:.1f} s; "
              f"{int(model.correspondence.outliers.sum())} correspondence outlier(s)")
        quality(model, f"PSB {cls}", 5 if args.quick else 20, results)

    (out / "deform.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {out / 'deform.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
