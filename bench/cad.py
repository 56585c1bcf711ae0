"""CAD-like collections in, clean meshes out.

    python bench/cad.py [--classes psb:Cup,psb:Vase,cups,vases] [-n 10] [--samples 8] [--picture]

Every class is made CAD-like the way large public CAD collections distribute models, then
written as OBJ files and read back through `reading.read_folder` (the CLI's reader):

* y up (procedural classes, built z up, are turned; PSB classes are y up already);
* a small extra part: a thin label (a box of 4 % of the height) standing off the side;
* double-sided: every face present twice, the copy wound the other way;
* a soup with UV seams: every triangle on its own three vertices and its own UVs (`v/vt`).

Per class: the intake's one-line message of the first file, the fit time (default
settings, `jobs=1`), and for `--samples` samples (`gated_samples`, seed 0): coincident
twin faces in the sample written through `MeshWriters` (the CLI's writer, counted on the
file's own vertices read back raw) and the gate's roughness ratio (mean angle between
adjacent face normals, sample over template). The same for the clean class (`clean` rows)
for comparison. `--picture` draws the first CAD sample of each class next to its template
(bench_output/cad.png). Writes bench_output/cad.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / ".pyshim"))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections

import numpy as np  # noqa: E402

from shapegen_core.preprocess.collection import PrepareSettings  # noqa: E402
from shapegen_core.meshes.writing import MeshWriters
from shapegen_core.meshes.reading import read_folder  # noqa: E402
from shapegen_core.meshes.mesh import Mesh  # noqa: E402
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.app.pipeline import fit_meshes  # noqa: E402
from shapegen_core.generate.quality import coincident_faces  # noqa: E402
from shapegen_core.generate.sampling import gated_samples  # noqa: E402
from shared_data import folder_or_exit  # noqa: E402

OUTPUT = ROOT / "bench_output"
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # (x, y, z) -> (x, z, -y)


def clean_class(name: str, n: int) -> tuple[list[Mesh], str]:
    """The class's first `n` meshes as they are, and their up axis."""
    if name.startswith("psb:"):
        return read_folder(folder_or_exit("psb", name[4:]))[:n], "y"
    if name == "vases":
        from shapegen_core.demo_data import make_vases

        return [s.mesh for s in make_vases(n, seed=0)], "z"
    if name == "cups":
        from shapegen_core.demo_data import make_cups

        return make_cups(n, seed=0), "z"
    raise SystemExit(f"unknown class {name!r} (psb:<Class>, vases, cups, blender:bottles)")


def label_part(mesh: Mesh, up: int) -> tuple[np.ndarray, np.ndarray]:
    """A thin box (4 % of the height) just off the side of the mesh's bounding box."""
    lo, hi = mesh.bounds()
    size = 0.04 * (hi[up] - lo[up])
    side = (up + 1) % 3
    centre = (lo + hi) / 2
    centre[side] = hi[side] + 0.02 * (hi[side] - lo[side]) + size / 2
    half = np.full(3, size / 2)
    half[side] = size / 20
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=float)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    triangles = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
    return centre + corners * half, triangles


def write_cad_obj(mesh: Mesh, path: Path, up_axis: str, rng: np.random.Generator) -> None:
    """`mesh` as a CAD file would have it (module docstring): y up, a label, double-sided,
    a soup with one UV per corner."""
    vertices = mesh.vertices @ Z_UP_TO_Y_UP.T if up_axis == "z" else mesh.vertices
    faces = mesh.faces
    as_y_up = Mesh(vertices, faces)
    label_vertices, label_faces = label_part(as_y_up, 1)
    vertices = np.concatenate([vertices, label_vertices])
    faces = np.concatenate([faces, label_faces + len(mesh.vertices)])
    faces = np.concatenate([faces, faces[:, [0, 2, 1]]])  # the back of every sheet
    corners = vertices[faces.ravel()]
    uv = rng.random((len(corners), 2))
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in corners]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uv]
    lines += [f"f {3 * i + 1}/{3 * i + 1} {3 * i + 2}/{3 * i + 2} {3 * i + 3}/{3 * i + 3}" for i in range(len(faces))]
    path.write_text("\n".join(lines) + "\n")


