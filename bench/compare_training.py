"""Held-out curves of several training runs side by side (issue 8: why does a model generalise).

Reads the validation records of each run's ``metrics.jsonl`` (``w2e train --val-data``) and,
for finished checkpoints given with ``--checkpoint LABEL=PATH``, scores them with the same
validator on ``--val-data``. Writes a markdown table (metric at every validated step, and each
run's best-step row) and one image with a panel per metric.

    .venv/bin/python bench/compare_training.py --runs where2act=runs/where2act_cfw_pull \
        nosim=runs_abl/w2e_nosim_cabinet_pull w2e=runs_abl/w2e_pull_1440 \
        --checkpoint shipped=checkpoints/w2e_cfw_pull.pt \
        --val-data data/val/cfw_heldout data/valset/novel_cfw --out bench/results/training_ablation
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

METRICS = ("caff_auroc", "csim_auroc", "novel_auroc", "novel_fscore", "novel_ap",
           "novel_valid_auroc", "novel_simcorr_auroc")


def _records(run: Path) -> list[dict]:
    rows = [json.loads(s) for s in (run / "metrics.jsonl").read_text().splitlines()]
    return [r for r in rows if "val_score" in r]


def _score_checkpoint(path: str, data) -> dict:
    from w2e_ros.core.model.network import load_model
    from w2e_ros.core.model.training import Validator, method_categories

    model, meta = load_model(path, "cpu")
    model.eval()
    aff, sim = method_categories(meta["method"], meta["combo"])
    out = Validator(data, aff, sim, meta["primitive"]).run(model)
    return {"step": meta.get("step", -1), **{f"val_{k}": v for k, v in out.items()}}


def _tables(curves: dict[str, list[dict]], points: dict[str, dict],
            metrics: tuple[str, ...]) -> str:
    """The markdown: each run's best-step row and each checkpoint's, then every validated
    step."""

    def cell(r: dict, m: str) -> str:
        v = r.get(f"val_{m}")
        return "–" if v is None or not np.isfinite(v) else f"{100 * v:.1f}"

    lines = ["| run | step | " + " | ".join(metrics) + " |",
             "|---|---|" + "---|" * len(metrics)]
    for label, recs in curves.items():
        for r in recs:
            lines.append(f"| {label} | {r['step']} | " + " | ".join(cell(r, m) for m in metrics)
                         + " |")
    best = ["| run (best step by the training-category score) | step | "
            + " | ".join(metrics) + " |", "|---|---|" + "---|" * len(metrics)]
    for label, recs in curves.items():
        r = max(recs, key=lambda r: r["val_score"])
        best.append(f"| {label} | {r['step']} | " + " | ".join(cell(r, m) for m in metrics)
                    + " |")
    for label, r in points.items():
        best.append(f"| {label} | {r['step']} | " + " | ".join(cell(r, m) for m in metrics)
                    + " |")
    return ("Held-out validation, % (caff / csim: unseen instances of the training categories "
            "(a where2act model's caff holds all three); novel: explore instances of the 11 "
            "novel categories, the validation split). Rows of runs are as validated during "
            "training, before the similarity calibration; rows of checkpoints are scored now."
            "\n\n"
            + "\n".join(best) + "\n\nEvery validated step:\n\n" + "\n".join(lines) + "\n")


def _figure(curves: dict[str, list[dict]], points: dict[str, dict], path: Path) -> None:
    """One panel per metric: the runs' validation curves, the checkpoints as stars."""
    import matplotlib.pyplot as plt

    from w2e_ros.core.model.viz import write_figure  # selects the Agg backend

    shown = tuple(m for m in ("caff_auroc", "csim_auroc", "novel_auroc", "novel_fscore")
                  if any(recs and f"val_{m}" in recs[0] for recs in curves.values())
                  or any(f"val_{m}" in r for r in points.values()))
    colour = {label: f"C{i}" for i, label in enumerate([*curves, *points])}
    fig, axes = plt.subplots(1, len(shown), figsize=(4 * len(shown), 3.4), squeeze=False)
    axes = axes[0]
    for ax, m in zip(axes, shown, strict=True):
        for label, recs in curves.items():
            if recs and f"val_{m}" in recs[0]:  # a where2act run has no csim group
                ax.plot([r["step"] for r in recs], [100 * r[f"val_{m}"] for r in recs], "o-",
                        label=label, ms=3, color=colour[label])
        for label, r in points.items():
            if f"val_{m}" in r:
                ax.plot([r["step"]], [100 * r[f"val_{m}"]], "*", ms=10, label=label,
                        color=colour[label])
        ax.set_title(m.replace("_", " ") + (" (where2act: all 3)" if m == "caff_auroc" else ""))
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("%")
    axes[-1].legend(fontsize=7)
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", nargs="*", default=[], help="LABEL=RUN_DIR")
    ap.add_argument("--checkpoint", nargs="*", default=[], help="LABEL=MODEL_PT (scored now)")
    ap.add_argument("--val-data", nargs="*", default=[])
    ap.add_argument("--metrics", nargs="*", default=list(METRICS),
                    help="validator keys shown as columns (default: %(default)s)")
    ap.add_argument("--name", default="training_ablation", help="stem of the output files")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    import torch

    torch.set_num_threads(a.threads)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    curves: dict[str, list[dict]] = {}
    for spec in a.runs:
        label, run = spec.split("=", 1)
        curves[label] = _records(Path(run))
    points = {}
    if a.checkpoint:
        from w2e_ros.core.dataset.interactions import InteractionData

        val = InteractionData.concat([InteractionData.load(d) for d in a.val_data])
        for spec in a.checkpoint:
            label, path = spec.split("=", 1)
            points[label] = _score_checkpoint(path, val)

    text = _tables(curves, points, tuple(a.metrics))
    (out / f"{a.name}.md").write_text(text)
    (out / f"{a.name}.json").write_text(json.dumps(
        {"curves": curves, "checkpoints": points}, indent=1))
    print(text)
    _figure(curves, points, out / f"{a.name}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
