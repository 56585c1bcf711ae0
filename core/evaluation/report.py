"""Writing an evaluation (core/evaluation) to a folder: `report.json`, `summary.md`, PNG figures.

Byte-for-byte reproducible for a fixed seed: no timestamps or paths of the output folder in
any file, floats rounded to 7 significant digits (so last-bit differences of BLAS cannot
show), keys in a fixed order, and PNGs written by matplotlib's Agg backend with the
'Software' metadata removed (Agg PNGs carry no date).

matplotlib is imported lazily inside `write_figures` (a pinned requirement of the
development environments, not of the Blender extension): `write_report(..., figures=False)`
works without it.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from . import EvaluationResult, procrustes_align

__all__ = ["clean_for_json", "write_report", "write_summary", "write_figures", "REPORT_FILES"]

#: Files of a report folder (figures only when matplotlib is available and figures are on).
REPORT_FILES = ("report.json", "summary.md")
_SIGNIFICANT = 7
_BASELINE_LABELS = {"training-set": "training set (memoriser)", "mean-shape": "mean shape"}
_MODEL_LABELS = {"ppca": "PPCA", "gplvm": "GP-LVM", "bgplvm": "BGP-LVM"}


def clean_for_json(value):
    """Plain JSON values: numpy -> Python, floats rounded to 7 significant digits,
    NaN / inf -> null, tuples -> lists, dict keys -> str (order kept)."""
    if isinstance(value, dict):
        return {str(k): clean_for_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean_for_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return [clean_for_json(v) for v in value.tolist()]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        if not math.isfinite(value):
            return None
        return float(f"{value:.{_SIGNIFICANT}g}")
    if value is None or isinstance(value, str):
        return value
    raise TypeError(f"cannot write {type(value).__name__} to the report")


def _label(name: str) -> str:
    return _MODEL_LABELS.get(name, _BASELINE_LABELS.get(name, name))


def _fmt(value, digits: int = 4) -> str:
    if value is None:
        return "–"
    if isinstance(value, int):
        return str(value)
    return f"{value:.{digits}g}"


def write_report(result: EvaluationResult, folder: str | os.PathLike, figures: bool = True) -> list[Path]:
    """Write report.json, summary.md and (figures=True) the PNGs into `folder`; returns paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    report = clean_for_json(result.report)
    written = []
    path = folder / "report.json"
    path.write_text(json.dumps(report, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    written.append(path)
    figure_paths = write_figures(result, folder) if figures else []
    path = folder / "summary.md"
    path.write_text(write_summary(report, [p.name for p in figure_paths]), encoding="utf-8")
    written.append(path)
    return written + figure_paths


# ============================================================================ markdown
def write_summary(report: dict, figure_names: list[str] = ()) -> str:
    """Markdown tables of a cleaned report (the same rounded numbers as report.json)."""
    lines = (["# ShapeGen evaluation", ""] + _data_lines(report) + _completion_lines(report)
             + _sample_lines(report) + _ppca_lines(report) + _latent_lines(report))
    if figure_names:
        lines += ["", "## Figures", ""] + [f"![{name}]({name})" for name in figure_names]
    return "\n".join(lines) + "\n"


def _data_lines(report: dict) -> list[str]:
    """The data and the protocol."""
    data, settings = report["data"], report["settings"]
    source = data.get("source")
    lines = [f"- data: {data['n_shapes']} shapes × {data['n_landmarks']} landmarks"
             + (f" ({source})" if source else "")]
    if data.get("correspondence_outliers"):
        lines += [f"- correspondence outliers (kept): {', '.join(data['correspondence_outliers'])}"]
    if data.get("unreadable_files"):
        lines += [f"- files left out as unreadable: {'; '.join(data['unreadable_files'].values())}"]
    lines += [f"- protocol: {settings['folds']}-fold cross-validation, seed {settings['seed']}; "
              f"latent dimension {settings['latent_dim'] if settings['latent_dim'] else 'by the 80 % rule'}; "
              f"{settings['n_samples']} samples per model for novelty / specificity",
              f"- distances are in the units of the normalised frame; median nearest-neighbour "
              f"distance between training shapes (Procrustes RMS) {_fmt(data['training_nn_median_procrustes_rms'])}",
              ""]
    return lines


def _completion_lines(report: dict) -> list[str]:
    """Shape completion per region and model (thesis Table 5.1)."""
    regions, models = report["settings"]["regions"], report["models"]
    lines = ["## Shape completion (thesis Table 5.1 protocol)", "",
             "Mean over held-out shapes of the summed squared error of the hidden coordinates "
             "(± sd over shapes); in brackets the error relative to filling in the mean training shape.", "",
             "| model | q | " + " | ".join(regions) + " |",
             "|---|---|" + "---|" * len(regions)]
    for name, entry in models.items():
        q = entry["latent_dim_per_fold"]
        q_text = "–" if entry["kind"] == "baseline" else (str(q[0]) if len(set(q)) == 1 else f"{min(q)}–{max(q)}")
        cells = [f"{_fmt(entry['completion'][r]['mean_sse'])} ± {_fmt(entry['completion'][r]['sd_sse'], 2)} "
                 f"({_fmt(entry['completion'][r]['relative_to_mean_shape'], 3)})" for r in regions]
        lines.append(f"| {_label(name)} | {q_text} | " + " | ".join(cells) + " |")
    lines += ["", "RMS per hidden landmark (square root of the error per hidden landmark, mean over shapes):", "",
              "| model | " + " | ".join(regions) + " |", "|---|" + "---|" * len(regions)]
    for name, entry in models.items():
        lines.append(f"| {_label(name)} | "
                     + " | ".join(_fmt(entry["completion"][r]["mean_rms_per_hidden_landmark"]) for r in regions) + " |")
    return lines


def _sample_lines(report: dict) -> list[str]:
    """Novelty, specificity and the held-out set measures per model."""
    settings, models = report["settings"], report["models"]
    lines = ["", "## Samples and generalisation", "",
             "Novelty / specificity: samples of the model fitted on all shapes against the training shapes "
             "(Procrustes RMS). Held-out columns: per fold, as many samples as held-out shapes; mean ± sd over folds. "
             f"1-NNA: 1 = separable; for {settings['folds']} folds the chance level (samples indistinguishable "
             f"from held-out shapes) is {_fmt(settings['one_nna_chance_level'], 3)}, not 0.5, as the sets are small. "
             "Reference rows: training set = a memoriser (its samples are training shapes), mean shape = "
             "a collapsed sampler (every sample is the mean shape).", "",
             "| model | q (all) | novelty median | specificity | held-out recon. RMS | MMD | coverage | 1-NNA | held-out log-lik. |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, entry in models.items():
        hs = entry["heldout_samples"]
        set_cells = " | ".join(f"{_fmt(hs[k]['mean'], 3)} ± {_fmt(hs[k]['sd'], 2)}" for k in ("mmd", "coverage", "one_nna"))
        if entry["kind"] == "baseline":
            lines.append(f"| {_label(name)} | – | – | – | – | {set_cells} | – |")
            continue
        full = entry["all_shapes"]
        lines.append(
            f"| {_label(name)} | {full['latent_dim']} | {_fmt(full['novelty']['median'])} | {_fmt(full['specificity'])} | "
            f"{_fmt(entry['heldout_reconstruction_rms']['mean'])} | {set_cells} | "
            f"{_fmt(entry['heldout_log_likelihood']['mean'], 6)} |")
    lines += ["", "Held-out log-likelihood: exact for PPCA; GP-LVM: predictive density at the optimised latent "
              "(optimistic); BGP-LVM: per-point variational lower bound. Compare within a model, not across.", ""]
    return lines


def _ppca_lines(report: dict) -> list[str]:
    """PPCA's NLL, generalisation and specificity against the latent dimension (thesis Fig. 5.10)."""
    curves = report["ppca_curves"]
    nll = curves["nll_vs_latent_dim"]
    gen, spec = curves["generalisation_loo"], curves["specificity"]
    lines = ["## PPCA against the latent dimension (thesis Fig. 5.10; Styner et al. 2003)", "",
             f"Held-out NLL is lowest at q = {nll['best_latent_dim']}.", "",
             "| q | train NLL | test NLL | generalisation (LOO RMS) | specificity |", "|---|---|---|---|---|"]
    gen_by_m = dict(zip(gen["modes"], gen["mean"]))
    spec_by_m = dict(zip(spec["modes"], spec["mean"]))
    for q, tr, te in zip(nll["latent_dims"], nll["train_nll"], nll["test_nll"]):
        lines.append(f"| {q} | {_fmt(tr, 6)} | {_fmt(te, 6)} | {_fmt(gen_by_m.get(q))} | {_fmt(spec_by_m.get(q))} |")
    return lines


def _latent_lines(report: dict) -> list[str]:
    """The 2-D latent map's outliers and the morph (thesis Figs. 5.11-5.12), when evaluated."""
    latent = report.get("latent_map")
    if not latent:
        return []
    z = latent["outlier_robust_z"]
    top = sorted(z, key=lambda k: -z[k])[:3]
    morph = latent["morph"]
    return ["", "## 2-D latent map (GP-LVM, thesis Fig. 5.11) and morph (Fig. 5.12)", "",
            f"- flagged outliers (robust z > 3): {', '.join(latent['outliers']) or 'none'}; "
            f"highest scores: " + ", ".join(f"{k} ({_fmt(z[k], 3)})" for k in top),
            f"- morph {morph['from']} → {morph['to']} in {morph['steps']} frames: step RMS "
            + ", ".join(_fmt(s, 3) for s in morph["step_rms"])
            + f"; decoded end points are {_fmt(morph['endpoint_rms'][0], 3)} and "
            f"{_fmt(morph['endpoint_rms'][1], 3)} (RMS) from the data shapes"]


# ============================================================================ figures
def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 8, "axes.titlesize": 8, "figure.dpi": 100, "savefig.dpi": 100,
                         "path.simplify": False})
    return plt


def _save(fig, path: Path) -> Path:
    # no 'Software' key: the PNG then depends only on the pixels and the matplotlib version
    fig.savefig(path, format="png", metadata={"Software": None})
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def _limits(point_sets) -> tuple[tuple[float, float], tuple[float, float]]:
    """Shared side-view (x horizontal, z up) limits over point sets, with a 5 % margin."""
    P = np.concatenate([np.asarray(p).reshape(-1, 3) for p in point_sets])
    lo, hi = P.min(0), P.max(0)
    span = float(max(hi[0] - lo[0], hi[2] - lo[2])) * 0.55
    cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
    return (cx - span, cx + span), (cz - span, cz + span)


def _cloud(ax, P, limits, color="0.2", size=1.0, alpha=0.8, title=None):
    """Side view of a landmark cloud: x horizontal, z up, nearer points (smaller y) on top."""
    P = np.asarray(P).reshape(-1, 3)
    order = np.argsort(-P[:, 1], kind="stable")
    ax.scatter(P[order, 0], P[order, 2], s=size, c=color, alpha=alpha, linewidths=0, rasterized=False)
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title)


