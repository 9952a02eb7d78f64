"""Does exploring unlearn what the model knew because one fit serves every category?

Item 1 of issue 40 found that a pooled fit on the explored pulls of all novel categories lifts
the categories the model did not know and lowers the ones it knew (microwave, table, door,
switch, washing_machine: −10 to −15 AUROC under every random set). If that is interference
between categories, adapting one model per category (``w2e benchmark --mode per-category``:
each category explored and fitted on its own, its judged rows predicted by its own model)
keeps the known categories and the pooled AUROC rises. This reads the two benchmarks' outputs
(same judged rows) and reports, per budget, the pooled AUROC / F-score of none, the pooled
fit and the per-category fits, their paired differences (95 % bootstrap over judged
observations and seeds), the seeds ending below none, and the per-category AUROC at the
largest budget.

    .venv/bin/python bench/per_category_fit.py --pooled results/ts_val_r \
        --per-category results/pc_val_r results/pc_val_r2 --seeds 0 1 2 3 4 5 6 7 8 9 \
        --out bench/results/per_category_fit/validation
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from w2e_ros.core.model.metrics import affordance_fscore_from_probs, auroc

ARMS = ("none", "pooled", "per_category")


def load(path: Path) -> tuple[dict[tuple[str, int, int], np.ndarray], dict[str, np.ndarray]]:
    """Affordance predictions keyed (method, seed, budget) and the judged rows' arrays."""
    z = np.load(path)
    preds = {}
    for k in z.files:
        if k.startswith("pred:") and k.endswith("|aff"):
            m, s, b, _ = k[5:].split("|")
            preds[(m, int(s), int(b))] = z[k]
    return preds, {k[5:]: z[k] for k in z.files if k.startswith("test:")}


def fscore(p: np.ndarray, y: np.ndarray) -> float:
    return affordance_fscore_from_probs(p, y)["fscore"]


def resample(obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Row indices of a bootstrap draw of the judged observations (whole clouds)."""
    groups = np.unique(obs)
    rows = [np.flatnonzero(obs == g) for g in groups]
    return np.concatenate([rows[i] for i in rng.integers(len(groups), size=len(groups))])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pooled", nargs="+", required=True,
                    help="w2e benchmark --out folders, --mode all (with none)")
    ap.add_argument("--per-category", nargs="+", required=True,
                    help="w2e benchmark --out folders, --mode per-category")
    ap.add_argument("--method", default="random")
    ap.add_argument("--combo", default="cfw")
    ap.add_argument("--primitive", default="pull")
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--boot", type=int, default=1000)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    name = f"predictions_{a.combo}_{a.primitive}.npz"
    pooled: dict = {}
    per_cat: dict = {}
    test: dict = {}
    for target, dirs in ((pooled, a.pooled), (per_cat, a.per_category)):
        for d in dirs:
            preds, t = load(Path(d) / name)
            target.update(preds)
            for k in ("success", "obs"):
                if test and not np.array_equal(test[k], t[k]):
                    raise SystemExit(f"{d} judged other rows than the first folder ({k})")
            test = test or t
    y, obs, cat = test["success"], test["obs"], test["category"]  # every judged row
    budgets = sorted({b for (m, _, b) in pooled if m == a.method and b > 0})
    none = pooled[("none", a.seeds[0], 0)]

    def arm(which: str, s: int, b: int) -> np.ndarray:
        if which == "none":
            return none
        src = pooled if which == "pooled" else per_cat
        return src[(a.method, s, b)]

    rng = np.random.default_rng(0)
    draws = [resample(obs, rng) for _ in range(a.boot)]
    report: dict = {"method": a.method, "seeds": a.seeds, "budgets": budgets,
                    "judged_rows": len(y), "positives": int(y.sum()), "by_budget": {}}
    for b in budgets:
        row: dict = {}
        for metric, fn in (("auroc", auroc), ("fscore", fscore)):
            point = {w: [100 * fn(arm(w, s, b), y) for s in a.seeds] for w in ARMS}
            boot = {w: np.array([[100 * fn(arm(w, s, b)[d], y[d]) for s in a.seeds]
                                 for d in draws]) for w in ARMS}  # (boot, seeds)
            pick = rng.integers(len(a.seeds), size=(a.boot, len(a.seeds)))

            def ci(x: np.ndarray, pick: np.ndarray = pick) -> list[float]:  # seeds resampled
                m = np.take_along_axis(x, pick, axis=1).mean(1)
                return [round(float(v), 2) for v in np.percentile(m, [2.5, 97.5])]

            row[metric] = {
                **{w: round(float(np.mean(point[w])), 2) for w in ARMS},
                "per_category - pooled": [round(float(np.mean(point["per_category"])
                                                      - np.mean(point["pooled"])), 2),
                                          ci(boot["per_category"] - boot["pooled"])],
                "per_category - none": [round(float(np.mean(point["per_category"])
                                                    - np.mean(point["none"])), 2),
                                        ci(boot["per_category"] - boot["none"])],
                "pooled - none": [round(float(np.mean(point["pooled"])
                                              - np.mean(point["none"])), 2),
                                  ci(boot["pooled"] - boot["none"])],
                "seeds below none": {w: int(sum(v < point["none"][0] for v in point[w]))
                                     for w in ("pooled", "per_category")},
            }
        report["by_budget"][str(b)] = row
    top = budgets[-1]
    report["per_category_auroc"] = {
        c: {w: round(float(np.mean([100 * auroc(arm(w, s, top)[cat == c], y[cat == c])
                                    for s in a.seeds])), 1) for w in ARMS}
        for c in dict.fromkeys(cat.tolist())}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "per_category_fit.json").write_text(json.dumps(report, indent=1) + "\n")
    (out / "per_category_fit.md").write_text(tables(report) + "\n")
    print(tables(report))


def tables(r: dict) -> str:
    def d(x: list) -> str:
        return f"{x[0]:+.1f} [{x[1][0]:+.1f}, {x[1][1]:+.1f}]"

    lines = [f"# One fit for all categories or one per category ({r['method']}, seeds "
             f"{', '.join(map(str, r['seeds']))}; {r['judged_rows']} judged pulls, "
             f"{r['positives']} successes)", "",
             "| budget | metric | none | pooled fit | per-category fits | per-category − pooled "
             "| pooled − none | per-category − none | seeds below none (pooled / per-category) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for b, row in r["by_budget"].items():
        for metric, label in (("auroc", "AUROC"), ("fscore", "F-score")):
            m = row[metric]
            lines.append(f"| {b} | {label} | {m['none']:.1f} | {m['pooled']:.1f} | "
                         f"{m['per_category']:.1f} | {d(m['per_category - pooled'])} | "
                         f"{d(m['pooled - none'])} | {d(m['per_category - none'])} | "
                         f"{m['seeds below none']['pooled']} / "
                         f"{m['seeds below none']['per_category']} |")
    top = r["budgets"][-1]
    lines += ["", f"Per category, AUROC at budget {top} (mean over seeds; rows of the category)",
              "", "| category | none | pooled fit | per-category fit |", "|---|---|---|---|"]
    for c, v in r["per_category_auroc"].items():
        lines.append(f"| {c} | {v['none']:.1f} | {v['pooled']:.1f} | {v['per_category']:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
