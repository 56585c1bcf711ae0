"""Gated sampling (issue 14): draw, mesh, check with the quality gate, and try again.

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
   in the run, independent of the order samples are made), up to
   `QualitySettings.max_redraws` times; the last draw is kept when every one fails, and
   says so.

Every rejected mesh is recorded with its seed, template and the gate's reasons
(`Rejection`), so a run can say how many it redrew and why (`gate_summary`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .mesh import Mesh
from .quality import CRITERIA, MeshQuality, QualityGate, QualitySettings, training_extents

__all__ = ["Rejection", "GatedSample", "TEMPLATES_TRIED", "quality_gate", "redraw_seed", "gated_sample",
           "gated_samples", "gate_summary", "rejection_lines", "sample_name"]

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


def gated_sample(model, index: int, first_seed: int, count: int, template: str | None = None,
                 settings: QualitySettings = QualitySettings(), smooth: int = 0, exact: bool = False,
                 name: str = "sample") -> GatedSample:
    """Sample `index` of a run of `count` from `first_seed`, gated (module docstring)."""
    gate = quality_gate(model, settings)
    alpha = model.deform_settings.final_alpha
    stiffnesses = [alpha] + ([alpha * settings.stiffer_remesh] if settings.stiffer_remesh > 1 else [])
    rejected: list[Rejection] = []
    for redraw in range(settings.max_redraws + 1):
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


def gated_samples(model, count: int, first_seed: int, template: str | None = None,
                  settings: QualitySettings = QualitySettings(), smooth: int = 0, exact: bool = False,
                  indices: Sequence[int] | None = None, names: Sequence[str] | None = None) -> list[GatedSample]:
    """Samples `indices` (default: all `count`) of a run from `first_seed`, gated."""
    indices = range(count) if indices is None else indices
    return [gated_sample(model, i, first_seed, count, template, settings, smooth, exact,
                         name=names[i] if names is not None else sample_name(i)) for i in indices]


def _criterion(reason: str) -> str:
    head = reason.split(":", 1)[0]
    return head if head in CRITERIA else "other"


def gate_summary(samples: Sequence[GatedSample]) -> str:
    """One line: how many first meshes failed and why, how many were re-meshed on another
    template, redrawn, and still fail."""
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
        text += f"; {len(failing)} still fail after every redraw (kept: " + ", ".join(
            f"{s.name}: {s.quality.summary()}" for s in failing[:3]) + (", ..." if len(failing) > 3 else "") + ")"
    return text


def rejection_lines(samples: Sequence[GatedSample]) -> list[str]:
    """One line per refused mesh: sample, seed, template and the gate's reasons."""
    return [f"{s.name}: {r.describe()}" for s in samples for r in s.rejected]
