"""Markdown tables for docs/results.md from `shapegen evaluate` report folders.

Usage: python bench/evaluate_tables.py bench_output/evaluate/psb_Vase bench_output/evaluate/psb_Cup ...
Prints, per report folder, the completion table (mean summed squared error of the hidden
coordinates, thesis Table 5.1 protocol) and the sample-quality table, then one cross-class
completion-ordering line per region.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

LABELS = {"ppca": "PPCA", "gplvm": "GP-LVM", "bgplvm": "BGP-LVM", "training-set": "training set (NN)",
          "mean-shape": "mean shape"}


def fmt(x, digits=4):
    return "–" if x is None else f"{x:.{digits}g}"


def tables(folder: Path) -> str:
    report = json.loads((folder / "report.json").read_text())
    models, regions = report["models"], report["settings"]["regions"]
    lines = [f"### {folder.name}: {report['data']['n_shapes']} shapes × {report['data']['n_landmarks']} landmarks",
             "", "| model | q per fold | " + " | ".join(regions) + " | ordering BGP ≤ GP ≤ PPCA |",
             "|---|---|" + "---|" * len(regions) + "---|"]
    order_ok = {}
    for r in regions:
        values = {m: models[m]["completion"][r]["mean_sse"] for m in ("ppca", "gplvm", "bgplvm") if m in models}
        order_ok[r] = (len(values) == 3 and values["bgplvm"] <= values["gplvm"] <= values["ppca"])
    for name, entry in models.items():
        q = entry["latent_dim_per_fold"]
        q_text = "–" if entry["kind"] == "baseline" else (str(q[0]) if len(set(q)) == 1 else f"{min(q)}–{max(q)}")
        cells = [f"{fmt(entry['completion'][r]['mean_sse'])} ({fmt(entry['completion'][r]['relative_to_mean_shape'], 3)})"
                 for r in regions]
        last = ", ".join(f"{r}: {'yes' if order_ok[r] else 'no'}" for r in regions) if name == "ppca" else ""
        lines.append(f"| {LABELS.get(name, name)} | {q_text} | " + " | ".join(cells) + f" | {last} |")
    lines += ["", "| model | q (all) | novelty median | specificity | held-out recon. RMS | MMD | coverage | 1-NNA |",
              "|---|---|---|---|---|---|---|---|"]
    for name, entry in models.items():
        hs = entry["heldout_samples"]
        sets = " | ".join(fmt(hs[k]["mean"], 3) for k in ("mmd", "coverage", "one_nna"))
        if entry["kind"] == "baseline":
            lines.append(f"| {LABELS.get(name, name)} | – | – | – | – | {sets} |")
        else:
            full = entry["all_shapes"]
            lines.append(f"| {LABELS[name]} | {full['latent_dim']} | {fmt(full['novelty']['median'], 3)} | "
                         f"{fmt(full['specificity'], 3)} | {fmt(entry['heldout_reconstruction_rms']['mean'], 3)} | {sets} |")
    if all(m in models for m in ("ppca", "gplvm", "bgplvm")):
        wins = []
        for r in regions:
            per = {m: models[m]["completion"][r]["per_shape"] for m in ("ppca", "gplvm", "bgplvm")}
            shapes = list(per["ppca"])
            gp = sum(per["gplvm"][k] < per["ppca"][k] for k in shapes)
            bgp = sum(per["bgplvm"][k] < per["ppca"][k] for k in shapes)
            wins.append(f"{r}: GP-LVM {gp}/{len(shapes)}, BGP-LVM {bgp}/{len(shapes)}")
        lines += ["", "Held-out shapes completed better than by PPCA (paired): " + "; ".join(wins)]
    nll = report["ppca_curves"]["nll_vs_latent_dim"]
    latent = report.get("latent_map") or {}
    lines += ["", f"PPCA held-out NLL lowest at q = {nll['best_latent_dim']} (of {len(nll['latent_dims'])}); "
              f"training-shape NN distance (median) {fmt(report['data']['training_nn_median_procrustes_rms'], 3)}; "
              f"1-NNA chance level {fmt(report['settings']['one_nna_chance_level'], 3)}; "
              f"latent-map outliers: {', '.join(latent.get('outliers', [])) or 'none'}", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        print(tables(Path(arg)))