def written_twins(writers: MeshWriters, mesh: Mesh, template: int, path: Path) -> int:
    """Coincident face pairs in the sample as the CLI writes it to `path`, on the file's own
    vertices."""
    import trimesh

    path = writers.write(mesh, template, path)
    written = trimesh.load(path, process=False, force="mesh")
    return coincident_faces(np.asarray(written.vertices), np.asarray(written.faces))


def measure(meshes: list[Mesh], up_axis: str, n_samples: int, folder: Path) -> dict:
    start = time.perf_counter()
    model = fit_meshes(meshes, FitSettings(prepare=PrepareSettings(up_axis=up_axis)), jobs=1)
    fit_seconds = time.perf_counter() - start
    samples = gated_samples(model, n_samples, 0)
    writers = MeshWriters(model.meshes)
    twins = [written_twins(writers, s.mesh, s.template_index, folder / f"sample_{k}.obj") for k, s in enumerate(samples)]
    ratio = [s.quality.roughness_ratio for s in samples]
    return {"fit_seconds": fit_seconds, "twins_max": int(max(twins)), "roughness_median": float(np.median(ratio)),
            "roughness_max": float(np.max(ratio)),
            "redraws": int(sum(s.redraws for s in samples)),
            "failing": int(sum(not s.quality.ok for s in samples)), "model": model, "samples": samples}