def write_figures(result: EvaluationResult, folder: Path) -> list[Path]:
    """samples.png, nearest.png, completion_<region>.png, ppca_curves.png, latent_map.png,
    morph.png (those whose data the evaluation produced)."""
    plt = _pyplot()
    fig_data = result.figures
    out: list[Path] = []
    if fig_data.get("samples", {}):
        out.append(_samples_figure(plt, result, folder))
        out.append(_nearest_figure(plt, fig_data, folder))
    for region, example in fig_data.get("completion", {}).items():
        out.append(_completion_figure(plt, region, example, folder))
    curves = fig_data.get("curves")
    if curves and curves["nll"]["latent_dims"]:
        out.append(_ppca_curves_figure(plt, curves, len(result.report["settings"]["fold_test_sets"]), folder))
    latent = fig_data.get("latent_map")
    if latent is not None:
        out.append(_latent_map_figure(plt, latent, fig_data["names"], folder))
        out.append(_morph_figure(plt, latent, fig_data["names"], folder))
    return out


def _samples_figure(plt, result: EvaluationResult, folder: Path) -> Path:
    """samples.png: training shapes (a random choice by the evaluation's seed) beside each
    model's first samples (thesis Figs. 5.4-5.6)."""
    names, data, samples = result.figures["names"], result.figures["data"], result.figures["samples"]
    rng = np.random.default_rng(result.report["settings"]["seed"])
    columns = min(6, len(data))
    shown = np.sort(rng.choice(len(data), columns, replace=False))
    rows = [("data", [data[i] for i in shown], [names[i] for i in shown])]
    for name, s in samples.items():
        rows.append((_label(name), list(s["samples"][:columns]), [f"sample {k}" for k in range(columns)]))
    limits = _limits([p for _, sets, _ in rows for p in sets])
    fig, axes = plt.subplots(len(rows), columns, figsize=(1.5 * columns, 1.6 * len(rows)), squeeze=False)
    for r, (label, sets, titles) in enumerate(rows):
        for c in range(columns):
            _cloud(axes[r, c], sets[c], limits, color="tab:red" if r == 0 else "tab:blue", title=titles[c])
        axes[r, 0].set_ylabel(label)
    fig.suptitle("Training shapes (red) and model samples (blue), side view")
    fig.tight_layout()
    return _save(fig, folder / "samples.png")


