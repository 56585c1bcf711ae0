"""`shapegen sample`: N new meshes from a model file, each through the quality gate
(core/generate/sampling.py: next template, stiffer, redraw, within the run's pooled draw
budget), in worker processes (`--jobs`) or on a Dask cluster (`--scheduler`); registered
by cli_generate.py. Written into a staged folder moved into place when every file
succeeded."""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..base.child_process import exit_with_parent
from ..base.npzfile import save_npz
from ..generate.quality import QualitySettings
from ..generate.sampling import (GatedSample, draw_budget, gate_summary, gated_slots, pooled_samples, redraw_seed,
                                 rejection_lines, shortfall)
from ..meshes.labels import write_label_file, written_face_labels
from ..meshes.writing import MeshWriters
from .cli_common import CommandError, StagedOutput, settings_from_args
from .sample_batch import cluster_sampler, contiguous_chunks
from .shape_model import GenerativeShapeModel

__all__ = ["cmd_sample"]


@dataclass(frozen=True)
class SampleRun:
    """What every sample of one `shapegen sample` run shares (sent to worker processes)."""

    count: int
    first_seed: int
    template: str | None
    folder: str
    file_format: str
    smooth: int
    exact: bool
    quality: str  # QualitySettings as JSON


def _gated_chunk(model, run: SampleRun, slots) -> list[GatedSample]:
    """One round's `slots` ((index, draws) pairs) of `run`, gated (core/generate/sampling.py); a
    passing sample is written into the run's folder and returned without its mesh, a
    failing one returned with it (it may still pass in a later round)."""
    settings = QualitySettings.from_json(run.quality)
    writers = MeshWriters(model.meshes, model.file_axes)
    return [_written(writers, run, sample) if sample.quality.ok else sample
            for sample in gated_slots(model, run.count, run.first_seed, slots, run.template, settings, run.smooth,
                                      run.exact)]


def _written(writers: MeshWriters, run: SampleRun, sample: GatedSample, folder: Path | None = None) -> GatedSample:
    """Write `sample`'s mesh into `folder` (default: the run's); the sample without its mesh."""
    writers.write(sample.mesh, sample.template_index,
                  Path(folder or run.folder) / f"{sample.name}.{run.file_format}")
    return replace(sample, mesh=None)


_WORKER_MODEL = None


def _init_sample_worker(model_path: str) -> None:
    global _WORKER_MODEL
    exit_with_parent()
    _WORKER_MODEL = GenerativeShapeModel.load(Path(model_path))


def _sample_chunk(run: SampleRun, slots) -> list[GatedSample]:
    return _gated_chunk(_WORKER_MODEL, run, slots)


@contextmanager
def _single_threaded_blas():
    """OPENBLAS_NUM_THREADS=1 while worker processes start: spawned workers inherit it
    before they load numpy (set inside a worker it comes too late), so `jobs` workers
    share the cores instead of each running OpenBLAS on all of them."""
    previous = os.environ.get("OPENBLAS_NUM_THREADS")
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    try:
        yield
    finally:
        if previous is None:
            del os.environ["OPENBLAS_NUM_THREADS"]
        else:
            os.environ["OPENBLAS_NUM_THREADS"] = previous


def _first_templates(model, run: SampleRun) -> list[int]:
    """The template of each sample's first draw (what most samples keep)."""
    first = []
    for index in range(run.count):
        landmarks, _ = model.sample(1, np.random.default_rng(redraw_seed(run.first_seed, run.count, index, 0)))
        first.append(int(model.template_order(landmarks[0], run.template)[0]))
    return first


@contextmanager
def _round_gate(args, model, run: SampleRun, templates: list):
    """The gate of one round of `pooled_samples` for this run: in this process, in
    `args.jobs` processes when there are many samples, or on the Dask cluster
    `args.scheduler` (core/app/sample_batch.py; the meshes come back and passing ones are
    written here, so workers need no shared file system). The pool or cluster stays open
    for every round. Each worker gets a contiguous run of the round's samples sorted by
    the template of their first draw (`templates`), so it builds the mesh maps of few
    templates."""
    def by_template(slots):
        return sorted(slots, key=lambda slot: (templates[slot[0]], slot[0])) if templates else list(slots)

    if args.scheduler is not None:
        writers = MeshWriters(model.meshes, model.file_axes)
        with cluster_sampler(args.scheduler, args.model) as gated:
            yield lambda slots: [_written(writers, run, sample) if sample.quality.ok else sample
                                 for sample in gated(run, by_template(slots))]
        return
    jobs = args.jobs or (os.cpu_count() or 1)
    if jobs == 1 or run.count < 64:
        yield lambda slots: _gated_chunk(model, run, slots)
        return
    context = multiprocessing.get_context("spawn")
    with _single_threaded_blas(), ProcessPoolExecutor(jobs, mp_context=context, initializer=_init_sample_worker,
                                                      initargs=(str(args.model),)) as pool:
        def gate(slots):
            done = [pool.submit(_sample_chunk, run, chunk) for chunk in contiguous_chunks(by_template(slots), jobs)]
            return [sample for future in done for sample in future.result()]
        yield gate


def _write_samples(args, model, run: SampleRun, templates: list) -> list[GatedSample]:
    """Draw, gate, mesh and write every sample within the run's pooled draw budget
    (core/generate/sampling.py, `pooled_samples`; `_round_gate` says where); the samples in order,
    passing ones written and without their meshes, failing ones with theirs."""
    budget = draw_budget(run.count, QualitySettings.from_json(run.quality))
    with _round_gate(args, model, run, templates) as gate:
        return pooled_samples(run.count, budget, gate)


