"""Orientation benchmark: how many shapes Prepare turns, how many it restores,
flags and leaves in a wrong pose, for several versions of the core in one run: the
working tree ("after") and git revisions given by --revisions NAME=REV (default: "old",
consensus from each shape's PCA pose, commit 5a0b44e, and "main", the default before
the symmetry stage, commit 5dbb1d5), each imported as its own package.

Sets:
  (a) procedural classes generated upright and facing +x (vases; barrels, nearly
      symmetric top-to-bottom), random size and position, at --seeds seeds;
  (b) the same with a known subset (--perturbed shapes) turned by a random one of the 23
      non-identity axis rotations (axis permutations, half turns), or by a random turn
      about up of 45°-315° (every third perturbed shape);
  (c) the real PSB classes (files y-up: --up y);
  (d) mugs modelled in Blender through bpy (bench/blender_mugs.py `model_mugs`: quads,
      32-gon caps, UVs, a material, a handle as a second part; plain, mirrored, parented,
      rotated and subdivided objects, all +Z up facing +x in world coordinates), read as
      the add-on reads them, at --mug-seeds seeds; the same with a known subset turned
      (upside down, on its side, a quarter or three-eighths turn about up) or mirrored;
      and the same with every mug turned about up at random (objects scattered over a
      scene), "restored" counting those that end in the collection's pose;
  (e) the PSB classes with every file turned about its own up at random (the up its
      version's Prepare found for the file as it is), at --turned-seeds seeds: "wrong" =
      shapes that end visibly away from that version's result for the files as they are,
      after one common turn (the rotation between the two moves the shape's own surface
      more than a 20° turn about up does, by self-Chamfer distance, and by more than
      VISIBLE_CHAMFER: a round cup may end at any turn, a cup's handle may not).

Counts per set: "changed" = shapes whose rotation is not the up rotation alone; "wrong" =
shapes whose pose (canonical frame → prepared frame) is more than 20° from the
collection's pose, defined as the pose most shapes share to within 20° (sets a, b, d
know every shape's canonical frame); "flagged" = pose_outlier flags (versions without
them: 0); for perturbed sets also perturbed shapes restored and unperturbed shapes
moved. PSB has no canonical frame: the counts are changed and flagged; wrong ones are
counted on the rendered pictures (render mode: every version drawn, turned shapes red,
flagged ones marked "!"). A table of all rows is printed at the end.

    python bench/orientation.py [--seeds 20] [--mug-seeds 10] [--shapes 12] [--no-render] [--sets a c d e]
        [--turned-seeds 4]
        [--classes Cup Vase] [--revisions old=5a0b44e main=5dbb1d5] [--methods main after]

Writes <out>/orientation_<Class>_<version>.png in render mode (needs bpy).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # shared_data: the real collections
from shared_data import missing, shared_path  # noqa: E402

try:
    import shapegen_core
except ImportError:  # not installed: use the source tree
    shapegen_core = importlib.import_module("core")
    sys.modules["shapegen_core"] = shapegen_core
from shapegen_core.demo_data import make_barrels, make_vases  # noqa: E402
from shapegen_core.meshes.reading import read_folder  # noqa: E402
from shapegen_core.preprocess import ShapeTransform, prepare_collection  # noqa: E402
from shapegen_core.preprocess.rotations import AXIS_ROTATIONS, up_rotation, yaw_rotation  # noqa: E402

REVISIONS = {"old": "5a0b44e", "main": "5dbb1d5"}  # old default; the default before the symmetry stage
CLASSES = ("Fish", "Vase", "Airplane", "Cup")
COLUMNS = 8
WRONG_DEGREES = 20.0
#: self-Chamfer distance (samples of unit RMS radius) below which a turn of a shape is
#: invisible whatever a 20° turn about up does (set e)
VISIBLE_CHAMFER = 0.01
ROWS: list[dict] = []  # every measured row, printed as one table at the end


def load_revision(name: str, revision: str):
    """prepare_collection of the core at `revision` (git archive) imported as its own package."""
    folder = Path(tempfile.mkdtemp(prefix=f"shapegen_{name}_"))
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision, "core"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    package = f"shapegen_{name}"
    spec = importlib.util.spec_from_file_location(package, folder / "core" / "__init__.py",
                                                  submodule_search_locations=[str(folder / "core")])
    module = importlib.util.module_from_spec(spec)
    sys.modules[package] = module
    spec.loader.exec_module(module)
    return importlib.import_module(f"{package}.preprocess").prepare_collection


def angle(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def wrong_shapes(poses: list[np.ndarray]) -> list[bool]:
    """Whether each shape is more than WRONG_DEGREES from the pose most shapes share (to
    WRONG_DEGREES)."""
    close = np.array([[angle(a @ b.T) <= WRONG_DEGREES for b in poses] for a in poses])
    reference = poses[int(np.argmax(close.sum(axis=1)))]
    return [angle(p @ reference.T) > WRONG_DEGREES for p in poses]


def upright(kind: str, n: int, seed: int):
    """Consistent input: canonical (upright, facing +x) shapes, random size and position."""
    rng = np.random.default_rng(1000 + seed)
    meshes = make_barrels(n, seed=seed, pose=False) if kind == "barrels" else \
        [v.mesh for v in make_vases(n, seed=seed, resolution=(12, 18), pose=False)]
    return [m.with_vertices(ShapeTransform(np.eye(3), rng.uniform(0.5, 2), rng.uniform(-1, 1, 3))
                            .to_normalised(m.vertices)) for m in meshes]


def perturbations(n: int, count: int, seed: int) -> dict[int, np.ndarray]:
    """A known subset of `count` shapes and the turn applied to each."""
    rng = np.random.default_rng(2000 + seed)
    chosen = rng.choice(n, count, replace=False)
    return {int(i): (yaw_rotation(float(rng.uniform(45, 315))) if k % 3 == 2 else AXIS_ROTATIONS[rng.integers(1, 24)])
            for k, i in enumerate(chosen)}


MIRROR_X = np.diag([-1.0, 1.0, 1.0])


def mug_perturbations(n: int, count: int, seed: int) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """(world maps applied to a known subset of mugs, the proper turn each amounts to): upside
    down, on its side, a quarter or three-eighths turn about up, a mirror across the yz
    plane (a mug is symmetric across its handle's plane xz, so the mirror amounts to a
    half turn about up)."""
    rng = np.random.default_rng(3000 + seed)
    chosen = rng.choice(n, count, replace=False)
    kinds = [AXIS_ROTATIONS[4], AXIS_ROTATIONS[int(rng.integers(8, 24))], yaw_rotation(90.0), MIRROR_X,
             yaw_rotation(135.0)]
    maps = {int(i): kinds[k % len(kinds)] for k, i in enumerate(chosen)}
    return maps, {i: (yaw_rotation(180.0) if m is MIRROR_X else m) for i, m in maps.items()}


class Counts:
    """Counts of one set and version over seeds (module docstring)."""

    def __init__(self, label: str, version: str, perturbed: bool):
        self.label, self.version, self.perturbed = label, version, perturbed
        self.shapes = self.changed = self.wrong = self.flagged = self.restored = self.turned = self.moved = 0
        self.seconds, self.runs = 0.0, 0

    def add(self, prepared, turns: dict[int, np.ndarray], seconds: float) -> None:
        poses = [s.transform.rotation @ turns.get(i, np.eye(3)) for i, s in enumerate(prepared)]
        moved = [not np.allclose(s.transform.rotation, np.eye(3), atol=1e-12) for s in prepared]
        off = wrong_shapes(poses)
        self.shapes += len(prepared)
        self.changed += sum(moved)
        self.wrong += sum(off)
        self.flagged += sum(bool(getattr(s, "pose_outlier", "")) for s in prepared)
        self.restored += sum(not off[i] for i in turns)
        self.turned += len(turns)
        self.moved += sum(t for i, t in enumerate(moved) if i not in turns)
        self.seconds += seconds
        self.runs += 1

    def report(self) -> None:
        extra = f", restored {self.restored}/{self.turned}, unperturbed moved {self.moved}" if self.perturbed else ""
        print(f"{self.label:26s} {self.version:6s}: {self.shapes} shapes ({self.runs} seeds), changed {self.changed}, "
              f"wrong {self.wrong}, flagged {self.flagged}{extra}; {self.seconds / max(self.runs, 1):.1f} s per "
              "collection", flush=True)
        ROWS.append({"set": self.label, "version": self.version, "shapes": self.shapes, "seeds": self.runs,
                     "changed": self.changed, "restored": f"{self.restored}/{self.turned}" if self.perturbed else "",
                     "moved": self.moved if self.perturbed else "", "flagged": self.flagged, "wrong": self.wrong,
                     "seconds": self.seconds / max(self.runs, 1)})


def run(prepare, meshes, up: str):
    start = time.perf_counter()
    prepared = prepare(meshes, up_axis=up)
    return prepared, time.perf_counter() - start


def procedural(kind: str, seeds: int, n: int, count: int, methods: dict) -> None:
    for perturbed in (False, True):
        label = f"({'b' if perturbed else 'a'}) {kind}{' perturbed' if perturbed else ''}"
        counts = {name: Counts(label, name, perturbed) for name in methods}
        for seed in range(seeds):
            meshes = upright(kind, n, seed)
            turns = perturbations(n, count, seed) if perturbed else {}
            meshes = [m.with_vertices(m.vertices @ turns[i].T) if i in turns else m for i, m in enumerate(meshes)]
            for name, prepare in methods.items():
                prepared, seconds = run(prepare, meshes, "z")
                counts[name].add(prepared, turns, seconds)
        for c in counts.values():
            c.report()


def mug_turns(n: int, seed: int) -> dict[int, np.ndarray]:
    """Every mug turned about up by a random angle (objects scattered over a scene)."""
    rng = np.random.default_rng(4000 + seed)
    return {i: yaw_rotation(float(rng.uniform(0.0, 360.0))) for i in range(n)}


def blender(seeds: int, n: int, count: int, methods: dict) -> None:
    """Set (d): mugs modelled in Blender (consistent, a perturbed subset, all turned about up)."""
    from blender_mugs import model_mugs

    for variant in ("", " perturbed", " turned"):
        label = f"(d) Blender mugs{variant}"
        counts = {name: Counts(label, name, bool(variant)) for name in methods}
        for seed in range(seeds):
            if variant == " perturbed":
                maps, turns = mug_perturbations(n, count, seed)
            else:
                maps = turns = mug_turns(n, seed) if variant else {}
            meshes, _ = model_mugs(n, seed, maps)
            for name, prepare in methods.items():
                prepared, seconds = run(prepare, meshes, "z")
                counts[name].add(prepared, turns, seconds)
                if name == "after":
                    for i, s in enumerate(prepared):
                        if s.pose_change or s.pose_outlier:
                            print(f"      seed {seed} {s.name}{' (perturbed)' if i in turns else ''}: "
                                  f"{s.pose_change or '-'} | {s.pose_outlier or '-'}")
        for c in counts.values():
            c.report()


#: what sets (c) and (e) share, read and prepared once: class -> meshes, and
#: (class, version) -> (that version's result for the files as they are, seconds)
PSB_MESHES: dict[str, list] = {}
PSB_AS_FILED: dict[tuple[str, str], tuple[list, float]] = {}


def psb_classes(data: Path, classes, label: str):
    """(class, its meshes) for every PSB class (main checked that each folder is there)."""
    for cls in classes:
        folder = data / cls
        if cls not in PSB_MESHES:
            PSB_MESHES[cls] = read_folder(folder)
        yield cls, PSB_MESHES[cls]


def as_filed(cls: str, meshes, name: str, prepare, up: str):
    """Version `name`'s Prepare of the class's files as they are, and its seconds (run once)."""
    if (cls, name) not in PSB_AS_FILED:
        PSB_AS_FILED[cls, name] = run(prepare, meshes, up)
    return PSB_AS_FILED[cls, name]


def psb(data: Path, classes, up: str, methods: dict, out: Path, can_render: bool, oblique: bool) -> None:
    for cls, meshes in psb_classes(data, classes, "(c)"):
        for name, prepare in methods.items():
            prepared, seconds = as_filed(cls, meshes, name, prepare, up)
            base = up_rotation(up)
            turned = [not np.allclose(s.transform.rotation, base, atol=1e-12) for s in prepared]
            flags = [s.name for s in prepared if getattr(s, "pose_outlier", "")]
            print(f"(c) {cls:16s} {name:6s}: {len(prepared)} shapes, changed {sum(turned)}, flagged {len(flags)}"
                  f" ({' '.join(flags) or '-'}); {seconds:.1f} s", flush=True)
            ROWS.append({"set": f"(c) PSB {cls}", "version": name, "shapes": len(prepared), "seeds": 1,
                         "changed": sum(turned), "restored": "", "moved": "", "flagged": len(flags),
                         "wrong": "(pictures)", "seconds": seconds})
            for s in prepared:
                if getattr(s, "pose_change", "") or getattr(s, "pose_outlier", ""):
                    print(f"      {s.name}: {s.pose_change or '-'} | {s.pose_outlier or '-'}")
            if can_render:
                render(prepared, turned, flags, out / f"orientation_{cls}_{name}.png",
                       f"{cls}: {name} (red = turned, ! = flagged)")
                if oblique:
                    render(prepared, turned, flags, out / f"orientation_{cls}_{name}_oblique.png",
                           f"{cls}: {name}, seen from front-left, above", OBLIQUE)


def turned_psb(data: Path, classes, up: str, methods: dict, seeds: int) -> None:
    """Set (e): every PSB file turned about its own up at random (module docstring)."""
    from shapegen_core.geometry.chamfer import chamfer_distance
    from scipy.spatial import cKDTree

    for cls, meshes in psb_classes(data, classes, "(e)"):
        for name, prepare in methods.items():
            filed, _ = as_filed(cls, meshes, name, prepare, up)
            poses = [s.transform.rotation for s in filed]  # file -> prepared frame
            samples = []
            for s in filed:
                x = s.mesh.sample_surface(2000, np.random.default_rng(0)).points
                x = x - x.mean(axis=0)
                samples.append(x / np.sqrt((x ** 2).sum(axis=1).mean()))
            trees = [cKDTree(x) for x in samples]

            def moves(j: int, rotation: np.ndarray) -> float:
                return chamfer_distance(samples[j], samples[j], rotation, trees[j], trees[j])

            visible = [max(moves(j, yaw_rotation(WRONG_DEGREES)), VISIBLE_CHAMFER) for j in range(len(meshes))]
            wrong = flagged = changed = 0
            seconds = 0.0
            for seed in range(seeds):
                angles = np.random.default_rng(5000 + seed).uniform(0.0, 360.0, len(meshes))
                turns = [pose.T @ yaw_rotation(a) @ pose for pose, a in zip(poses, angles)]
                prepared, spent = run(prepare, [m.with_vertices(m.vertices @ t.T) for m, t in zip(meshes, turns)], up)
                relative = [s.transform.rotation @ t @ pose.T for s, t, pose in zip(prepared, turns, poses)]
                off = min(([j for j in range(len(meshes)) if moves(j, common.T @ relative[j]) > visible[j]]
                           for common in relative), key=len)
                wrong, seconds = wrong + len(off), seconds + spent
                flagged += sum(bool(getattr(s, "pose_outlier", "")) for s in prepared)
                changed += sum(bool(getattr(s, "pose_change", "")) for s in prepared)
                for j in off:
                    print(f"      seed {seed} {meshes[j].name}: {getattr(prepared[j], 'pose_change', '') or '-'} | "
                          f"{getattr(prepared[j], 'pose_outlier', '') or '-'}")
            print(f"(e) {cls:16s} {name:6s}: {len(meshes)} shapes ({seeds} seeds), changed {changed}, wrong {wrong}, "
                  f"flagged {flagged}; {seconds / max(seeds, 1):.1f} s per collection", flush=True)
            ROWS.append({"set": f"(e) PSB {cls} turned", "version": name, "shapes": len(meshes) * seeds,
                         "seeds": seeds, "changed": changed, "restored": "", "moved": "", "flagged": flagged,
                         "wrong": wrong, "seconds": seconds / max(seeds, 1)})


def table() -> None:
    """Every row measured, as one markdown table."""
    print("\n| set | version | shapes (seeds) | changed | restored | unperturbed moved | flagged | wrong "
          "| s / collection |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in ROWS:
        print(f"| {r['set']} | {r['version']} | {r['shapes']} ({r['seeds']}) | {r['changed']} | {r['restored']} | "
              f"{r['moved']} | {r['flagged']} | {r['wrong']} | {r['seconds']:.1f} |")


#: the oblique view: shapes turned 35° about up, then tilted 25° towards the camera
OBLIQUE = np.array([[np.cos(np.radians(-35)), -np.sin(np.radians(-35)), 0.0],
                    [np.sin(np.radians(-35)), np.cos(np.radians(-35)), 0.0], [0.0, 0.0, 1.0]])
OBLIQUE = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(np.radians(25)), -np.sin(np.radians(25))],
                    [0.0, np.sin(np.radians(25)), np.cos(np.radians(25))]]) @ OBLIQUE


def render(prepared, turned, flagged, path: Path, title: str, view: np.ndarray | None = None) -> None:
    """Grid picture of prepared shapes (normalised frame), front view (or the shapes first
    turned by `view`), Workbench."""
    import bpy

    if view is not None:
        prepared = [SimpleNamespace(mesh=s.mesh.with_vertices(s.mesh.vertices @ view.T), name=s.name) for s in prepared]

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    extents = np.array([np.ptp(s.mesh.vertices[np.unique(s.mesh.faces)], axis=0) for s in prepared])
    step = 1.25 * float(extents[:, [0, 2]].max())
    rows = (len(prepared) + COLUMNS - 1) // COLUMNS

    def text(body, size, location, colour):
        curve = bpy.data.curves.new(f"text_{body}", type="FONT")
        curve.body, curve.size = body, size
        obj = bpy.data.objects.new(f"text_{body}", curve)
        obj.location, obj.rotation_euler, obj.color = location, (np.pi / 2, 0.0, 0.0), colour
        scene.collection.objects.link(obj)

    for i, (shape, red) in enumerate(zip(prepared, turned)):
        mesh = bpy.data.meshes.new(shape.name)
        mesh.from_pydata(shape.mesh.vertices.tolist(), [], shape.mesh.faces.tolist())
        mesh.update()
        obj = bpy.data.objects.new(shape.name, mesh)
        x, z = (i % COLUMNS) * step, -(i // COLUMNS) * step
        obj.location = (x, 0.0, z)
        obj.color = (0.85, 0.25, 0.2, 1.0) if red else (0.75, 0.75, 0.78, 1.0)
        scene.collection.objects.link(obj)
        text(shape.name + (" !" if shape.name in flagged else ""), 0.1 * step,
             (x - 0.4 * step, -0.5 * step, z - 0.15 * step), (0.1, 0.1, 0.1, 1.0))
    text(title, 0.15 * step, (-0.45 * step, -0.5 * step, step), (0.0, 0.0, 0.0, 1.0))

    camera_data = bpy.data.cameras.new("camera")
    camera_data.type = "ORTHO"
    camera_data.ortho_scale = 1.05 * max(COLUMNS * step, (rows * step + 0.4 * step) * 16 / 9)
    camera_data.clip_end = 100.0 * step
    camera = bpy.data.objects.new("camera", camera_data)
    camera.location = ((COLUMNS - 1) * step / 2, -10.0 * step, -(rows - 1) * step / 2 + 0.35 * step)
    camera.rotation_euler = (np.pi / 2, 0.0, 0.0)  # looks along +y, z up
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "OBJECT"
    scene.render.resolution_x, scene.render.resolution_y = 1600, 900
    world = bpy.data.worlds.new("world")
    world.color = (1.0, 1.0, 1.0)
    scene.world = world
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=shared_path("psb"), help="the PSB folder (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench_output")
    parser.add_argument("--classes", nargs="+", default=list(CLASSES))
    parser.add_argument("--up", default="y")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--shapes", type=int, default=12)
    parser.add_argument("--perturbed", type=int, default=3)
    parser.add_argument("--mugs", type=int, default=14, help="mugs per Blender collection (set d)")
    parser.add_argument("--mugs-perturbed", type=int, default=4)
    parser.add_argument("--mug-seeds", type=int, default=10, help="Blender collections per variant (set d)")
    parser.add_argument("--sets", nargs="+", default=["a", "c", "d", "e"], help="a (with b), c, d, e")
    parser.add_argument("--turned-seeds", type=int, default=4, help="random turns of every PSB file (set e)")
    parser.add_argument("--revisions", nargs="+", default=[f"{k}={v}" for k, v in REVISIONS.items()],
                        help="NAME=REV: versions of the core to compare with the working tree ('after')")
    parser.add_argument("--methods", nargs="+", default=None, help="versions to run (default: all)")
    parser.add_argument("--no-render", action="store_true")
    parser.add_argument("--oblique", action="store_true", help="also draw each PSB class from front-left, above")
    args = parser.parse_args(argv)
    if "c" in args.sets or "e" in args.sets:
        for cls in args.classes:
            if missing(args.data / cls):
                raise SystemExit(f"orientation.py: {missing(args.data / cls)}")
    revisions = dict(item.split("=", 1) for item in args.revisions)
    names = args.methods or [*revisions, "after"]
    methods = {name: prepare_collection if name == "after" else load_revision(name, revisions[name]) for name in names}
    can_render = False
    if not args.no_render and "c" in args.sets:
        try:
            import bpy  # noqa: F401

            can_render = True
            args.out.mkdir(parents=True, exist_ok=True)
        except ImportError:
            print("bpy not importable: counts only, no pictures", file=sys.stderr)
    if "a" in args.sets:
        for kind in ("vases", "barrels"):
            procedural(kind, args.seeds, args.shapes, args.perturbed, methods)
    if "d" in args.sets:
        if importlib.util.find_spec("bpy") is None:
            print("(d) bpy not importable: the Blender-made set is skipped", file=sys.stderr)
        else:
            blender(args.mug_seeds, args.mugs, args.mugs_perturbed, methods)
    if "c" in args.sets:
        psb(args.data, args.classes, args.up, methods, args.out, can_render, args.oblique)
    if "e" in args.sets:
        turned_psb(args.data, args.classes, args.up, methods, args.turned_seeds)
    table()
    return 0


if __name__ == "__main__":
    sys.exit(main())
