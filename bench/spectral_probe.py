"""Intrinsic correspondence start: true error on TOSCA, procedural
vases and PSB label transfer, for today's start (closest points) and the spectral start.

    python bench/spectral_probe.py [--classes cat dog ...] [--initialisation closest spectral]
                                   [--vases N] [--psb Vase Cup ...] [--shapes N] [--starts]

Not part of the tests. Every class is run with the same settings (nothing tuned per
class). Figures go to stdout and bench_output/spectral_probe_<pid>.json.

TOSCA (tosca/<class>, tests/shared_data.py; z up): true error of a template landmark = distance, in
the input frame, from where the correspondence put it on a shape to where the ground truth
puts it (the three corners of its template face carried by the `.vts` maps, blended by its
barycentrics), over the shape's bounding-box diagonal; mean over landmarks and shapes other
than the template. Time: wall (and this process's CPU) seconds of `correspond` per shape
(1 process; with the spectral start this includes the closest-point registration each
shape is checked against). Vases: bench/correspondence.py part 1's error vs the template;
PSB: its part 3's label transfer (the closest-point rows are today's default).
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
from shapegen_core.correspond import CorrespondenceSettings, correspond  # noqa: E402
from shapegen_core.base.errors import MeshFileError  # noqa: E402
from shapegen_core.meshes.reading import read_folder, read_mesh  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/correspondence.py: the vase and PSB measures

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections
from shared_data import folder_or_exit  # noqa: E402

OUTPUT = ROOT / "bench_output"
TOSCA_CLASSES = ("cat", "centaur", "dog", "horse")


def tosca_class(name: str, limit: int | None = None):
    """(meshes, ground-truth maps) of one TOSCA class; a file the reader refuses is left out (said)."""
    meshes, maps = [], []
    for path in sorted(folder_or_exit("tosca", name).glob("*.off"), key=lambda p: int(p.stem[len(name):])):
        try:
            mesh = read_mesh(path)
        except MeshFileError as exc:  # horse7.off is cut short mid-line
            print(f"left out: {exc}", flush=True)
            continue
        truth = np.loadtxt(path.parent / "corres" / f"{path.stem}.vts", dtype=np.int64) - 1
        if mesh.n_vertices <= truth.max():
            print(f"left out: {path.name}: {mesh.n_vertices} vertices, its map names {truth.max() + 1}")
            continue
        meshes.append(mesh)
        maps.append(truth)
        if limit and len(meshes) >= limit:
            break
    return meshes, maps


def vertex_images(template_map: np.ndarray, shape_map: np.ndarray, template_vertices: np.ndarray) -> np.ndarray:
    """Per template vertex, the shape vertex the ground truth carries it to; a template vertex
    no common point names takes its nearest named neighbour's image."""
    from scipy.spatial import cKDTree

    image = np.full(len(template_vertices), -1, dtype=np.int64)
    image[template_map] = shape_map
    named = np.flatnonzero(image >= 0)
    unnamed = np.flatnonzero(image < 0)
    if len(unnamed):
        _, nearest = cKDTree(template_vertices[named]).query(template_vertices[unnamed])
        image[unnamed] = image[named[nearest]]
    return image


def tosca_errors(meshes, maps, result) -> np.ndarray:
    """Per shape: mean true landmark error / bounding-box diagonal (input frame)."""
    t = result.names.index(result.template_name)
    template = meshes[t]
    corners = template.faces[result.face_index[t]]  # (L, 3) template vertices of every landmark's face
    bary = result.barycentric[t]
    errors = []
    for m, mesh in enumerate(meshes):
        image = vertex_images(maps[t], maps[m], template.vertices)
        truth = np.einsum("lk,lkd->ld", bary, mesh.vertices[image[corners]])
        errors.append(np.linalg.norm(result.points_input[m] - truth, axis=1).mean() / mesh.bbox_diagonal())
    return np.array(errors)


def run_tosca(name: str, initialisations, shapes: int | None, landmarks: int) -> dict:
    meshes, maps = tosca_class(name, shapes)
    prepared = prepare_meshes(meshes, PrepareSettings(up_axis="z", n_landmarks=landmarks))
    out = {}
    for init in initialisations:
        settings = _settings(init)
        messages = []
        start, cpu = time.perf_counter(), time.process_time()
        result = correspond(prepared, settings, jobs=1, progress=lambda f, m: messages.append(m))
        seconds = (time.perf_counter() - start) / len(meshes)
        cpu_seconds = (time.process_time() - cpu) / len(meshes)
        errors = tosca_errors(meshes, maps, result)
        t = result.names.index(result.template_name)
        others = np.delete(errors, t)
        out[init] = {"mean %": 100 * float(others.mean()), "max %": 100 * float(others.max()),
                     "per shape %": {n: round(100 * float(e), 2) for n, e in zip(result.names, errors)},
                     "s/shape": seconds, "cpu s/shape": cpu_seconds, "template": result.template_name,
                     "fallbacks": [m for m in messages if ": closest-point start" in m or "spectral start (" in m]}
        print(f"TOSCA {name:8s} {init:9s} mean {out[init]['mean %']:5.2f} %  max {out[init]['max %']:5.2f} %  "
              f"{seconds:5.2f} s/shape ({cpu_seconds:4.2f} CPU)  template {result.template_name}  "
              + " ".join(f"{n}:{v}" for n, v in out[init]["per shape %"].items()), flush=True)
        for message in out[init]["fallbacks"]:
            print(f"    {message}")
    return out


def _correspond_timed(prepared, initialisation: str):
    """(result, wall s/shape, messages) of one `correspond` in this process."""
    messages = []
    start = time.perf_counter()
    result = correspond(prepared, _settings(initialisation), jobs=1, progress=lambda f, m: messages.append(m))
    return result, (time.perf_counter() - start) / len(prepared.shapes), messages


