"""One evaluation run: every metric of the package on one landmark matrix, in named steps.

Protocol (`run_evaluation`): one random k-fold split (seed). Per fold and model: fit on the
training folds; complete each region of the held-out shapes; reconstruct them (decode ∘
encode); score them; draw |test| samples for MMD / coverage / 1-NNA against them. Baselines
ride along (training-set memoriser, mean shape). Per model on all shapes: `n_samples`
samples for novelty / specificity. PPCA curves: held-out NLL vs q (k-fold), generalisation
and specificity vs modes. Finally the 2-D GP-LVM latent map with outlier scores and a morph.
`report.py` writes the result to files.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..models import MODEL_TYPES, GPLVM, make_model
from ..base.progress import Progress, no_progress
from .baselines import MeanShapeModel, TrainingSetModel
from .completion import REGIONS, completion_errors, hidden_coordinates, region_mask
from .curves import generalisation_curve, ppca_nll_curve, specificity_curve
from .latent import choose_morph_endpoints, latent_morph, latent_outlier_scores
from .metrics import (EvaluationError, as_point_sets, coverage, landmark_rms_matrix, mmd, novelty, one_nna,
                      one_nna_chance_level, procrustes_rms_matrix)
from .protocol import heldout_folds, random_stream

__all__ = ["EvaluationSettings", "EvaluationResult", "parse_model_names", "run_evaluation"]

#: Baselines fitted in every fold next to the models (name -> class).
BASELINES = {"training-set": TrainingSetModel, "mean-shape": MeanShapeModel}


# ============================================================================ settings and models
def parse_model_names(text_or_names) -> list[str]:
    """'ppca,gplvm' or a list -> validated, de-duplicated names (order kept)."""
    names = text_or_names.split(",") if isinstance(text_or_names, str) else list(text_or_names)
    names = [n.strip().lower() for n in names if n.strip()]
    unknown = [n for n in names if n not in MODEL_TYPES]
    if unknown:
        raise EvaluationError(f"unknown model name(s) {', '.join(repr(n) for n in unknown)} "
                              f"(known: {', '.join(MODEL_TYPES)})")
    if not names:
        raise EvaluationError(f"no model given (known: {', '.join(MODEL_TYPES)})")
    return list(dict.fromkeys(names))


@dataclass
class EvaluationSettings:
    """Settings of one evaluation run (all recorded in the report).

    models: model names (MODEL_TYPES keys). folds: k of the k-fold protocol used by
    completion, held-out reconstruction, held-out likelihood and MMD / coverage / 1-NNA.
    seed: every random choice (fold split, samples, inducing points) derives from it.
    n_samples: samples of the full-data models for novelty / specificity.
    latent_dim: None = each model's 80 % explained-variance rule, else fixed for all models.
    regions: completion regions (REGIONS keys). max_curve_dim: cap of q / m in the PPCA
    curves. latent_map: fit the 2-D GP-LVM map and morph.
    """

    models: list[str] = field(default_factory=lambda: ["ppca", "gplvm", "bgplvm"])
    folds: int = 5
    seed: int = 0
    n_samples: int = 100
    latent_dim: int | None = None
    regions: list[str] = field(default_factory=lambda: ["top", "middle", "rear"])
    max_curve_dim: int = 40
    latent_map: bool = True
    morph_steps: int = 7

    def validate(self, n_shapes: int) -> None:
        self.models = parse_model_names(self.models)
        unknown = [r for r in self.regions if r not in REGIONS]
        if unknown or not self.regions:
            raise EvaluationError(f"unknown completion region(s) {unknown} (known: {', '.join(REGIONS)})")
        if n_shapes < 4:
            raise EvaluationError(f"evaluation needs at least 4 shapes, got {n_shapes}")
        if isinstance(self.folds, bool) or not isinstance(self.folds, (int, np.integer)) or self.folds < 2:
            raise EvaluationError(f"--folds must be an integer >= 2, got {self.folds!r}")
        if self.folds > n_shapes:
            raise EvaluationError(f"--folds {self.folds} is more than the {n_shapes} shapes of the collection")
        smallest_train = n_shapes - -(-n_shapes // self.folds)
        if smallest_train < 3:
            raise EvaluationError(f"with {n_shapes} shapes and {self.folds} folds a training fold has only "
                                  f"{smallest_train} shapes; use fewer folds")
        if self.latent_dim is not None and not 1 <= self.latent_dim < smallest_train:
            raise EvaluationError(f"--latent-dim {self.latent_dim} must be between 1 and {smallest_train - 1} "
                                  f"(the smallest training fold has {smallest_train} shapes)")
        if self.n_samples < 1:
            raise EvaluationError(f"n_samples must be >= 1, got {self.n_samples}")


@dataclass
class EvaluationResult:
    """Numbers (`report`, JSON-ready after report.py's cleaning) and the arrays the figures
    show (`figures`: point sets in the normalised frame)."""

    report: dict
    figures: dict
    timings: dict


# ============================================================================ the steps of a run
class _Steps:
    """Progress over a known number of steps: `next` reports the fraction done, then counts."""

    def __init__(self, progress: Progress | None, total: int):
        self.progress = progress or no_progress
        self.total = total
        self.done = 0

    def next(self, message: str) -> None:
        self.progress(self.done / self.total, message)
        self.done += 1


@dataclass
class _HeldOutScores:
    """One model's (or baseline's) numbers on the held-out folds; per-shape arrays are
    indexed by the shape's row in Y, the lists hold one value per fold."""

    completion: dict[str, np.ndarray]           # region -> E per shape (Table 5.1)
    completion_relative: dict[str, np.ndarray]  # region -> E / E of filling in the training mean
    reconstruction: np.ndarray                  # d(y, decode(encode(y))) per shape (models only)
    heldout_ll: list[float] = field(default_factory=list)
    mmd: list[float] = field(default_factory=list)
    coverage: list[float] = field(default_factory=list)
    one_nna: list[float] = field(default_factory=list)
    latent_dims: list[int] = field(default_factory=list)

    @classmethod
    def empty(cls, n: int, regions: Sequence[str]) -> "_HeldOutScores":
        return cls(completion={r: np.full(n, np.nan) for r in regions},
                   completion_relative={r: np.full(n, np.nan) for r in regions},
                   reconstruction=np.full(n, np.nan))