def _write_sample_labels(model, samples, folder: Path, file_format: str) -> None:
    """`<sample>_labels.txt` for every sample: the parts of its template's faces, in the
    written file's face order (core/meshes/labels.py)."""
    names, parts = list(model.part_labels.names), model.part_labels.parts
    by_template: dict[int, np.ndarray] = {}
    for sample in samples:
        index = sample.template_index
        if index not in by_template:
            by_template[index] = written_face_labels(model.meshes[index], parts[index], file_format)
        write_label_file(folder / f"{sample.name}_labels.txt", names, by_template[index])


def _sample_arrays(model, samples, seed: int) -> dict:
    """The arrays of a `landmarks.npz` (format shapegen.samples) for `samples`: each one's
    name, landmarks, latent, template, kept seed, meshing stiffness and the gate's reasons
    ("" when it passes), and every mesh refused on their way (`rejected_sample`: the index
    of its sample in the run)."""
    rejected = [(s.index, r) for s in samples for r in s.rejected]
    return {"names": np.asarray([s.name for s in samples]),
            "landmarks": np.stack([s.landmarks for s in samples]),
            "latents": np.stack([s.latent for s in samples]),
            "templates": np.asarray([model.names[s.template_index] for s in samples]),
            "seeds": np.asarray([s.seed for s in samples], dtype=np.int64),
            "quality": np.asarray(["; ".join(s.quality.reasons) for s in samples], dtype=str),
            "rejected_sample": np.asarray([i for i, _ in rejected], dtype=np.int64),
            "rejected_seed": np.asarray([r.seed for _, r in rejected], dtype=np.int64),
            "rejected_template": np.asarray([r.template for _, r in rejected], dtype=str),
            "rejected_reasons": np.asarray(["; ".join(r.reasons) for _, r in rejected], dtype=str),
            "rejected_stiffness": np.asarray([r.stiffness for _, r in rejected], dtype=np.float64),
            "stiffness": np.asarray([s.stiffness for s in samples], dtype=np.float64),
            "seed": np.asarray(seed), "model_type": np.asarray(model.model_type)}


def _keep_failed(args, model, run: SampleRun, samples, staging: Path) -> None:
    """The output folder of a run whose samples did not all pass, with --keep-failed: only
    `failed/`, holding each failing sample's last mesh (and labels with --labels), its
    records in `landmarks.npz` and `reasons.txt` (one line per sample: its seed, template,
    draws and the gate's reasons); the passing samples' files are removed, since a run
    short of N is not written."""
    for path in staging.iterdir():
        path.unlink()
    failing = [s for s in samples if not s.quality.ok]
    folder = staging / "failed"
    folder.mkdir()
    writers = MeshWriters(model.meshes, model.file_axes)
    for sample in failing:
        _written(writers, run, sample, folder)
    save_npz(folder / "landmarks.npz", "shapegen.samples", 1, _sample_arrays(model, failing, args.seed))
    (folder / "reasons.txt").write_text("".join(
        f"{s.name}: seed {s.seed} on {model.names[s.template_index]}"
        f"{f' (stiffness {s.stiffness:g})' if s.stiffer else ''} after {s.draws} draw(s): "
        f"{s.quality.summary()}\n" for s in failing))
    if args.labels:
        _write_sample_labels(model, failing, folder, args.format)


def cmd_sample(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    if args.n < 1:
        raise CommandError(f"-n must be at least 1, got {args.n}")
    quality = settings_from_args(QualitySettings, args)
    model = GenerativeShapeModel.load(args.model)
    if args.labels and model.part_labels is None:
        raise CommandError(f"{args.model}: --labels: the model records no part labels (fit it from a folder with "
                           "<name>_labels.txt beside the meshes)")
    if args.template is not None:
        model.template_order(model.training_points[0], args.template)  # an unknown name fails before any work
    run = SampleRun(args.n, args.seed, args.template, "", args.format, args.smooth, args.exact, quality.to_json())
    budget = draw_budget(args.n, quality)
    samples = failure = None
    try:
        with StagedOutput(args.output) as staging:
            jobs = args.jobs or (os.cpu_count() or 1)
            templates = _first_templates(model, run) if jobs > 1 and run.count >= 64 else []
            samples = _write_samples(args, model, replace(run, folder=str(staging)), templates)
            failure = shortfall(samples, budget)
            if failure and not args.keep_failed:
                raise CommandError(f"{failure}; nothing written (--max-redraws {quality.max_redraws}: "
                                   f"{quality.max_redraws + 1} draws per sample, pooled; --keep-failed writes the "
                                   "failing ones to failed/)")
            if failure:
                _keep_failed(args, model, run, samples, staging)
            else:
                save_npz(staging / "landmarks.npz", "shapegen.samples", 1, _sample_arrays(model, samples, args.seed))
                if args.labels:
                    _write_sample_labels(model, samples, staging, args.format)
    finally:
        if samples is not None:  # what the gate did, also when the run falls short
            print(gate_summary(samples))
            for line in rejection_lines(samples):
                print(f"  {line}")
    if failure:
        raise CommandError(f"{failure}; the failing ones are in {Path(args.output) / 'failed'}, nothing else written")
    seconds = time.perf_counter() - start
    print(f"wrote {args.n} {args.format.upper()} meshes + landmarks.npz{' + part labels' if args.labels else ''} -> "
          f"{args.output} "
          f"({seconds:.1f} s, {1000 * seconds / args.n:.1f} ms per sample)")
    return 0
