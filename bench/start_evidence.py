"""What a collection says about its own pose variation, per class of
bench/correspondence_truth.py: the evidence `initialisation="auto"` decides from.

    python bench/start_evidence.py [--classes a,b] [--quick] [--psb-shapes N]

Per shape against the Chamfer-medoid template (the template correspondence uses):
intrinsic distance (Laplace–Beltrami eigenvalues of the unit-area surfaces, mean |log
ratio|: shape DNA, Reuter et al. 2006; bending leaves it unchanged), extrinsic distance
(symmetric Chamfer of the prepared landmark clouds, RMS, over the template's RMS radius),
and per class the medians and their ratio. Writes bench_output/start_evidence.json.
Not part of the tests."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes  # noqa: E402
from shapegen_core.correspond.start import pose_evidence  # noqa: E402
from shapegen_core.correspond.groupwise import chamfer_medoid  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from correspondence_truth import LANDMARKS, OUTPUT, classes  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--classes", default=None)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--psb-shapes", type=int, default=None)
    args = parser.parse_args()
    only = None if args.classes is None else set(args.classes.split(","))
    report = {}
    for name, make in classes(args.quick, only, args.psb_shapes):
        bench = make()
        prepared = prepare_meshes(bench.meshes, PrepareSettings(n_landmarks=LANDMARKS, up_axis=bench.up_axis, seed=0))
        start = time.perf_counter()
        t = chamfer_medoid([l.points for l in prepared.landmarks])
        evidence = pose_evidence([s.mesh for s in prepared.shapes], [l.points for l in prepared.landmarks], t)
        seconds = time.perf_counter() - start
        report[name] = {**evidence.summary(), "seconds": seconds, "template": prepared.names[t],
                        "intrinsic": evidence.intrinsic.tolist(), "extrinsic": evidence.extrinsic.tolist()}
        print(f"{name:16s} {evidence.describe()}  ({seconds:.1f} s)", flush=True)
        OUTPUT.mkdir(exist_ok=True)
        (OUTPUT / "start_evidence.json").write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
