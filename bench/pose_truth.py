"""How far each TOSCA person lies turned from the template, before and after the
correspondence poses it by its landmarks (core/correspond/posing.py). Not part of the tests.

    shapegen prepare DIR --up z -o prepared.npz          # DIR: TOSCA man + woman files
    shapegen correspond prepared.npz --initialisation spectral -o corr.npz
    python bench/pose_truth.py prepared.npz corr.npz [--data FOLDER]   # default: tosca/people

The truth is TOSCA's common points (`corres/<name>.vts`, the same body point on every
person), not the landmarks: each shape's common points (prepared frame) are fitted rigidly
onto the template's (Kabsch). "up" is the angle between the shape's up axis and the
template's, "whole" the angle of that whole rotation; "before" as Prepare left the shape,
"after" moved by its recorded pose. Also per shape: its start, its true error (% of the
diagonal) and whether its map is mirrored (error against `.sym.vts` below 0.8 × against
`.vts`, as bench/correspondence_truth.py counts). Last, what a linear model sees: the
variance shares of the landmark matrix's first four principal directions, and how many
directions hold 80 % of the variance (the default latent dimension rule), unposed and posed.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from shapegen_core.preprocess.collection import PreparedCollection  # noqa: E402
from shapegen_core.correspond import Correspondence  # noqa: E402
from shapegen_core.correspond.posing import apply_pose, pose_angle, rigid_fit  # noqa: E402
from shapegen_core.meshes.reading import read_mesh  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # shared_data: the real collections
from shared_data import missing, shared_path  # noqa: E402


def up_and_whole(points: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """(degrees between the up axes, degrees of the whole rotation) of the rigid fit of
    `points` onto `reference`."""
    motion, _ = rigid_fit(points, reference)
    up = float(np.degrees(np.arccos(np.clip(motion[2, 2], -1.0, 1.0))))
    return up, pose_angle(motion)


def variance_shares(matrix: np.ndarray) -> tuple[np.ndarray, int]:
    """The first four principal directions' shares of the variance, and how many hold 80 %."""
    centred = matrix - matrix.mean(axis=0)
    shares = np.linalg.svd(centred, compute_uv=False) ** 2
    shares /= shares.sum()
    return shares[:4], int(np.searchsorted(np.cumsum(shares), 0.8) + 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("prepared", type=Path)
    parser.add_argument("correspondence", type=Path)
    parser.add_argument("--data", type=Path, default=shared_path("tosca", "people"),
                        help="the TOSCA people folder, with corres/ (default: %(default)s)")
    args = parser.parse_args()
    if missing(args.data):
        raise SystemExit(f"pose_truth.py: {missing(args.data)}")
    prepared, corr = PreparedCollection.load(args.prepared), Correspondence.load(args.correspondence)
    names, t = corr.names, corr.names.index(corr.template_name)
    meshes = {n: read_mesh(args.data / f"{n}.off") for n in names}
    vts = {n: np.loadtxt(args.data / "corres" / f"{n}.vts", dtype=np.int64) - 1 for n in names}
    sym = {n: np.loadtxt(args.data / "corres" / f"{n}.sym.vts", dtype=np.int64) - 1 for n in names}
    common = {n: shape.transform.to_normalised(meshes[n].vertices[vts[n]])
              for n, shape in zip(names, prepared.shapes)}
    _, nearest = cKDTree(meshes[names[t]].vertices[vts[names[t]]]).query(corr.points_input[t])
    print(f"template {names[t]}")
    print("| shape | start | true error % | mirrored | up: before → after (°) | whole: before → after (°) | note |")
    print("|---|---|---|---|---|---|---|")
    for i, n in enumerate(names):
        if i == t:
            continue
        diagonal = meshes[n].bbox_diagonal()
        error = np.linalg.norm(corr.points_input[i] - meshes[n].vertices[vts[n][nearest]], axis=1).mean() / diagonal
        mirror = np.linalg.norm(corr.points_input[i] - meshes[n].vertices[sym[n][nearest]], axis=1).mean() / diagonal
        before = up_and_whole(common[n], common[names[t]])
        after = up_and_whole(apply_pose(corr.model_poses[i], common[n]), common[names[t]])
        start = corr.recorded.shape_starts[i] if corr.recorded.shape_starts else "?"
        note = corr.recorded.pose_notes[i] if corr.recorded.pose_notes else ""
        print(f"| {n} | {start} | {100 * error:.1f} | {'yes' if mirror < 0.8 * error else ''} | "
              f"{before[0]:.0f} → {after[0]:.0f} | {before[1]:.0f} → {after[1]:.0f} | {note} |")
    print("\n| landmarks | variance share of principal directions 1-4 (%) | directions for 80 % |")
    print("|---|---|---|")
    for label, points in (("as Prepare left them", corr.points), ("posed by their landmarks", corr.model_points())):
        shares, count = variance_shares(points.reshape(len(points), -1))
        print(f"| {label} | {' / '.join(f'{100 * s:.1f}' for s in shares)} | {count} |")


if __name__ == "__main__":
    main()