@dataclass
class _HeldOut:
    """What the fold loop measures: scores per model, the hidden landmarks, and the first
    completed test shape of fold 0 per region (the completion figures)."""

    scores: dict[str, _HeldOutScores]
    hidden_per_fold: dict[str, list[int]]       # region -> hidden landmarks in each fold
    hidden_per_shape: dict[str, np.ndarray]     # region -> hidden landmarks when the shape was held out
    examples: dict[str, dict] = field(default_factory=dict)


def _complete_regions(model, Y_test: np.ndarray, test_idx: np.ndarray, train_mean: np.ndarray,
                      masks: dict[str, np.ndarray], scores: _HeldOutScores) -> dict[str, np.ndarray]:
    """Hide each region of the held-out shapes and let the model complete it (§5.5.3);
    records E and E relative to filling in the training mean; returns the completions."""
    completions = {}
    for r, hidden in masks.items():
        observed = np.broadcast_to(~hidden, Y_test.shape).copy()
        completed = model.complete(np.where(observed, Y_test, np.nan), observed)
        err = completion_errors(Y_test, completed, hidden)
        mean_err = completion_errors(Y_test, np.broadcast_to(train_mean, Y_test.shape), hidden)
        scores.completion[r][test_idx] = err
        scores.completion_relative[r][test_idx] = err / mean_err
        completions[r] = completed
    return completions


def _keep_completion_examples(examples: dict, name: str, Y_test: np.ndarray, test_name: str,
                              masks: dict[str, np.ndarray], completions: dict[str, np.ndarray]) -> None:
    """The first test shape of a fold with each model's completion of each region."""
    for r, hidden in masks.items():
        example = examples.setdefault(r, {"truth": as_point_sets(Y_test[0])[0], "name": test_name,
                                          "hidden": hidden[::3].copy(), "models": {}})
        example["models"][name] = as_point_sets(completions[r][0])[0]


