"""Part labels of the PSB files as the benchmarks score them (numpy and trimesh only, so
that bench/label_transfer_regression.py can use it with the core of any revision)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def face_labels(off_path: Path, mesh) -> np.ndarray:
    """Part label of every face of `mesh` (as the core read it) from `<stem>_labels.txt`:
    blocks of a part-name line followed by a line of 1-based face ids of the file; a face
    the reader changed (no face of the file with its corners) maps to "?"."""
    import trimesh

    lines = [ln.strip() for ln in (off_path.parent / f"{off_path.stem}_labels.txt").read_text().splitlines()
             if ln.strip()]
    original = trimesh.load(str(off_path), force="mesh", process=False, maintain_order=True).faces
    labels = np.full(len(original), "?", dtype=object)
    for name, ids in zip(lines[0::2], lines[1::2]):
        labels[np.asarray(ids.split(), dtype=np.int64) - 1] = name
    index = {tuple(f): i for i, f in enumerate(original.tolist())}
    return np.array([labels[index[tuple(f)]] if tuple(f) in index else "?" for f in mesh.faces.tolist()])