def draw(panels: list[tuple[str, Mesh]], path: Path) -> None:
    """Flat-shaded pictures (light from the viewer's upper left) of meshes in the model's
    frame (z up), one per panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    figure = plt.figure(figsize=(4 * len(panels), 4.4))
    light = np.array([-0.5, -0.6, 0.6]) / np.linalg.norm([-0.5, -0.6, 0.6])
    for i, (title, mesh) in enumerate(panels):
        axes = figure.add_subplot(1, len(panels), i + 1, projection="3d")
        triangles = mesh.vertices[mesh.faces]
        shade = 0.25 + 0.75 * np.clip(mesh.face_normals() @ light, 0, 1)
        axes.add_collection3d(Poly3DCollection(triangles, facecolors=plt.cm.gray(shade), edgecolor="none"))
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        middle, half = (lo + hi) / 2, (hi - lo).max() / 2
        axes.set_xlim(middle[0] - half, middle[0] + half)
        axes.set_ylim(middle[1] - half, middle[1] + half)
        axes.set_zlim(middle[2] - half, middle[2] + half)
        axes.view_init(elev=20, azim=-60)
        axes.set_title(title, fontsize=9)
        axes.set_axis_off()
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


def thinnest_faces() -> None:
    """The thinnest face (shortest altitude / longest edge) of every clean mesh of PSB, TOSCA
    and the procedural classes, per class: intake.SLIVER_RATIO must stay below them all."""
    from shapegen_core.demo_data import make_barrels, make_cups, make_mugs, make_vases
    from shapegen_core.meshes.reading import list_mesh_files, read_mesh
    from shapegen_core.meshes.mesh import SLIVER_RATIO

    def ratios(mesh: Mesh) -> np.ndarray:
        corners = mesh.vertices[mesh.faces]
        edges = corners[:, [1, 2, 0]] - corners
        return 2 * mesh.face_areas() / np.einsum("fki,fki->fk", edges, edges).max(axis=1)

    classes = {folder.name: folder for root in (folder_or_exit("psb"), folder_or_exit("tosca"))
               for folder in sorted(root.iterdir()) if folder.is_dir()}
    print(f"{'class':>10} {'meshes':>6} {'thinnest':>9}  {'faces < SLIVER_RATIO':>20}")
    for name, folder in classes.items():
        meshes = []
        for path in list_mesh_files(folder):
            try:
                meshes.append(read_mesh(path))
            except Exception as exc:  # a damaged file of the real collections (TOSCA horse7) is named
                print(f"{'':>10} skipped: {exc}")
        values = [ratios(m) for m in meshes]
        dropped = sum(m.report.sliver_faces_dropped for m in meshes)  # read: loose slivers already left out
        print(f"{name:>10} {len(meshes):6d} {min(v.min() for v in values):9.2e}  "
              f"{dropped + sum(int((v < SLIVER_RATIO).sum()) for v in values):20d}")
    procedural = {"vases": [v.mesh for v in make_vases(20, seed=0)], "barrels": make_barrels(20, seed=0),
                  "cups": make_cups(20, seed=0), "mugs": make_mugs(10, seed=0)}
    for name, meshes in procedural.items():
        values = [ratios(m) for m in meshes]
        print(f"{name:>10} {len(meshes):6d} {min(v.min() for v in values):9.2e}  "
              f"{sum(int((v < SLIVER_RATIO).sum()) for v in values):20d}")


def cad_files(name: str, n: int, folder: Path, rng: np.random.Generator) -> tuple[list[Mesh], str]:
    """The class's CAD-like files written to `folder`: a real or procedural class made
    CAD-like (`write_cad_obj`), or the Blender bottles (bench/blender_cad.py); and the
    clean meshes it was made from with their up axis (none for the Blender class)."""
    if name == "blender:bottles":
        from blender_cad import write_bottles

        write_bottles(folder, n)
        return [], "y"
    meshes, up_axis = clean_class(name, n)
    for mesh in meshes:
        write_cad_obj(mesh, folder / f"{mesh.name}.obj", up_axis, rng)
    return meshes, up_axis


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--classes", default="psb:Cup,psb:Vase,cups,vases,blender:bottles")
    parser.add_argument("-n", type=int, default=10, help="shapes per class")
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--no-clean", action="store_true", help="skip the clean classes' rows")
    parser.add_argument("--picture", action="store_true")
    parser.add_argument("--thinnest", action="store_true", help="only: the thinnest face of each clean class")
    args = parser.parse_args()
    if args.thinnest:
        thinnest_faces()
        return 0
    OUTPUT.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    rows, panels = [], []
    print(f"{'class':>15} {'kind':>5} {'fit s':>6} {'twins':>5} {'rough med':>9} {'rough max':>9} "
          f"{'redraws':>7} {'failing':>7}", flush=True)
    for name in args.classes.split(","):
        with tempfile.TemporaryDirectory() as scratch:
            scratch = Path(scratch)
            (scratch / "in").mkdir()
            (scratch / "out").mkdir()
            meshes, up_axis = cad_files(name, args.n, scratch / "in", rng)
            cad = read_folder(scratch / "in")
            kinds = [("cad", cad, "y")] + ([] if args.no_clean or not meshes else [("clean", meshes, up_axis)])
            for kind, collection, up in kinds:
                result = measure(collection, up, args.samples, scratch / "out")
                row = {"class": name, "kind": kind, **{k: v for k, v in result.items() if k not in ("model", "samples")}}
                if kind == "cad":
                    row["intake"] = [m.report.summary() for m in cad]
                    first = result["samples"][0]
                    panels += [(f"{name} template", result["model"].meshes[first.template_index]),
                               (f"{name} CAD sample", first.mesh)]
                    if args.picture and name.startswith("blender:"):
                        render_blender_class(name, result, scratch)
                rows.append(row)
                print(f"{name:>15} {kind:>5} {row['fit_seconds']:6.1f} {row['twins_max']:5d} "
                      f"{row['roughness_median']:9.3f} {row['roughness_max']:9.3f} "
                      f"{row['redraws']:7d} {row['failing']:7d}", flush=True)
                if kind == "cad":
                    print(f"{'':>15} intake of {cad[0].name}: {row['intake'][0]}", flush=True)
    (OUTPUT / "cad.json").write_text(json.dumps(rows, indent=1))
    if args.picture and panels:
        draw(panels, OUTPUT / "cad.png")
        print(f"picture: {OUTPUT / 'cad.png'}")
    return 0


def render_blender_class(name: str, result: dict, scratch: Path) -> None:
    """Blender's Workbench render of the first file (the bouquet) and the first four
    samples' template files (top row), and the samples as written (bottom row), imported
    by Blender's OBJ importer (the files Y up, the samples in the model's frame, Z up)."""
    from blender_cad import render_files

    samples = result["samples"][:4]
    names = result["model"].names
    files = [names[0]] + [names[s.template_index] for s in samples]
    rows = [[(scratch / "in" / f"{n}.obj", "Y") for n in files],
            [(scratch / "out" / f"sample_{k}.obj", "Z") for k in range(len(samples))]]
    path = render_files(rows, OUTPUT / f"cad_{name.split(':')[1]}.png")
    print(f"render: {path} (top: {files}, bottom: samples 0-{len(samples) - 1})")

if __name__ == "__main__":
    sys.exit(main())
