"""How low can feature matches go? The true error when the profile feature is perfect.

`matching="features"` with `feature_between` > 0 compares where a point lies between the
turning lines of its region (core/correspond/turning.py). This diagnostic replaces that
computed position, on every target point, by what the procedural generator knows: the
true profile coordinate s of the point (core/demo_data/), times a weight W, so the
feature column is W · feature_between · s. Everything else is the default feature-space
non-rigid ICP. The rows therefore bound what any better profile feature could give this
registration:

    python bench/correspondence_ceiling.py [--seeds 11 1 2 3 4] [--weights 3 10 30]

Rows per seed (6 vases, `make_vases(6, seed, resolution=(65, 130))`, 800 landmarks, the
Chamfer-medoid template): `features` (turning-line feature off), `features + between`
(the computed feature, `feature_between=1`), and per W two truth rows. "template own" is
what correspondence does with the feature: the first round compares sides only, later
rounds give the template the feature of the shape it was made from, at its landmarks (here
its true s). "template from population" is what it did before (git log -p docs/results.md,
Correspondence): the population's mean feature at the first round's matches. With the
truth every shape compares the feature with the full weight (the agreement weights of
features.py are set to 1). Columns: true error against the template's surface
coordinates (% of the diagonal; bench/correspondence_seeds.py counts the template's own
row as well, "others" leaves it out, "with a neck" keeps the others whose neck is a
turning line: on a vase whose lip is narrower than its neck, the generator's neck is a
point of an even taper that no geometry marks), its profile and angle parts (`decompose`), and the
mean |Δs| of the outer wall in thirds of the wall (belly to neck is one third).

How the truth gets in: `features.position_between_turning_lines`,
`groupwise.registration_frame`, `groupwise._template_between` and
`groupwise.agreement_weights` are wrapped while this script runs (registrations in this
process, jobs=1); a target point's true s is that of its closest point on the shape it
lies on, found among the collection's shapes by distance. Writes
bench_output/correspondence_ceiling.{json,txt}.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from correspondence import LANDMARKS, OUTPUT, console_log, decompose, error_vs_template  # noqa: E402

import shapegen_core.correspond.features as features  # noqa: E402
import shapegen_core.correspond.groupwise as groupwise  # noqa: E402
from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes  # noqa: E402
from shapegen_core.correspond import CorrespondenceSettings, chamfer_medoid, correspond  # noqa: E402
from shapegen_core.correspond.settings import DataTermSettings  # noqa: E402
from shapegen_core.demo_data import PROFILE_BREAKS, make_vases  # noqa: E402
from shapegen_core.geometry import TargetSurface  # noqa: E402

#: the outer wall's s-range (core/demo_data/ PROFILE_BREAKS) and one third of it
WALL = (PROFILE_BREAKS[1], PROFILE_BREAKS[2])
WALL_THIRD = (WALL[1] - WALL[0]) / 3


class TruthProfile:
    """The true profile coordinate s at surface points of a procedural collection, in the
    normalised frame or in the registration frame of the rounds under way."""

    def __init__(self, prepared, shapes):
        self.shapes = shapes
        self.surfaces = [TargetSurface(p.mesh.vertices, p.mesh.faces) for p in prepared.shapes]
        self.frame = (np.zeros(3), 1.0)  # centre, scale of the registration frame

    def s_at(self, points: np.ndarray) -> np.ndarray:
        """s of points lying on one of the shapes (either frame), from the closest point of
        the shape and frame they lie on."""
        centre, scale = self.frame
        candidates = [points, points * scale + centre]
        probe = slice(0, min(64, len(points)))
        best = min(((surface.closest(frame[probe]).distance.mean(), m, k)
                    for m, surface in enumerate(self.surfaces) for k, frame in enumerate(candidates)))
        _, m, k = best
        placed = self.surfaces[m].closest(candidates[k])
        return self.shapes[m].surface_coordinates(placed.face_index, placed.barycentric)[:, 0]


def run(prepared, shapes, template: int, settings: CorrespondenceSettings, weight: float | None, own: bool):
    """correspond with the computed feature (weight None) or the truth × weight in its place."""
    if weight is None:
        return correspond(prepared, settings, template=prepared.names[template], jobs=1)
    truth = TruthProfile(prepared, shapes)
    landmarks = prepared.landmarks[template]
    own_s = shapes[template].surface_coordinates(landmarks.face_index, landmarks.barycentric)[:, 0]
    saved = (features.position_between_turning_lines, groupwise.registration_frame, groupwise._template_between,
             groupwise.agreement_weights)

    def frame(points, name):
        truth.frame = saved[1](points, name)
        return truth.frame

    def template_between(outcome, start):
        if own:
            return weight * own_s
        return np.mean([r.between for r in groupwise._fitting(outcome.results, outcome.keep)], axis=0)

    features.position_between_turning_lines = lambda points, normals: weight * truth.s_at(points)
    groupwise.registration_frame, groupwise._template_between = frame, template_between
    groupwise.agreement_weights = lambda template, shapes: np.ones(len(shapes))
    try:
        return correspond(prepared, settings, template=prepared.names[template], jobs=1)
    finally:
        (features.position_between_turning_lines, groupwise.registration_frame, groupwise._template_between,
         groupwise.agreement_weights) = saved


def one_collection(seed: int, weights: list[float]) -> dict:
    shapes = make_vases(6, seed=seed, resolution=(65, 130))
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=LANDMARKS, seed=0))
    template = chamfer_medoid([l.points for l in prepared.landmarks])
    landmarks = prepared.landmarks[template]
    s_template = shapes[template].surface_coordinates(landmarks.face_index, landmarks.barycentric)[:, 0]
    on_wall = (s_template > WALL[0]) & (s_template < WALL[1])
    # shapes other than the template whose neck is a turning line: the lip is wider than the neck
    necked = np.array([m != template and s.params.lip_radius > s.params.neck_radius for m, s in enumerate(shapes)])
    plain = CorrespondenceSettings(data_term=DataTermSettings(matching="features", feature_between=0.0))
    between = CorrespondenceSettings(data_term=DataTermSettings(matching="features", feature_between=1.0))
    variants = [("features", plain, None, False), ("features + between", between, None, False)]
    for w in weights:
        variants += [(f"truth s x {w:g}, template from population", between, w, False),
                     (f"truth s x {w:g}, template own", between, w, True)]
    rows = {}
    for name, settings, weight, own in variants:
        result = run(prepared, shapes, template, settings, weight, own)
        points = np.stack([s.transform.to_input(p) for s, p in zip(prepared.shapes, result.points)])
        error = error_vs_template(shapes, template, landmarks, points)
        parts = decompose(shapes, template, landmarks, result.face_index, result.barycentric)
        ds = [np.abs(shapes[m].surface_coordinates(result.face_index[m], result.barycentric[m])[on_wall, 0]
                     - s_template[on_wall]).mean() / WALL_THIRD for m in range(len(shapes)) if m != template]
        rows[name] = {"error_pct": 100 * float(error.mean()),
                      "others_pct": 100 * float(np.delete(error, template).mean()),
                      "with_neck_pct": 100 * float(error[necked].mean()),
                      "profile_pct": parts["profile (s)"], "angle_pct": parts["angle (θ)"],
                      "wall_ds_thirds": float(np.mean(ds))}
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[11, 1, 2, 3, 4])
    parser.add_argument("--weights", type=float, nargs="+", default=[3.0, 10.0, 30.0])
    args = parser.parse_args()
    OUTPUT.mkdir(exist_ok=True)
    log, lines = console_log()
    log(f"6 procedural vases per seed, {LANDMARKS} landmarks; errors in % of the diagonal, |Δs| in wall thirds")
    log("| variant | seed | error | others | with a neck | profile part | angle part | wall abs(Δs) |")
    log("|---|---|---|---|---|---|---|---|")
    report = {}
    columns = ("error_pct", "others_pct", "with_neck_pct", "profile_pct", "angle_pct", "wall_ds_thirds")
    for seed in args.seeds:
        report[seed] = one_collection(seed, args.weights)
        for name, r in report[seed].items():
            log(f"| {name} | {seed} | " + " | ".join(f"{r[c]:.3f}" for c in columns) + " |")
    for name in report[args.seeds[0]]:
        log(f"| {name} | mean | " + " | ".join(f"{np.mean([report[s][name][c] for s in args.seeds]):.3f}"
                                             for c in columns) + " |")
    (OUTPUT / "correspondence_ceiling.json").write_text(json.dumps(report, indent=2))
    (OUTPUT / "correspondence_ceiling.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
