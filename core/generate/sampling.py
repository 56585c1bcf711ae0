"""Gated sampling: draw, mesh, check with the quality gate, and try again.

Sample i of a run with first seed S draws its latent vector from `default_rng(S + i)`, so a
sample is reproducible alone (the CLI, Blender's Sample and the benchmark give the same
shape for the same model and seed). Its landmarks are meshed on the nearest template
(`GenerativeShapeModel.template_order`) and checked (`quality.QualityGate`). When the mesh
fails:

1. when the template was chosen (nearest-data / nearest-latent, not a name), the same
   landmarks are meshed on the next-nearest templates, up to `TEMPLATES_TRIED` in all: a
   template whose correspondence landmarks cover it badly crumples where a neighbour
   does not (PSB Vase: 28 of 30 failing first meshes pass on the 2nd or 3rd template);
2. then on the same templates again at `QualitySettings.stiffer_remesh` times the model's
   final α (a stiffer mesh follows the landmarks less closely but does not fold; the
   sample records the α it was meshed with);
3. otherwise the sample is redrawn with seed S + r·n + i for redraw r = 1, 2, ... (unique
   in the run, independent of the order samples are made).

A run of n samples has a budget of `draw_budget` = n·(1 + `QualitySettings.max_redraws`)
draws, pooled over its samples (`pooled_samples`): every sample first gets 1 + max_redraws
draws (so a run whose samples all pass within them is what it was when the budget was per
sample); draws its passing samples left unused then go, in rounds, to the samples still
failing, shared equally (lowest index first). A class where most draws fold can still give
n good samples, and a run that cannot costs at most the budget. A sample still failing
when the budget is spent is a failure of the run: it is returned with its last mesh and
the gate's reasons, and callers must not use it as a good sample (`shapegen sample` writes
nothing and exits 2; Blender's Sample adds only the passing ones).

Every rejected mesh is recorded with its seed, template and the gate's reasons
(`Rejection`), so a run can say how many it redrew and why (`gate_summary`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from ..meshes.mesh import Mesh
from .quality import CRITERIA, MeshQuality, QualityGate, QualitySettings, training_extents

__all__ = ["Rejection", "GatedSample", "TEMPLATES_TRIED", "quality_gate", "redraw_seed", "gated_sample",
           "gated_samples", "gated_slots", "draw_budget", "pooled_samples", "gate_summary", "failed_reasons",
           "shortfall", "rejection_lines", "sample_name"]

#: Templates a sample's landmarks are meshed on (nearest first) before the sample is redrawn.
TEMPLATES_TRIED = 3


@dataclass(frozen=True)
class Rejection:
    """One mesh the gate refused: its draw's seed, its template, the final α it was meshed
    with (`stiffer`: above the model's) and the gate's reasons."""

    seed: int
    template: str
    reasons: tuple[str, ...]
    stiffness: float
    stiffer: bool = False

    def describe(self) -> str:
        """"seed S on TEMPLATE[ (stiffness A)]: reasons"."""
        where = f"seed {self.seed} on {self.template}" + (f" (stiffness {self.stiffness:g})" if self.stiffer else "")
        return f"{where}: " + "; ".join(self.reasons)


@dataclass
class GatedSample:
    """One sample as it was kept: its seed (the draw kept), landmarks (L, 3), latent (Q,),
    template index, mesh (None once written, e.g. by a worker process), the gate's verdict,
    the final α it was meshed with (`stiffer`: above the model's), and the meshes rejected
    on the way."""

    index: int
    name: str
    seed: int
    landmarks: np.ndarray
    latent: np.ndarray
    template_index: int
    mesh: Mesh | None
    quality: MeshQuality
    stiffness: float
    stiffer: bool = False
    rejected: list[Rejection] = field(default_factory=list)

    @property
    def redraws(self) -> int:
        """Draws with a new seed (re-meshing on another template is not a redraw)."""
        return len({r.seed for r in self.rejected if r.seed != self.seed})

    @property
    def draws(self) -> int:
        """Draws this sample used (its kept draw and every refused one; seeds are unique in
        a run)."""
        return len({r.seed for r in self.rejected} | {self.seed})


def quality_gate(model, settings: QualitySettings = QualitySettings()) -> QualityGate:
    """The gate of `model`'s samples: its training meshes as templates and their extents
    (the model's normalised frame, where samples are meshed). Kept on the model, one per
    settings."""
    cache = model.__dict__.setdefault("_quality_gates", {})
    if settings not in cache:
        cache[settings] = QualityGate(model.meshes, training_extents(model.meshes), settings)
    return cache[settings]


def sample_name(index: int) -> str:
    """The name (and file stem) of sample `index` of a run."""
    return f"sample_{index:04d}"


def redraw_seed(first_seed: int, count: int, index: int, redraw: int) -> int:
    """The seed of redraw `redraw` (0: the first draw) of sample `index` of `count`."""
    return int(first_seed) + int(redraw) * int(count) + int(index)


def _draw(model, seed: int) -> tuple[np.ndarray, np.ndarray]:
    landmarks, latents = model.sample(1, np.random.default_rng(seed))
    latent = latents[0] if latents is not None else model.encode(landmarks)[0]
    return landmarks[0], np.asarray(latent, dtype=np.float64)


def draw_budget(count: int, settings: QualitySettings = QualitySettings()) -> int:
    """Draws a run of `count` samples may make in all: 1 + max_redraws per sample, pooled."""
    return int(count) * (int(settings.max_redraws) + 1)


def gated_sample(model, index: int, first_seed: int, count: int, template: str | None = None,
                 settings: QualitySettings = QualitySettings(), smooth: int = 0, exact: bool = False,
                 name: str = "sample", redraws: range | None = None) -> GatedSample:
    """Sample `index` of a run of `count` from `first_seed`, gated (module docstring), with
    the draws `redraws` (0: the first; default 0 to max_redraws). When every draw fails the
    last mesh tried is returned, failing (its `quality` says why)."""
    gate = quality_gate(model, settings)
    alpha = model.deform_settings.final_alpha
    stiffnesses = [alpha] + ([alpha * settings.stiffer_remesh] if settings.stiffer_remesh > 1 else [])
    rejected: list[Rejection] = []
    for redraw in (range(settings.max_redraws + 1) if redraws is None else redraws):
        seed = redraw_seed(first_seed, count, index, redraw)
        landmarks, latent = _draw(model, seed)
        order = model.template_order(landmarks, template)[:TEMPLATES_TRIED]
        for stiffness in stiffnesses:
            stiffer = stiffness != alpha
            for template_index in order:
                mesh = model.mesh_from_landmarks(landmarks, template=model.names[template_index], smooth=smooth,
                                                 exact=exact, name=name, stiffness=stiffness)
                quality = gate.check(mesh, template_index)
                kept = GatedSample(index, name, seed, landmarks, latent, int(template_index), mesh, quality,
                                   stiffness, stiffer, rejected)
                if quality.ok:
                    return kept
                rejected.append(Rejection(seed, model.names[template_index], quality.reasons, stiffness, stiffer))
    return kept


def gated_slots(model, count: int, first_seed: int, slots: Sequence[tuple[int, range]], template: str | None = None,
                settings: QualitySettings = QualitySettings(), smooth: int = 0, exact: bool = False) -> list[GatedSample]:
    """One round of a run of `count` from `first_seed`: sample i of each (i, redraws) in
    `slots` gated with those draws (`gated_sample`), in the order of `slots`."""
    return [gated_sample(model, index, first_seed, count, template, settings, smooth, exact, name=sample_name(index),
                         redraws=redraws) for index, redraws in slots]


def pooled_samples(count: int, budget: int, gate: Callable[[list[tuple[int, range]]], list[GatedSample]]
                   ) -> list[GatedSample]:
    """Samples 0..count-1 of a run, each passing or failing once `budget` draws are spent
    (module docstring), in index order. `gate(slots)` gates one round: for each (i, draws)
    of `slots`, sample i with those draws (a `GatedSample` for each, passing or not; a
    process pool or cluster may do them in any order). Round 0 gives every sample
    budget // count draws; each later round shares the draws left among the samples still
    failing, at least one each, lowest index first. A sample's refused meshes of every
    round are kept, in order."""
    if count < 1:
        return []
    if budget < count:
        raise ValueError(f"a run of {count} samples needs a budget of at least {count} draws, got {budget}")
    kept: dict[int, GatedSample] = {}
    next_draw = [0] * count
    failing = list(range(count))
    used = 0
    while failing and used < budget:
        left = budget - used
        share = max(1, left // len(failing))
        slots = []
        for index in failing[:left]:
            slots.append((index, range(next_draw[index], next_draw[index] + share)))
            next_draw[index] += share
        for sample in gate(slots):
            earlier = kept.get(sample.index)
            if earlier is not None:
                sample = replace(sample, rejected=earlier.rejected + sample.rejected)
            kept[sample.index] = sample
        failing = [i for i in failing if not kept[i].quality.ok]
        used = sum(sample.draws for sample in kept.values())
    return [kept[i] for i in range(count)]


def gated_samples(model, count: int, first_seed: int, template: str | None = None,
                  settings: QualitySettings = QualitySettings(), smooth: int = 0, exact: bool = False
                  ) -> list[GatedSample]:
    """The `count` samples of a run from `first_seed`, gated with the run's pooled draw
    budget (`pooled_samples`), in this process; failing ones included (check `quality.ok`)."""
    return pooled_samples(count, draw_budget(count, settings),
                          lambda slots: gated_slots(model, count, first_seed, slots, template, settings, smooth,
                                                    exact))


def _criterion(reason: str) -> str:
    head = reason.split(":", 1)[0]
    return head if head in CRITERIA else "other"


def gate_summary(samples: Sequence[GatedSample]) -> str:
    """One line: how many first meshes failed and why, how many were re-meshed on another
    template, redrawn, and still fail when the run's draws were spent."""
    first_failed = [s for s in samples if s.rejected]
    if not first_failed:
        return f"quality gate: all {len(samples)} passed at the first draw"
    reasons = Counter(_criterion(reason) for s in samples for r in s.rejected for reason in r.reasons)
    redrawn = [s for s in samples if s.redraws]
    stiffer = [s for s in samples if s.stiffer and not s.redraws]
    failing = [s for s in samples if not s.quality.ok]
    why = ", ".join(f"{name} {n}" for name, n in reasons.most_common())
    text = (f"quality gate: {len(first_failed)} of {len(samples)} first meshes failed ({why}); "
            f"{len(first_failed) - len(redrawn) - len(stiffer)} passed on another template, {len(stiffer)} meshed "
            f"stiffer, {len(redrawn)} redrawn ({sum(s.redraws for s in samples)} redraws)")
    if failing:
        text += (f"; {len(failing)} still fail after {sum(s.draws for s in samples)} draws in all (" + ", ".join(
            f"{s.name}: {s.quality.summary()}" for s in failing[:3]) + (", ..." if len(failing) > 3 else "") + ")")
    return text


def failed_reasons(samples: Sequence[GatedSample]) -> Counter:
    """The gate's criteria over every mesh refused for the samples that still fail: how
    often each was a reason (a mesh may fail several)."""
    return Counter(_criterion(reason) for s in samples if not s.quality.ok for r in s.rejected for reason in r.reasons)


def shortfall(samples: Sequence[GatedSample], budget: int) -> str:
    """One line for a run whose samples do not all pass: how many passed within the budget
    of draws, how many still fail and the commonest reasons ("" when all pass)."""
    failing = [s for s in samples if not s.quality.ok]
    if not failing:
        return ""
    meshes = sum(len(s.rejected) for s in failing)
    why = ", ".join(f"{name} {n}" for name, n in failed_reasons(samples).most_common(3))
    return (f"{len(samples) - len(failing)} of {len(samples)} samples passed the quality gate within the budget of "
            f"{budget} draws; {len(failing)} still fail (commonest reasons over their {meshes} refused meshes: {why})")


def rejection_lines(samples: Sequence[GatedSample]) -> list[str]:
    """One line per refused mesh: sample, seed, template and the gate's reasons."""
    return [f"{s.name}: {r.describe()}" for s in samples for r in s.rejected]
