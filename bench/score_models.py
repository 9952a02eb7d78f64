"""Held-out AUROC of finished models with bootstrap intervals over observations (issue 26).

The training curves (``bench/compare_training.py``) show one number per validation; choosing
between recipes needs the uncertainty of that number. Each ``LABEL=MODEL_PT@VAL_DIR[,VAL_DIR]``
is scored on its own validation collections (a 4,096-point model on 4,096-point clouds):
per-category AUROC of the training categories (held-out instances), their mean (the
training score), and the novel categories' pooled AUROC, each with a 95 % interval that
resamples whole observations; and every held-out row pooled (how a Full-data model, which has no
novel categories, compares on a novel collection).

    .venv/bin/python bench/score_models.py \
        obs750=runs_scale/obs750_pull/model.pt@data/val/cfw_heldout_big,data/valset/novel_cfw \
        --out bench/results/ceiling/scaling/scores
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def score(model_path: str, val_dirs: list[str], n_boot: int) -> dict:
    from w2e_ros.core.data import InteractionData
    from w2e_ros.core.metrics import auroc, bootstrap_ci
    from w2e_ros.core.model import load_model
    from w2e_ros.core.predict import predict_interactions
    from w2e_ros.core.training import Validator, method_categories

    model, meta = load_model(model_path, "cpu")
    aff_cats, sim_cats = method_categories(meta["method"], meta["combo"])
    val = InteractionData.concat([InteractionData.load(d) for d in val_dirs])
    data = Validator(val, aff_cats, sim_cats, meta["primitive"]).data
    prob, _ = predict_interactions(model, data, cache=None)
    y, cats = data.success, data.interaction_category
    train_cats = [c for c in dict.fromkeys(aff_cats + sim_cats) if (cats == c).any()]

    def training_score(rows: np.ndarray) -> float:
        return float(np.nanmean([auroc(prob[rows][cats[rows] == c], y[rows][cats[rows] == c])
                                 for c in train_cats]))

    out = {"model": model_path, "step": meta.get("step"), "val": val_dirs,
           "positives": int(y[np.isin(cats, train_cats)].sum())}
    out["training_score"] = bootstrap_ci(training_score, data.obs_index, n_boot)
    # every held-out row pooled, whatever its category: a Full-data model has no "novel"
    # group (it trains on every category), so this is how it compares on novel collections
    out["pooled_auroc"] = bootstrap_ci(lambda r: auroc(prob[r], y[r]), data.obs_index, n_boot)
    for c in train_cats:
        m = np.flatnonzero(cats == c)
        out[f"{c}_auroc"] = bootstrap_ci(lambda r, m=m: auroc(prob[m][r], y[m][r]),
                                         data.obs_index[m], n_boot)
    novel = np.flatnonzero(~np.isin(cats, train_cats))
    if len(novel):
        out["novel_auroc"] = bootstrap_ci(lambda r: auroc(prob[novel][r], y[novel][r]),
                                          data.obs_index[novel], n_boot)
        out["novel_positives"] = int(y[novel].sum())
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+", help="LABEL=MODEL_PT@VAL_DIR[,VAL_DIR...]")
    ap.add_argument("--boot", type=int, default=500)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", required=True, help="stem: writes STEM.json and STEM.md")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(a.threads)
    rows = {}
    for spec in a.models:
        label, rest = spec.split("=", 1)
        path, _, dirs = rest.partition("@")
        rows[label] = score(path, dirs.split(","), a.boot)
    keys = list(dict.fromkeys(k for r in rows.values() for k, v in r.items()
                              if isinstance(v, tuple)))

    def cell(v) -> str:
        return "–" if v is None else f"{100 * v[0]:.1f} [{100 * v[1]:.1f}, {100 * v[2]:.1f}]"

    lines = ["| model | step | " + " | ".join(keys) + " |", "|---|---|" + "---|" * len(keys)]
    for label, r in rows.items():
        lines.append(f"| {label} | {r['step']} | " + " | ".join(cell(r.get(k)) for k in keys)
                     + " |")
    text = ("Held-out AUROC, % [95 % bootstrap interval over observations]; training score = "
            "mean over the training categories.\n\n" + "\n".join(lines) + "\n")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    out.with_suffix(".md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