def _nearest_figure(plt, fig_data: dict, folder: Path) -> Path:
    """nearest.png: each model's first samples, aligned, over their nearest training
    shapes (thesis Fig. 5.7)."""
    names, data, samples = fig_data["names"], fig_data["data"], fig_data["samples"]
    pairs = 4
    fig, axes = plt.subplots(len(samples), pairs, figsize=(1.8 * pairs, 1.9 * len(samples)), squeeze=False)
    all_sets = []
    chosen = {}
    for name, s in samples.items():
        idx = list(range(min(pairs, len(s["samples"]))))
        chosen[name] = idx
        all_sets += [s["samples"][i] for i in idx] + [data[s["nearest"][i]] for i in idx]
    limits = _limits(all_sets)
    for r, (name, s) in enumerate(samples.items()):
        for c in range(pairs):
            ax = axes[r, c]
            if c >= len(chosen[name]):
                ax.axis("off")
                continue
            i = chosen[name][c]
            nearest = data[s["nearest"][i]]
            _cloud(ax, nearest, limits, color="tab:red", alpha=0.6)
            _cloud(ax, procrustes_align(s["samples"][i], nearest), limits, color="tab:blue", alpha=0.6,
                   title=f"{names[s['nearest'][i]]}: {s['distance'][i]:.3g}")
        axes[r, 0].set_ylabel(_label(name))
    fig.suptitle("Samples (blue, aligned) and their nearest training shape (red); Procrustes RMS")
    fig.tight_layout()
    return _save(fig, folder / "nearest.png")


