"""Batch meshing of sampled landmark sets on a Dask cluster (issue 15): `shapegen sample
--scheduler tcp://host:8786` (or local:N). The model file's bytes go to every worker once;
each worker meshes a contiguous run of the samples (sorted by template, so it builds few
mesh maps) and returns the vertices, which this process writes, so the workers need no
shared file system. Same meshes as the local process pool (the same code on the same
inputs)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

from .cluster import connect

__all__ = ["mesh_on_cluster"]


def _mesh_run(model_bytes: bytes, items: Sequence, smooth: int, exact: bool) -> list[tuple[str, np.ndarray]]:
    """A worker's run: (name, vertices) of every (name, landmarks, template) item."""
    from .pipeline import GenerativeShapeModel

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "model.npz"
        path.write_bytes(model_bytes)
        model = GenerativeShapeModel.load(path)
    return [(name, model.mesh_from_landmarks(landmarks, template=template, smooth=smooth, exact=exact,
                                             name=name).vertices)
            for name, landmarks, template in items]


def mesh_on_cluster(scheduler: str, model_path: str | Path, items: list, smooth: int, exact: bool,
                    runs: int | None = None) -> list[tuple[str, np.ndarray]]:
    """(name, vertices) of every (name, landmarks, template) item, in order, meshed on the
    Dask cluster `scheduler` in `runs` contiguous runs (default: one per worker thread)."""
    from .cli_generate import contiguous_chunks

    with connect(scheduler) as client:
        runs = runs or max(1, sum(client.nthreads().values()))
        model = client.scatter(Path(model_path).read_bytes(), broadcast=True)
        futures = [client.submit(_mesh_run, model, chunk, smooth, exact, pure=False)
                   for chunk in contiguous_chunks(items, runs)]
        return [pair for future in futures for pair in future.result()]
