"""Gated sampling on a Dask cluster (issue 15): `shapegen sample --scheduler tcp://host:8786`
(or local:N). The model file's bytes go to every worker once; each worker draws, gates and
meshes a contiguous run of the samples (core/sampling.py, sorted by template so it builds
few mesh maps) and returns them with their meshes, which the calling process writes, so
the workers need no shared file system. Same samples as the local process pool: sample i
of a run depends only on its seed (the same code on the same inputs)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Sequence

from .cluster import connect
from .quality import QualitySettings
from .sampling import GatedSample, gated_samples

__all__ = ["contiguous_chunks", "gated_samples_on_cluster"]


def contiguous_chunks(items: list, parts: int) -> list[list]:
    """`items` cut into at most `parts` contiguous runs of (nearly) equal length."""
    size = -(-len(items) // parts)
    return [items[i:i + size] for i in range(0, len(items), size)]


def _gated_run(model_bytes: bytes, run, indices: Sequence[int]) -> list[GatedSample]:
    """A worker's run: samples `indices` of `run` (cli_generate.SampleRun), gated, with meshes."""
    from .pipeline import GenerativeShapeModel

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "model.npz"
        path.write_bytes(model_bytes)
        model = GenerativeShapeModel.load(path)
    return gated_samples(model, run.count, run.first_seed, run.template, QualitySettings.from_json(run.quality),
                         run.smooth, run.exact, indices=indices)


def gated_samples_on_cluster(scheduler: str, model_path: str | Path, run, indices: list[int],
                             runs: int | None = None) -> list[GatedSample]:
    """Samples `indices` of `run`, gated and meshed on the Dask cluster `scheduler` in `runs`
    contiguous runs (default: one per worker thread), in the order of `indices`."""
    with connect(scheduler) as client:
        runs = runs or max(1, sum(client.nthreads().values()))
        model = client.scatter(Path(model_path).read_bytes(), broadcast=True)
        futures = [client.submit(_gated_run, model, run, chunk, pure=False)
                   for chunk in contiguous_chunks(indices, runs)]
        return [sample for future in futures for sample in future.result()]