def _score_samples(model, Y_test: np.ndarray, rng: np.random.Generator, scores: _HeldOutScores) -> None:
    """|test| samples of the model against the held-out shapes: MMD, coverage, 1-NNA."""
    samples = model.sample(len(Y_test), rng)
    scores.mmd.append(mmd(samples, Y_test))
    scores.coverage.append(coverage(samples, Y_test))
    scores.one_nna.append(one_nna(samples, Y_test))


def _score_reconstruction(model, Y_test: np.ndarray, test_idx: np.ndarray, scores: _HeldOutScores) -> None:
    """Held-out reconstruction d(y, decode(encode(y))) and log-likelihood of a model."""
    scores.reconstruction[test_idx] = np.diag(landmark_rms_matrix(Y_test, model.decode(model.encode(Y_test))))
    scores.heldout_ll.append(float(model.score(Y_test)))


def _held_out_evaluation(Y: np.ndarray, names: list[str], folds: list[np.ndarray], settings: EvaluationSettings,
                         steps: _Steps, timings: dict) -> _HeldOut:
    """The fold loop: per fold, every model and baseline is fitted on the training folds,
    then completes, samples against and (models) reconstructs and scores the held-out fold.
    Completion regions are chosen on the training mean."""
    n = len(Y)
    all_models = [*settings.models, *BASELINES]
    held = _HeldOut(scores={name: _HeldOutScores.empty(n, settings.regions) for name in all_models},
                    hidden_per_fold={r: [] for r in settings.regions},
                    hidden_per_shape={r: np.zeros(n) for r in settings.regions})
    for f, test_idx in enumerate(folds):
        train_idx = np.setdiff1d(np.arange(n), test_idx)
        Y_train, Y_test = Y[train_idx], Y[test_idx]
        train_mean = Y_train.mean(0)
        masks = {r: hidden_coordinates(region_mask(train_mean, r)) for r in settings.regions}
        for r in settings.regions:
            held.hidden_per_fold[r].append(int(masks[r].sum()) // 3)
            held.hidden_per_shape[r][test_idx] = masks[r].sum() // 3
        for name in all_models:
            steps.next(f"fold {f + 1}/{settings.folds}: {name}")
            start = time.perf_counter()
            model = (BASELINES[name]() if name in BASELINES
                     else make_model(name, settings.latent_dim, settings.seed + f))
            model.fit(Y_train)
            scores = held.scores[name]
            scores.latent_dims.append(int(model.latent_dim))
            completions = _complete_regions(model, Y_test, test_idx, train_mean, masks, scores)
            if f == 0:
                _keep_completion_examples(held.examples, name, Y_test, names[test_idx[0]], masks, completions)
            _score_samples(model, Y_test, random_stream(settings.seed, 2, f, all_models.index(name)), scores)
            if name not in BASELINES:
                _score_reconstruction(model, Y_test, test_idx, scores)
            timings[f"fold{f}:{name}"] = time.perf_counter() - start
    return held


@dataclass
class _FullDataFit:
    """A model fitted on all shapes: its latent dimension, samples and their novelty."""

    latent_dim: int
    samples: np.ndarray
    novelty: dict


def _full_data_fits(Y: np.ndarray, settings: EvaluationSettings, steps: _Steps, timings: dict) -> dict[str, _FullDataFit]:
    """Each model fitted on all shapes, `n_samples` samples and their novelty (§5.5.2)."""
    fits = {}
    for name in settings.models:
        steps.next(f"all shapes: {name}")
        start = time.perf_counter()
        model = make_model(name, settings.latent_dim, settings.seed).fit(Y)
        samples = model.sample(settings.n_samples, random_stream(settings.seed, 3, settings.models.index(name)))
        fits[name] = _FullDataFit(int(model.latent_dim), samples, novelty(samples, Y))
        timings[f"all:{name}"] = time.perf_counter() - start
    return fits


def _training_nn_median(Y: np.ndarray) -> float:
    """Median over the shapes of d_P to their nearest other shape (the scale novelty is read on)."""
    training_nn = procrustes_rms_matrix(Y, Y)
    np.fill_diagonal(training_nn, np.inf)
    return float(np.median(training_nn.min(1)))


def _ppca_curves(Y: np.ndarray, folds: list[np.ndarray], settings: EvaluationSettings, steps: _Steps,
                 timings: dict) -> dict:
    """Held-out NLL vs q, generalisation and specificity vs modes (curves.py)."""
    steps.next("PPCA curves")
    start = time.perf_counter()
    curves = {"nll": ppca_nll_curve(Y, folds, settings.max_curve_dim),
              "generalisation": generalisation_curve(Y, settings.max_curve_dim),
              "specificity": specificity_curve(Y, settings.n_samples, settings.seed, min(settings.max_curve_dim, 20))}
    timings["ppca_curves"] = time.perf_counter() - start
    return curves


def _latent_map(Y: np.ndarray, names: list[str], morph_steps: int, steps: _Steps, timings: dict) -> tuple[dict, dict]:
    """The 2-D GP-LVM latent map with outlier scores and a morph (latent.py): the report
    section and the figure's arrays."""
    steps.next("2-D latent map (GP-LVM)")
    start = time.perf_counter()
    gp2 = GPLVM(n_components=2).fit(Y)
    Z = gp2.latents_
    outliers = latent_outlier_scores(Z, gp2.kde_bandwidth_)
    a, b = choose_morph_endpoints(Z, gp2.kde_bandwidth_)
    morph = latent_morph(gp2, Z[a], Z[b], morph_steps)
    endpoint_error = [float(landmark_rms_matrix(morph["shapes"][0], Y[a])[0, 0]),
                      float(landmark_rms_matrix(morph["shapes"][-1], Y[b])[0, 0])]
    section = {
        "model": "gplvm", "latent_dim": 2, "kde_bandwidth": gp2.kde_bandwidth_,
        "points": {nm: [float(v) for v in z] for nm, z in zip(names, Z)},
        "outlier_score": dict(zip(names, outliers["score"])),
        "outlier_robust_z": dict(zip(names, outliers["robust_z"])),
        "outliers": [nm for nm, flag in zip(names, outliers["flagged"]) if flag],
        "morph": {"from": names[a], "to": names[b], "steps": morph_steps,
                  "step_rms": morph["step"], "step_ratio_max_min": float(morph["step"].max() / morph["step"].min())
                  if morph["step"].min() > 0 else None,
                  "endpoint_rms": endpoint_error},
    }
    figure = {"latents": Z, "score": outliers["robust_z"], "flagged": outliers["flagged"],
              "morph": morph, "from": a, "to": b}
    timings["latent_map"] = time.perf_counter() - start
    return section, figure


# ============================================================================ the report
def _mean_sd(values) -> dict:
    values = np.asarray(values, dtype=float)
    return {"mean": float(np.mean(values)), "sd": float(np.std(values, ddof=1)) if values.size > 1 else 0.0}


def _novelty_entry(fit: _FullDataFit, names: list[str], training_nn_median: float) -> dict:
    """Specificity and novelty of a full-data model's samples."""
    distance = fit.novelty["distance"]
    return {
        "latent_dim": fit.latent_dim,
        "specificity": float(np.mean(distance)),
        "novelty": {"mean": float(np.mean(distance)), "median": float(np.median(distance)),
                    "min": float(np.min(distance)), "max": float(np.max(distance)),
                    "relative_to_training_nn_median": float(np.median(distance) / training_nn_median)
                    if training_nn_median > 0 else None,
                    "per_sample": distance.tolist(),
                    "nearest": [names[i] for i in fit.novelty["nearest"]]},
    }


def _model_entry(name: str, held: _HeldOut, fits: dict[str, _FullDataFit], names: list[str],
                 regions: Sequence[str], training_nn_median: float) -> dict:
    """The report entry of one model or baseline."""
    scores = held.scores[name]
    entry = {
        "kind": "baseline" if name in BASELINES else "model",
        "latent_dim_per_fold": scores.latent_dims,
        "completion": {
            r: {"mean_sse": float(np.mean(scores.completion[r])),
                "sd_sse": float(np.std(scores.completion[r], ddof=1)),
                "mean_rms_per_hidden_landmark": float(np.mean(np.sqrt(
                    scores.completion[r] / held.hidden_per_shape[r]))),
                "relative_to_mean_shape": float(np.mean(scores.completion_relative[r])),
                "per_shape": dict(zip(names, scores.completion[r]))}
            for r in regions},
        "heldout_samples": {"mmd": _mean_sd(scores.mmd), "coverage": _mean_sd(scores.coverage),
                            "one_nna": _mean_sd(scores.one_nna)},
    }
    if name not in BASELINES:
        entry["heldout_reconstruction_rms"] = {**_mean_sd(scores.reconstruction),
                                               "per_shape": dict(zip(names, scores.reconstruction))}
        entry["heldout_log_likelihood"] = {**_mean_sd(scores.heldout_ll), "per_fold": scores.heldout_ll}
        entry["all_shapes"] = _novelty_entry(fits[name], names, training_nn_median)
    return entry


def _curves_entry(curves: dict) -> dict:
    nll, gen, spec = curves["nll"], curves["generalisation"], curves["specificity"]
    return {
        "nll_vs_latent_dim": {"latent_dims": nll["latent_dims"], "train_nll": nll["train_nll"],
                              "test_nll": nll["test_nll"], "test_nll_stderr": nll["test_nll_stderr"],
                              "best_latent_dim": nll["best_latent_dim"]},
        "generalisation_loo": {"modes": gen["modes"], "mean": gen["mean"], "stderr": gen["stderr"]},
        "specificity": {"modes": spec["modes"], "mean": spec["mean"]},
    }


# ============================================================================ the whole run
def run_evaluation(Y, names: Sequence[str], settings: EvaluationSettings,
                   progress: Progress | None = None, extra: dict | None = None) -> EvaluationResult:
    """Every metric of the package on the landmark matrix Y (N × 3L) for `settings.models`
    (protocol in the module docstring). The report holds plain Python values; report.py
    rounds and writes them."""
    Y = np.asarray(Y, dtype=np.float64)
    if Y.ndim != 2 or Y.shape[1] % 3 or not np.all(np.isfinite(Y)):
        raise EvaluationError(f"landmark matrix must be a finite (N, 3L) array, got shape {Y.shape}")
    n, n_coords = Y.shape
    names = list(names)
    settings.validate(n)
    folds = heldout_folds(n, settings.folds, settings.seed)
    timings: dict[str, float] = {}
    steps = _Steps(progress, settings.folds * (len(settings.models) + len(BASELINES)) + len(settings.models) + 3)

    held = _held_out_evaluation(Y, names, folds, settings, steps, timings)
    training_nn_median = _training_nn_median(Y)
    fits = _full_data_fits(Y, settings, steps, timings)
    curves = _ppca_curves(Y, folds, settings, steps, timings)
    figures: dict = {"names": names, "data": as_point_sets(Y),
                     "samples": {name: {"samples": as_point_sets(fit.samples), "nearest": fit.novelty["nearest"],
                                        "distance": fit.novelty["distance"]} for name, fit in fits.items()},
                     "completion": held.examples, "curves": curves}
    latent_section = None
    if settings.latent_map:
        latent_section, figures["latent_map"] = _latent_map(Y, names, settings.morph_steps, steps, timings)
    steps.progress(1.0, "evaluation done")

    report = {
        "format": "shapegen.evaluation",
        "format_version": 1,
        "data": {"n_shapes": n, "n_landmarks": n_coords // 3, "names": names,
                 "training_nn_median_procrustes_rms": training_nn_median, **(extra or {})},
        "settings": {"models": settings.models, "folds": settings.folds, "seed": settings.seed,
                     "n_samples": settings.n_samples, "latent_dim": settings.latent_dim,
                     "regions": list(settings.regions), "max_curve_dim": settings.max_curve_dim,
                     "fold_test_sets": [[names[i] for i in f] for f in folds],
                     "hidden_landmarks_per_fold": held.hidden_per_fold,
                     "one_nna_chance_level": float(np.mean([one_nna_chance_level(len(f)) for f in folds]))},
        "models": {name: _model_entry(name, held, fits, names, settings.regions, training_nn_median)
                   for name in held.scores},
        "ppca_curves": _curves_entry(curves),
        "latent_map": latent_section,
    }
    return EvaluationResult(report=report, figures=figures, timings=timings)
