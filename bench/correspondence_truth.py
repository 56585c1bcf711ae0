"""Correspondence across classes against the truth: one table, method × class.

    python bench/correspondence_truth.py [--quick] [--method NAME:key=value,...] [--classes a,b]
                                         [--rows closest,spectral,auto] [--psb-shapes N]
                                         [--seed N] [--output NAME]

Writes bench_output/correspondence_truth.{json,txt} (--output: bench_output/NAME.{json,txt}).
Not part of the tests.

Seeds: --seed (default 0) is Prepare's `seed`, the one random choice of a run: the
surface samples of the pose evidence and each shape's landmarks (shape i's from seed + i).
The correspondence itself is deterministic (its samples have fixed seeds), and the
classes' shapes do not change with it (the procedural ones are generated from seed 11).
Two runs with different seeds of the same method measure its run-to-run noise.

Classes (one PrepareSettings for all but the up axis their files use; no setting tuned
per class):
* procedural vases (core/demo_data/ `make_vases`), handled mugs (`make_handled_mugs`: a
  handle at a shape-specific height, walls leaning in and out) and quadrupeds
  (`make_quadrupeds`: not a body of revolution; neck and tail raised by per-shape angles).
  True error: landmark i of shape m against the point of m at the surface coordinates of
  landmark i on the template shape (the coordinates of the generator's parametrisation).
* TOSCA cat, centaur, dog, horse (the real collections, tests/shared_data.py; one animal
  in many poses, z up).
  True error: landmark i of the template goes to its nearest common point k of the class
  (`corres/<name>.vts`), whose point on shape m is the truth. The template landmark's own
  distance to its common point is the protocol's floor (logged). horse7.off is cut short
  mid-line and refused by the reader: left out (said in the log).
* TOSCA people (man + woman, one collection) and TOSCA gorilla (tosca/people):
  the truth runs across individuals (900 common points), scored as the animals. For every
  TOSCA class also the mirrored shapes (error against `.sym.vts` below MIRRORED × the error
  against `.vts`) and the field's unit: mean geodesic error ÷ √(surface area) × 100, the
  geodesic by Dijkstra on the mesh's edge graph (an approximation from above).
* PSB Vase, Cup, Fish, Airplane (psb/<Class>, up axis y): label transfer = share of
  landmarks whose part label on shape m is the label of landmark i on the template.

Shapes: --quick 5 per procedural class, 4 cats, 3 men + 3 women, 4 gorillas, 5 PSB vases;
full 10 per procedural class, every TOSCA shape, the first 10 of each PSB class
(--psb-shapes: another count). 800 landmarks (the default).
True error is the mean distance / the shape's bounding-box diagonal (%), averaged over the
shapes other than the template ("mean") and the worst shape's ("max"). Every row is scored
against its own landmarks on the template shape (the template shape is registered too, so
landmark i lies elsewhere on it from row to row). Time is the correspondence wall time
per shape in this process (jobs=1).

Methods:
* one row per choice of the start (`initialisation`: closest, spectral, auto), the
  default's first, marked "(default)", `CorrespondenceSettings()`;
* features: `matching="features"`;
* (groupwise refinement after NICP had a row, "population", until it was removed: it won
  no class beyond run-to-run noise, docs/results.md; the code before its removal is in git;)
* nricp_amberg: trimesh's, deforming the template mesh onto 2 shapes of each procedural
  class and 1 of each TOSCA class (--quick: 1; not on PSB: its dense meshes make it far
  from cheap), compared with closest points on the same pairs;
* (kernel warps, core/correspond/warps.py, had a row until they were removed: their
  figures are in docs/history.md, the code at bfbd68b;)
* any `--method NAME:key=value,...` (CorrespondenceSettings fields, values as JSON or words).
`--rows` runs only the rows named (nricp_amberg only when named).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes  # noqa: E402
from shapegen_core.correspond import CorrespondenceSettings, correspond  # noqa: E402
from shapegen_core.correspond.settings import DataTermSettings  # noqa: E402
from shapegen_core.demo_data import make_handled_mugs, make_quadrupeds, make_vases  # noqa: E402
from shapegen_core.base.errors import MeshFileError  # noqa: E402
from shapegen_core.geometry import TargetSurface  # noqa: E402
from shapegen_core.meshes.reading import read_folder, read_mesh  # noqa: E402
from shapegen_core.base.settings import nested_data  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # shared_data: the real collections
from correspondence import console_log, face_labels, nricp_baseline  # noqa: E402
from shared_data import folder_or_exit  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUTPUT = ROOT / "bench_output"
LANDMARKS = 800
JOBS = 1
#: a shape came out mirrored when its error against the mirrored truth (`.sym.vts`) is below
#: this times its error against the truth
MIRRORED = 0.8


# ---------------------------------------------------------------------------- classes
@dataclass
class BenchClass:
    """One class: its meshes (input frame), the up axis its files use, and a scorer
    `score(t, reference, m, points)`: the error of every landmark of shape m (`points`,
    input frame) given the same landmarks on the template shape t (`reference`): a true
    error (% of m's diagonal) or, for labels, 1 where the part label differs."""

    name: str
    meshes: list
    score: object
    measure: str = "error"  # "error" (% of the diagonal) or "labels" (transfer, %)
    up_axis: str = "z"
    notes: list = field(default_factory=list)


def _on_surface(mesh, points):
    placed = TargetSurface(mesh.vertices, mesh.faces).closest(np.asarray(points))
    return placed.face_index, placed.barycentric


def procedural_class(name: str, shapes) -> BenchClass:
    """A core/demo_data/ class with a parametrisation (ProceduralShape, PartedShape)."""

    def score(t, reference, m, points):
        coordinates = shapes[t].surface_coordinates(*_on_surface(shapes[t].mesh, reference))
        truth = shapes[m].points_at(coordinates)
        return 100 * np.linalg.norm(points - truth, axis=1) / shapes[m].mesh.bbox_diagonal()

    return BenchClass(name, [s.mesh for s in shapes], score)


def _edge_graph(mesh):
    """The mesh's edge graph (n × n, symmetric, weights the edge lengths)."""
    from scipy import sparse
    edges = np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]])
    lengths = np.linalg.norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]], axis=1)
    n = len(mesh.vertices)
    graph = sparse.coo_matrix((lengths, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    return graph.maximum(graph.T)


def geodesic_errors(mesh, truth_vertices, points, graph=None) -> np.ndarray:
    """Geodesic distance on `mesh` from each truth vertex to the vertex nearest the
    predicted point, by Dijkstra on the mesh's edge graph (an approximation from above of
    the surface geodesic: paths run along edges), one search per distinct truth vertex."""
    from scipy.sparse.csgraph import dijkstra
    graph = _edge_graph(mesh) if graph is None else graph
    nearest = cKDTree(mesh.vertices).query(np.asarray(points))[1]
    sources, inverse = np.unique(truth_vertices, return_inverse=True)
    distances = dijkstra(graph, directed=False, indices=sources)
    return distances[inverse, nearest]


def tosca_class(name: str, stems, folder: Path, limit: int | None) -> BenchClass:
    """TOSCA shapes `stems` of `folder` (ground truth `corres/<stem>.vts`, mirrored truth
    `corres/<stem>.sym.vts` where present): true error against the template landmark's
    nearest common point; beside it (`extras`) the error against the mirrored truth and the
    geodesic error ÷ √(surface area) × 100 (edge-graph geodesics)."""
    meshes, common, mirrored, notes = [], [], [], []
    for stem in stems:
        path = folder / f"{stem}.off"
        try:
            mesh = read_mesh(path)
        except MeshFileError as exc:
            notes.append(f"left out: {exc}")
            continue
        meshes.append(mesh)
        common.append(np.loadtxt(folder / "corres" / f"{stem}.vts", dtype=np.int64) - 1)
        sym = folder / "corres" / f"{stem}.sym.vts"
        mirrored.append(np.loadtxt(sym, dtype=np.int64) - 1 if sym.is_file() else None)
    meshes, common, mirrored = meshes[:limit], common[:limit], mirrored[:limit]
    floors, graphs = [], {}

    def truth_points(t, reference):
        distance, k = cKDTree(meshes[t].vertices[common[t]]).query(reference)
        return distance, k

    def score(t, reference, m, points):
        distance, k = truth_points(t, reference)
        floors.append(100 * distance.mean() / meshes[t].bbox_diagonal())
        truth = meshes[m].vertices[common[m][k]]
        return 100 * np.linalg.norm(points - truth, axis=1) / meshes[m].bbox_diagonal()

    def extras(t, reference, m, points) -> dict:
        _, k = truth_points(t, reference)
        out = {}
        if mirrored[m] is not None:
            truth = meshes[m].vertices[mirrored[m][k]]
            out["mirror_error"] = float((100 * np.linalg.norm(points - truth, axis=1) / meshes[m].bbox_diagonal()).mean())
        if m not in graphs:
            graphs[m] = _edge_graph(meshes[m])
        geodesic = geodesic_errors(meshes[m], common[m][k], points, graphs[m])
        out["geodesic"] = float(100 * geodesic.mean() / np.sqrt(meshes[m].area()))
        return out

    made = BenchClass(name, meshes, score, notes=notes)
    made.floors = floors
    made.extras = extras
    return made


def tosca_animal(animal: str, limit: int | None) -> BenchClass:
    """One TOSCA animal in many poses (tosca/<animal>)."""
    folder = folder_or_exit("tosca", animal)
    stems = sorted((p.stem for p in folder.glob("*.off")), key=lambda s: int(s[len(animal):]))
    return tosca_class(f"TOSCA {animal}", stems, folder, limit)


def tosca_people(kinds: tuple[str, ...], name: str, limit: int | None) -> BenchClass:
    """TOSCA's people (tosca/people): the shapes whose names hold one of
    `kinds` ("man", "woman", "gorilla"), truth across individuals (900 common points)."""
    folder = folder_or_exit("tosca", "people")
    stems = sorted(p.stem for p in folder.glob("*.off") if p.stem.split("_")[1] in kinds)
    if limit is not None:  # a quick run keeps every kind
        by_kind = [[s for s in stems if s.split("_")[1] == kind] for kind in kinds]
        stems = sorted(s for group in by_kind for s in group[:max(2, limit // len(kinds))])
    return tosca_class(name, stems, folder, None)


def psb_class(folder: Path, limit: int | None) -> BenchClass:
    meshes = read_folder(folder)[:limit]
    labels = [face_labels(folder / f"{m.name}.off", m) for m in meshes]

    def score(t, reference, m, points):
        reference_labels = labels[t][_on_surface(meshes[t], reference)[0]]
        return 100.0 * (labels[m][_on_surface(meshes[m], points)[0]] != reference_labels)

    return BenchClass(f"PSB {folder.name}", meshes, score, measure="labels", up_axis="y")


def classes(quick: bool, only: set | None, psb_shapes: int | None = None) -> list:
    """(name, maker) of every class, the small procedural ones first, then the TOSCA
    animals, then PSB (the report is written after every class: a run cut short keeps
    what it measured)."""
    n, psb_default = (5, 5) if quick else (10, 10)
    psb_shapes = psb_default if psb_shapes is None else psb_shapes
    makers = {
        "vases": lambda: procedural_class("vases", make_vases(n, seed=11, resolution=(40, 80))),
        "handled mugs": lambda: procedural_class("handled mugs", make_handled_mugs(n, seed=11)),
        "quadrupeds": lambda: procedural_class("quadrupeds", make_quadrupeds(n, seed=11)),
    }
    for animal in (["cat"] if quick else ["cat", "centaur", "dog", "horse"]):
        makers[f"TOSCA {animal}"] = lambda animal=animal: tosca_animal(animal, 4 if quick else None)
    makers["TOSCA people"] = lambda: tosca_people(("man", "woman"), "TOSCA people", 6 if quick else None)
    makers["TOSCA gorilla"] = lambda: tosca_people(("gorilla",), "TOSCA gorilla", 4 if quick else None)
    for folder in (["Vase"] if quick else ["Vase", "Cup", "Fish", "Airplane"]):
        makers[f"PSB {folder}"] = lambda folder=folder: psb_class(folder_or_exit("psb", folder), psb_shapes)
    return [(name, make) for name, make in makers.items() if only is None or name in only]


# ---------------------------------------------------------------------------- methods
def parse_method(text: str) -> tuple[str, dict]:
    """`NAME:key=value,...` → (NAME, CorrespondenceSettings options: flat names of before or
    dotted places, e.g. alpha_end=3 or stiffness.alpha_end=3); values are JSON (numbers,
    true, null) or else words."""
    name, _, body = text.partition(":")
    options = {}
    for item in filter(None, body.split(",")):
        key, _, value = item.partition("=")
        try:
            options[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            options[key.strip()] = None if value.strip() == "None" else value.strip()
    options = nested_data(options)
    CorrespondenceSettings.from_dict(options)  # a wrong name or value fails here, before any work
    return name, options


def settings_methods(extra: list) -> dict:
    """Name → CorrespondenceSettings options of the methods run through `correspond`: one
    row per choice of the start (`data_term.initialisation`), the default's first and
    marked, then feature matches and the `extra` methods."""
    default = CorrespondenceSettings().data_term.initialisation
    choices = next(f.metadata.get("choices") or (f.default,) for f in fields(DataTermSettings)
                   if f.name == "initialisation")
    methods = {f"{default} (default)": {}}
    methods.update({choice: {"initialisation": choice} for choice in choices if choice != default})
    methods["features"] = {"matching": "features"}
    methods.update(parse_method(text) for text in extra)
    return methods


def chosen_rows(methods: dict, rows: str | None) -> tuple[dict, bool]:
    """(the methods named in `rows`, comma-separated names or their first words, e.g.
    "closest,spectral,auto"; whether nricp_amberg runs). None: all."""
    if rows is None:
        return methods, True
    wanted = [r.strip() for r in rows.split(",") if r.strip()]
    kept = {name: options for name, options in methods.items() if name in wanted or name.split()[0] in wanted}
    return kept, "nricp_amberg" in wanted


def summary(bench: BenchClass, t: int, reference, points_input, seconds: float, shapes=None) -> dict:
    """Per-shape mean scores of shapes `shapes` (default: all but the template t)."""
    shapes = [m for m in range(len(points_input)) if m != t] if shapes is None else shapes
    per_shape = [float(bench.score(t, reference, m, points_input[m]).mean()) for m in shapes]
    if bench.measure == "labels":
        per_shape = [100.0 - e for e in per_shape]
    out = {"mean": float(np.mean(per_shape)), "max": float(np.max(per_shape)) if bench.measure == "error"
           else float(np.min(per_shape)), "per_shape": per_shape, "seconds_per_shape": float(seconds),
           "shapes": shapes}
    extras = getattr(bench, "extras", None)
    if extras is not None:
        found = [extras(t, reference, m, points_input[m]) for m in shapes]
        out["geodesic_per_shape"] = [f["geodesic"] for f in found]
        out["geodesic"] = float(np.mean(out["geodesic_per_shape"]))
        if all("mirror_error" in f for f in found):
            out["mirror_error_per_shape"] = [f["mirror_error"] for f in found]
            out["mirrored_shapes"] = [bench.meshes[m].name for m, f, e in zip(shapes, found, per_shape)
                                      if f["mirror_error"] < MIRRORED * e]
            out["mirrored"] = len(out["mirrored_shapes"])
    return out


def run_class(bench: BenchClass, methods: dict, nricp_pairs: int, log, seed: int = 0) -> dict:
    start = time.perf_counter()
    prepared = prepare_meshes(bench.meshes, PrepareSettings(n_landmarks=LANDMARKS, up_axis=bench.up_axis, seed=seed))
    vertices = [m.n_vertices for m in bench.meshes]
    log(f"\n== {bench.name}: {len(bench.meshes)} shapes, {min(vertices)}–{max(vertices)} vertices, prepare "
        f"{time.perf_counter() - start:.1f} s" + "".join(f"; {note}" for note in bench.notes))
    rows, template = {}, None
    for name, options in methods.items():
        start = time.perf_counter()
        messages = []
        result = correspond(prepared, CorrespondenceSettings.from_dict(options), template=template, jobs=JOBS,
                            progress=lambda fraction, message: messages.append(message))
        seconds = (time.perf_counter() - start) / len(bench.meshes)
        if template is None:
            template = result.template_name
            t = result.names.index(template)
            reference = result.points_input[t]
            default = result, seconds
        # each row against its own template landmarks: the template shape is registered in
        # every round too, so where landmark i lies on it differs from row to row
        rows[name] = summary(bench, t, result.points_input[t], result.points_input, seconds)
        rows[name]["outliers"] = int(result.outliers.sum())
        rows[name]["starts"] = [m for m in messages if "start" in m and ": " in m]
        log(row_text(name, rows[name], bench.measure))
    if nricp_pairs and bench.measure == "error":
        targets = [m for m in range(len(bench.meshes)) if m != t][:nricp_pairs]
        theirs = nricp_baseline(prepared, t, targets)
        points = {m: prepared.shapes[m].transform.to_input(theirs[m][0]) for m in targets}
        lm = prepared.shapes[t].transform.to_input(prepared.landmarks[t].points)
        seconds = float(np.mean([theirs[m][3] for m in targets]))
        rows["nricp_amberg"] = summary(bench, t, lm, points, seconds, shapes=targets)
        rows["nricp_amberg"]["pairs"] = len(targets)
        same = summary(bench, t, reference, default[0].points_input, default[1], shapes=targets)
        rows["nricp_amberg"]["closest_same_pairs"] = same["mean"]
        log(row_text(f"nricp_amberg ({len(targets)} pairs)", rows["nricp_amberg"], bench.measure)
            + f"   (closest on the same pairs {same['mean']:.2f})")
    floors = getattr(bench, "floors", [])
    out = {"shapes": len(bench.meshes), "template": template, "measure": bench.measure, "methods": rows,
           "notes": bench.notes}
    if floors:
        out["protocol_floor_pct"] = float(np.mean(floors))
        log(f"protocol floor (template landmark to its nearest common point): {np.mean(floors):.2f} %")
    return out


def row_text(name: str, row: dict, measure: str) -> str:
    if measure == "labels":
        return f"  {name:26s} label transfer {row['mean']:5.1f} % (worst shape {row['max']:5.1f} %)   " \
               f"{row['seconds_per_shape']:6.2f} s/shape"
    text = f"  {name:26s} true error {row['mean']:6.2f} % (worst shape {row['max']:6.2f} %)   " \
           f"{row['seconds_per_shape']:6.2f} s/shape"
    if "geodesic" in row:
        text += f"   geodesic/√area {row['geodesic']:5.2f}"
    if "mirrored" in row:
        text += f"   mirrored {row['mirrored']} of {len(row['per_shape'])}" + \
            (f" ({', '.join(row['mirrored_shapes'])})" if row["mirrored"] else "")
    return text


# ---------------------------------------------------------------------------- the table
def table(report: dict) -> list[str]:
    """Method × class: mean / worst-shape true error (% of the diagonal) or label
    transfer (%), s/shape; last column the method's mean rank over the classes it ran on
    (1 best: lowest error, highest transfer)."""
    names = list(report["classes"])
    methods = []
    for c in report["classes"].values():
        methods += [m for m in c["methods"] if m not in methods]
    ranks = {m: [] for m in methods}
    for c in report["classes"].values():
        rows = {m: r for m, r in c["methods"].items() if m != "nricp_amberg"}
        order = sorted(rows, key=lambda m: -rows[m]["mean"] if c["measure"] == "labels" else rows[m]["mean"])
        for rank, m in enumerate(order, 1):
            ranks[m].append(rank)
    width = 20
    lines = ["method".ljust(20) + "".join(n.rjust(width) for n in names) + "   mean rank",
             " " * 20 + "".join(("transfer %, s" if report["classes"][n]["measure"] == "labels"
                                 else "mean/max %, s").rjust(width) for n in names)]
    for m in methods:
        cells = []
        for n in names:
            row = report["classes"][n]["methods"].get(m)
            if row is None:
                cells.append("—".rjust(width))
            elif report["classes"][n]["measure"] == "labels":
                cells.append(f"{row['mean']:.1f} {row['seconds_per_shape']:.1f}s".rjust(width))
            else:
                cells.append(f"{row['mean']:.2f}/{row['max']:.1f} {row['seconds_per_shape']:.1f}s".rjust(width))
        rank = f"{np.mean(ranks[m]):.2f}" if ranks[m] else "—"
        lines.append(m[:20].ljust(20) + "".join(cells) + rank.rjust(12))
    truth = [n for n in names if any("geodesic" in r for r in report["classes"][n]["methods"].values())]
    if truth:
        lines += ["", "geodesic error ÷ √(surface area) × 100 (edge-graph geodesics) / mirrored shapes "
                      f"(error against .sym.vts below {MIRRORED} × against .vts)",
                  "method".ljust(20) + "".join(n.rjust(width) for n in truth)]
        for m in methods:
            cells = []
            for n in truth:
                row = report["classes"][n]["methods"].get(m)
                if row is None or "geodesic" not in row:
                    cells.append("—".rjust(width))
                else:
                    mirrored = f"{row['mirrored']} of {len(row['per_shape'])}" if "mirrored" in row else "–"
                    cells.append(f"{row['geodesic']:.2f} / {mirrored}".rjust(width))
            lines.append(m[:20].ljust(20) + "".join(cells))
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer classes and shapes (a few minutes)")
    parser.add_argument("--method", action="append", default=[], metavar="NAME:key=value,...",
                        help="another row: CorrespondenceSettings fields (repeatable)")
    parser.add_argument("--classes", default=None, help="comma-separated class names (default: all)")
    parser.add_argument("--rows", default=None, metavar="NAMES",
                        help="comma-separated rows to run (e.g. closest,spectral,auto; nricp_amberg only when named; "
                             "default: all)")
    parser.add_argument("--psb-shapes", type=int, default=None, help="shapes per PSB class (default 10, --quick 5)")
    parser.add_argument("--seed", type=int, default=0, help="Prepare's seed: pose evidence samples and landmarks "
                                                                 "(default 0)")
    parser.add_argument("--output", default="correspondence_truth", metavar="NAME",
                        help="write bench_output/NAME.{json,txt} (default correspondence_truth)")
    parser.add_argument("--table", metavar="JSON", help="only print the table of a report (a run cut short too)")
    args = parser.parse_args()
    if args.table:
        print("\n".join(table(json.loads(Path(args.table).read_text()))))
        return 0
    methods, nricp = chosen_rows(settings_methods(args.method), args.rows)
    OUTPUT.mkdir(exist_ok=True)
    log, lines = console_log()
    report = {"quick": args.quick, "seed": args.seed, "landmarks": LANDMARKS, "jobs": JOBS, "numpy": np.__version__,
              "load_average_start": os.getloadavg()[0], "classes": {}}
    log(f"methods: {', '.join([*methods, *['nricp_amberg'][:nricp]])}; "
        f"{LANDMARKS} landmarks; jobs {JOBS}; Prepare's seed {args.seed}")
    only = None if args.classes is None else set(args.classes.split(","))
    for name, make in classes(args.quick, only, args.psb_shapes):
        pairs = (1 if args.quick or name.startswith("TOSCA") else 2) if nricp else 0
        report["classes"][name] = run_class(make(), methods, pairs, log, args.seed)
        (OUTPUT / f"{args.output}.json").write_text(json.dumps(report, indent=2))
    report["load_average_end"] = os.getloadavg()[0]
    log("\nmethod × class: true error mean/worst shape (% of the bounding-box diagonal) or PSB label transfer (%), "
        "seconds per shape; mean rank over the classes (nricp_amberg not ranked: 2 pairs)")
    for line in table(report):
        log(line)
    (OUTPUT / f"{args.output}.json").write_text(json.dumps(report, indent=2))
    (OUTPUT / f"{args.output}.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