def _completion_figure(plt, region: str, example: dict, folder: Path) -> Path:
    """completion_<region>.png: a held-out shape's hidden region, truth and each model's
    reconstruction (thesis Figs. 5.8-5.9)."""
    panels = [("truth", example["truth"])] + [(_label(n), P) for n, P in example["models"].items()]
    limits = _limits([P for _, P in panels])
    hidden = example["hidden"]
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(1.6 * (len(panels) + 1), 2.0), squeeze=False)
    _cloud(axes[0, 0], example["truth"][~hidden], limits, title="visible")
    for c, (label, P) in enumerate(panels, start=1):
        _cloud(axes[0, c], P[~hidden], limits, color="0.6")
        _cloud(axes[0, c], P[hidden], limits, color="tab:red" if c == 1 else "tab:blue", title=label)
    fig.suptitle(f"Completion of the '{region}' region of held-out shape {example['name']} "
                 f"(hidden: red = truth, blue = reconstruction)")
    fig.tight_layout()
    return _save(fig, folder / f"completion_{region}.png")


def _ppca_curves_figure(plt, curves: dict, folds: int, folder: Path) -> Path:
    """ppca_curves.png: PPCA's k-fold NLL against q, its generalisation and specificity
    against the number of modes (thesis Fig. 5.10; Styner et al. 2003)."""
    from matplotlib.ticker import MaxNLocator

    nll, gen, spec = curves["nll"], curves["generalisation"], curves["specificity"]
    fig, axes = plt.subplots(1, 2, figsize=(8, 3))
    ax = axes[0]
    ax.plot(nll["latent_dims"], nll["train_nll"], "o-", ms=3, label="train")
    ax.errorbar(nll["latent_dims"], nll["test_nll"], yerr=nll["test_nll_stderr"], fmt="s-", ms=3,
                capsize=2, label="held-out")
    ax.set_xlabel("latent dimension q")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("mean NLL per shape")
    ax.set_title(f"PPCA {folds}-fold NLL (best held-out q = {nll['best_latent_dim']})")
    ax.legend()
    ax = axes[1]
    ax.errorbar(gen["modes"], gen["mean"], yerr=gen["stderr"], fmt="o-", ms=3, capsize=2,
                label="generalisation (LOO)")
    ax.plot(spec["modes"], spec["mean"], "s-", ms=3, label="specificity")
    ax.set_xlabel("number of modes m")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("RMS per landmark")
    ax.set_title("PPCA generalisation and specificity (Styner 2003)")
    ax.legend()
    fig.tight_layout()
    return _save(fig, folder / "ppca_curves.png")