def _starts_said(messages) -> list[str]:
    return [m for m in messages if ": closest-point start" in m]


def run_vases(n: int, initialisations) -> dict:
    """Procedural vases (core/demo_data/, bench/correspondence.py part 1): mean true error
    vs the template landmark's surface coordinates, % of the diagonal."""
    from correspondence import error_vs_template
    from shapegen_core.demo_data import make_vases

    shapes = make_vases(n, seed=11, resolution=(65, 130))
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=800, seed=0))
    out = {}
    for init in initialisations:
        result, seconds, messages = _correspond_timed(prepared, init)
        t = result.names.index(result.template_name)
        errors = np.delete(error_vs_template(shapes, t, prepared.landmarks[t], result.points_input), t)
        out[init] = {"mean %": 100 * float(errors.mean()), "s/shape": seconds, "fallbacks": _starts_said(messages)}
        print(f"vases ({n})     {init:9s} mean {out[init]['mean %']:5.2f} %  {seconds:5.2f} s/shape  "
              f"fallbacks {len(out[init]['fallbacks'])}", flush=True)
    return out


def run_psb(name: str, initialisations, shapes: int | None) -> dict:
    """PSB label transfer (bench/correspondence.py part 3): share of landmarks whose part
    label is the template landmark's."""
    from correspondence import face_labels

    folder = folder_or_exit("psb", name)
    meshes = read_folder(folder)[:shapes] if shapes else read_folder(folder)
    labels = {m.name: face_labels(folder / f"{m.name}.off", m) for m in meshes}
    prepared = prepare_meshes(meshes, PrepareSettings(n_landmarks=800, up_axis="y", seed=0))
    out = {}
    for init in initialisations:
        result, seconds, messages = _correspond_timed(prepared, init)
        ref = result.names.index(result.template_name)
        reference = labels[result.template_name][result.face_index[ref]]
        accuracy = [np.mean(labels[n][result.face_index[m]] == reference) for m, n in enumerate(result.names) if m != ref]
        out[init] = {"label transfer %": 100 * float(np.mean(accuracy)), "s/shape": seconds,
                     "fallbacks": _starts_said(messages)}
        print(f"PSB {name:10s} {init:9s} label transfer {out[init]['label transfer %']:5.1f} %  {seconds:5.2f} s/shape  "
              f"fallbacks {len(out[init]['fallbacks'])}", flush=True)
    return out


#: the template `correspond` chooses in each class (its Chamfer medoid), for `--starts`
MEDOIDS = {"cat": "cat0", "dog": "dog5", "centaur": "centaur4", "horse": "horse6"}


def run_starts(name: str) -> dict:
    """The spectral start alone (functional_map.spectral_start, no NICP): the class's medoid's
    ground-truth points (every 6th common point) carried to every other shape, true error %
    of the diagonal (input frames: TOSCA files share up and facing) and CPU seconds per
    shape (the shape's spectrum and the map; the template's spectrum once)."""
    from shapegen_core.correspond.functional_map import spectral_shape, spectral_start

    meshes, maps = tosca_class(name)
    t = [m.name for m in meshes].index(MEDOIDS[name])
    template = spectral_shape(meshes[t].vertices, meshes[t].faces)
    common = np.arange(0, len(maps[t]), 6)
    errors, seconds = {}, []
    for mesh, truth in zip(meshes, maps):
        if mesh is meshes[t]:
            continue
        cpu = time.process_time()
        start = spectral_start(template, meshes[t].vertices[maps[t][common]], spectral_shape(mesh.vertices, mesh.faces))
        seconds.append(time.process_time() - cpu)
        errors[mesh.name] = (float("nan") if start.points is None else
                             100 * float(np.linalg.norm(start.points - mesh.vertices[truth[common]], axis=1).mean()
                                         / mesh.bbox_diagonal()))
    out = {"mean %": float(np.nanmean(list(errors.values()))), "per shape %": errors,
           "cpu s/shape": float(np.mean(seconds))}
    print(f"start {name:8s} mean {out['mean %']:5.2f} %  {out['cpu s/shape']:4.2f} CPU s/shape  "
          + " ".join(f"{n}:{e:.1f}" for n, e in errors.items()), flush=True)
    return out


def _settings(initialisation: str) -> CorrespondenceSettings:
    if initialisation == "closest":
        return CorrespondenceSettings()
    return CorrespondenceSettings.from_dict({"data_term": {"initialisation": initialisation}})


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--classes", nargs="*", default=list(TOSCA_CLASSES))
    parser.add_argument("--initialisation", nargs="+", default=["closest", "spectral"])
    parser.add_argument("--shapes", type=int, default=None, help="first N shapes of each class")
    parser.add_argument("--landmarks", type=int, default=800)
    parser.add_argument("--vases", type=int, default=0, help="also N procedural vases")
    parser.add_argument("--starts", action="store_true", help="the spectral start alone on the TOSCA classes")
    parser.add_argument("--psb", nargs="*", default=[], help="also these PSB classes (label transfer)")
    args = parser.parse_args(argv)
    OUTPUT.mkdir(exist_ok=True)
    report = {}
    for name in args.classes:
        if args.starts:
            report[f"start {name}"] = run_starts(name)
        else:
            report[f"TOSCA {name}"] = run_tosca(name, args.initialisation, args.shapes, args.landmarks)
    if args.vases:
        report["vases"] = run_vases(args.vases, args.initialisation)
    for name in args.psb:
        report[f"PSB {name}"] = run_psb(name, args.initialisation, args.shapes)
    (OUTPUT / f"spectral_probe_{os.getpid()}.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
