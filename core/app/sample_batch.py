"""Gated sampling on a Dask cluster: `shapegen sample --scheduler tcp://host:8786`
(or local:N). The model file's bytes go to every worker once; in each round of the run's
pooled draw budget (core/generate/sampling.py, `pooled_samples`) each worker draws, gates and meshes
a contiguous run of the round's samples (sorted by template so it builds few mesh maps) and
returns them with their meshes, which the calling process writes, so the workers need no
shared file system. Same samples as the local process pool: sample i of a run depends only
on its seeds (the same code on the same inputs)."""

from __future__ import annotations

import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Sequence

from ..base.cluster import connect
from ..generate.quality import QualitySettings
from ..generate.sampling import GatedSample, gated_slots

__all__ = ["contiguous_chunks", "cluster_sampler"]


def contiguous_chunks(items: list, parts: int) -> list[list]:
    """`items` cut into at most `parts` contiguous runs of (nearly) equal length."""
    size = -(-len(items) // parts)
    return [items[i:i + size] for i in range(0, len(items), size)]


def _gated_run(model_bytes: bytes, run, slots: Sequence[tuple[int, range]]) -> list[GatedSample]:
    """A worker's part of a round: `slots` ((index, draws) pairs) of `run`
    (cli_generate.SampleRun), gated, with meshes."""
    from .shape_model import GenerativeShapeModel

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "model.npz"
        path.write_bytes(model_bytes)
        model = GenerativeShapeModel.load(path)
    return gated_slots(model, run.count, run.first_seed, slots, run.template, QualitySettings.from_json(run.quality),
                       run.smooth, run.exact)


@contextmanager
def cluster_sampler(scheduler: str, model_path: str | Path, runs: int | None = None):
    """The Dask cluster `scheduler` with the model file `model_path` on every worker, open
    for every round of a run: yields `gated(run, slots)`, one round's `slots` of `run`
    gated and meshed on the cluster in `runs` contiguous runs (default: one per worker
    thread), in the order of `slots`."""
    with connect(scheduler) as client:
        runs = runs or max(1, sum(client.nthreads().values()))
        model = client.scatter(Path(model_path).read_bytes(), broadcast=True)

        def gated(run, slots: list[tuple[int, range]]) -> list[GatedSample]:
            futures = [client.submit(_gated_run, model, run, chunk, pure=False)
                       for chunk in contiguous_chunks(slots, runs)]
            return [sample for future in futures for sample in future.result()]

        yield gated