def _latent_map_figure(plt, latent: dict, names: list[str], folder: Path) -> Path:
    """latent_map.png: the GP-LVM's 2-D latent points coloured by outlier score, flagged
    and highest-scoring shapes named, and the morph's path (thesis Fig. 5.11)."""
    Z, score, flagged = latent["latents"], latent["score"], latent["flagged"]
    fig, ax = plt.subplots(figsize=(4.5, 4))
    points = ax.scatter(Z[:, 0], Z[:, 1], c=score, cmap="viridis", s=25)
    fig.colorbar(points, ax=ax, label="outlier score (robust z)")
    highlight = set(np.nonzero(flagged)[0].tolist()) | set(np.argsort(-score, kind="stable")[:2].tolist())
    for i in sorted(highlight):
        ax.annotate(names[i], Z[i], textcoords="offset points", xytext=(4, 4),
                    color="tab:red" if flagged[i] else "0.2")
    a, b = latent["from"], latent["to"]
    ax.plot(latent["morph"]["latents"][:, 0], latent["morph"]["latents"][:, 1], "--", color="tab:orange",
            label=f"morph {names[a]} → {names[b]}")
    ax.set_xlabel("latent 1")
    ax.set_ylabel("latent 2")
    ax.set_title("GP-LVM 2-D latent map (red labels: flagged outliers)")
    ax.legend(loc="best")
    fig.tight_layout()
    return _save(fig, folder / "latent_map.png")


def _morph_figure(plt, latent: dict, names: list[str], folder: Path) -> Path:
    """morph.png: the frames of the straight-line latent morph (thesis Fig. 5.12)."""
    frames = latent["morph"]["shapes"]
    limits = _limits(list(frames))
    fig, axes = plt.subplots(1, len(frames), figsize=(1.3 * len(frames), 1.8), squeeze=False)
    for c, (t, P) in enumerate(zip(latent["morph"]["t"], frames)):
        _cloud(axes[0, c], P, limits, color="tab:blue", title=f"t = {t:.2f}")
    fig.suptitle(f"Straight-line latent morph {names[latent['from']]} → {names[latent['to']]} (GP-LVM, Q = 2)")
    fig.tight_layout()
    return _save(fig, folder / "morph.png")
