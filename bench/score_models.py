"""Held-out AUROC of finished models with bootstrap intervals over observations (issue 26).

The training curves (``bench/compare_training.py``) show one number per validation; choosing
between recipes needs the uncertainty of that number. Each ``LABEL=MODEL_PT@VAL_DIR[,VAL_DIR]``
is scored on its own validation collections (a 4,096-point model on 4,096-point clouds;
``A.pt+B.pt`` scores the mean probability of several models, an ensemble; ``--paired`` adds
each model's difference to the first with a paired interval):
per-category AUROC of the training categories (held-out instances), their mean (the
training score), and the novel categories' pooled AUROC, each with a 95 % interval that
resamples whole observations (``--resample instance``: whole objects, the honest unit when a
held-out set has few instances per category); and every held-out row pooled (how a Full-data
model, which has no novel categories, compares on a novel collection). ``--per-instance``
also writes each held-out object's AUROC (STEM_instances.md): is a low score many objects a
little wrong, or a few objects badly?

    .venv/bin/python bench/score_models.py \
        obs750=runs_scale/obs750_pull/model.pt@data/val/cfw_heldout_big,data/valset/novel_cfw \
        --out bench/results/ceiling/scaling/scores
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def score(model_path: str, val_dirs: list[str], n_boot: int, resample: str = "observation",
          per_instance: bool = False) -> dict:
    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.model.metrics import auroc, bootstrap_ci
    from w2e_ros.core.model.network import load_model
    from w2e_ros.core.model.predict import predict_interactions
    from w2e_ros.core.model.training import Validator, method_categories

    paths = model_path.split("+")  # A.pt+B.pt: the ensemble's mean probability
    meta = load_model(paths[0], "cpu")[1]
    aff_cats, sim_cats = method_categories(meta["method"], meta["combo"])
    val = InteractionData.concat([InteractionData.load(d) for d in val_dirs])
    data = Validator(val, aff_cats, sim_cats, meta["primitive"]).data
    prob = np.mean([predict_interactions(load_model(p, "cpu")[0].eval(), data, cache=None)[0]
                    for p in paths], axis=0)
    y, cats = data.success, data.interaction_category
    train_cats = [c for c in dict.fromkeys(aff_cats + sim_cats) if (cats == c).any()]
    if resample == "instance":  # one unit per object: (category, instance) of the row's cloud
        obj = np.char.add(np.char.add(data.category.astype(str), "/"),
                          data.instance.astype(str))
        unit = np.unique(obj, return_inverse=True)[1][data.obs_index]
    else:
        unit = data.obs_index

    def training_score(rows: np.ndarray) -> float:
        return category_mean_auroc(prob, y, cats, train_cats, rows)

    out = {"model": model_path, "step": meta.get("step"), "val": val_dirs,
           "positives": int(y[np.isin(cats, train_cats)].sum())}
    out["training_score"] = bootstrap_ci(training_score, unit, n_boot)
    # every held-out row pooled, whatever its category: a Full-data model has no "novel"
    # group (it trains on every category), so this is how it compares on novel collections
    out["pooled_auroc"] = bootstrap_ci(lambda r: auroc(prob[r], y[r]), unit, n_boot)
    for c in train_cats:
        m = np.flatnonzero(cats == c)
        out[f"{c}_auroc"] = bootstrap_ci(lambda r, m=m: auroc(prob[m][r], y[m][r]),
                                         unit[m], n_boot)
    novel = np.flatnonzero(~np.isin(cats, train_cats))
    if len(novel):
        out["novel_auroc"] = bootstrap_ci(lambda r: auroc(prob[novel][r], y[novel][r]),
                                          unit[novel], n_boot)
        out["novel_positives"] = int(y[novel].sum())
    if per_instance:  # (category, instance) -> (AUROC, positives, rows), training categories
        inst = data.instance[data.obs_index]
        out["instances"] = {
            f"{c}/{i}": (auroc(prob[m], y[m]), int(y[m].sum()), int(m.sum()))
            for c in train_cats for i in np.unique(inst[cats == c])
            for m in [(cats == c) & (inst == i)]}
    out["_rows"] = (prob, y, cats, unit, train_cats)  # for --paired; not written
    return out


def paired_training_score(a: tuple, b: tuple, n_boot: int, novel: bool = False
                          ) -> tuple[float, float, float]:
    """Training score of b minus a on the same held-out rows (``novel``: the pooled AUROC of
    the novel categories' rows), with one bootstrap interval over the shared resampling
    units: the difference, not two overlapping intervals."""
    from w2e_ros.core.model.metrics import auroc, bootstrap_ci

    (pa, y, cats, unit, train_cats), pb = a, b[0]
    if len(pb) != len(pa) or not np.array_equal(b[1], y):
        raise ValueError("--paired needs every model scored on the same held-out rows")
    if novel:
        rows = np.flatnonzero(~np.isin(cats, train_cats))
        return bootstrap_ci(lambda r: auroc(pb[rows][r], y[rows][r]) -
                            auroc(pa[rows][r], y[rows][r]), unit[rows], n_boot)

    return bootstrap_ci(lambda r: category_mean_auroc(pb, y, cats, train_cats, r) -
                        category_mean_auroc(pa, y, cats, train_cats, r), unit, n_boot)


def category_mean_auroc(prob: np.ndarray, y: np.ndarray, cats: np.ndarray,
                        train_cats: list[str], rows: np.ndarray) -> float:
    """The training score: the mean over the training categories of their AUROC on ``rows``."""
    from w2e_ros.core.model.metrics import auroc

    return float(np.nanmean([auroc(prob[rows][cats[rows] == c], y[rows][cats[rows] == c])
                             for c in train_cats]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+", help="LABEL=MODEL_PT[+MODEL_PT...]@VAL_DIR[,VAL_DIR...]")
    ap.add_argument("--boot", type=int, default=500)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--resample", choices=("observation", "instance"), default="observation",
                    help="bootstrap unit: a held-out cloud, or a held-out object")
    ap.add_argument("--per-instance", action="store_true",
                    help="also each held-out object's AUROC (STEM_instances.md)")
    ap.add_argument("--paired", action="store_true",
                    help="also each model's training score (and novel AUROC) minus the first "
                         "model's, with a paired interval (minus_first, novel_minus_first)")
    ap.add_argument("--out", required=True, help="stem: writes STEM.json and STEM.md")
    a = ap.parse_args()
    import torch

    torch.set_num_threads(a.threads)
    rows = {}
    for spec in a.models:
        label, rest = spec.split("=", 1)
        path, _, dirs = rest.partition("@")
        rows[label] = score(path, dirs.split(","), a.boot, a.resample, a.per_instance)
    data_rows = {k: r.pop("_rows") for k, r in rows.items()}
    if a.paired:  # every model against the first, on the same rows
        first = next(iter(data_rows.values()))
        for k in list(rows)[1:]:
            rows[k]["minus_first"] = paired_training_score(first, data_rows[k], a.boot)
            if "novel_auroc" in rows[k]:
                rows[k]["novel_minus_first"] = paired_training_score(
                    first, data_rows[k], a.boot, novel=True)
    keys = list(dict.fromkeys(k for r in rows.values() for k, v in r.items()
                              if isinstance(v, tuple)))

    def cell(v) -> str:
        return "–" if v is None else f"{100 * v[0]:.1f} [{100 * v[1]:.1f}, {100 * v[2]:.1f}]"

    lines = ["| model | step | " + " | ".join(keys) + " |", "|---|---|" + "---|" * len(keys)]
    for label, r in rows.items():
        lines.append(f"| {label} | {r['step']} | " + " | ".join(cell(r.get(k)) for k in keys)
                     + " |")
    unit = "observations" if a.resample == "observation" else "held-out objects"
    text = (f"Held-out AUROC, % [95 % bootstrap interval over {unit}]; training score = "
            "mean over the training categories.\n\n" + "\n".join(lines) + "\n")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if a.per_instance:
        out.with_name(out.name + "_instances.md").write_text(_instance_table(rows))
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    out.with_suffix(".md").write_text(text)
    print(text)
    return 0


def _instance_table(rows: dict) -> str:
    """One line per held-out object, one column per model: AUROC % (positives / rows)."""
    objs = list(dict.fromkeys(o for r in rows.values() for o in r.get("instances", {})))
    lines = ["| object | " + " | ".join(rows) + " |", "|---|" + "---|" * len(rows)]
    for o in sorted(objs, key=lambda k: (k.split("/")[0], int(k.split("/")[1]))):
        cells = []
        for r in rows.values():
            v = r.get("instances", {}).get(o)
            cells.append("–" if v is None else f"{100 * v[0]:.1f} ({v[1]} / {v[2]})")
        lines.append(f"| {o} | " + " | ".join(cells) + " |")
    return ("Held-out AUROC per object, % (positive pulls / rows): few objects badly wrong, or "
            "many a little?\n\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
