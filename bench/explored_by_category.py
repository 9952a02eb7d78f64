"""What each exploration rule explored, per novel category, against what the model knew there.

For one combination and primitive of ``bench/combos.sh`` (one results directory per method):

1. the test AUROC per category before exploring (``none``) and after each rule (budget 5, mean
   over the exploration seeds);
2. the similarity of random's first two rounds of picks (unbiased: the base model and one fit)
   per category, beside the picks' accuracy and none's AUROC, with the rank correlations: does
   the similarity call the categories the model gets wrong unfamiliar?
3. per rule and category, how many interactions it spent, their success rate, and the share of
   picks the model rated below 0.3 (where an inverted model keeps its successes).

    .venv/bin/python bench/explored_by_category.py --combo tfr --primitive pull \
        --results results/combos_today --out bench/results/combos_today/tfr_pull/by_category.md
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from w2e_ros.core.model.metrics import auroc

RULES = ("random", "similarity", "nosim")
LOW = 0.3  # "rated low": below this predicted affordance


def _steps(results: Path, combo: str, prim: str, rule: str) -> list[dict]:
    path = results / f"{combo}_{prim}_{rule}" / f"explored_{combo}_{prim}.json"
    return [s for run in json.loads(path.read_text()).values() for s in run["steps"]]


def _category_auroc(z, key: str, cats: np.ndarray, y: np.ndarray, c: str) -> float:
    sel = cats == c
    return auroc(z[key][sel], y[sel]) if y[sel].any() and (~y[sel]).any() else float("nan")


def report(results: Path, combo: str, prim: str, budget: int = 5,
           rules: tuple[str, ...] = RULES) -> str:
    z = np.load(results / f"{combo}_{prim}_none" / f"predictions_{combo}_{prim}.npz")
    y, cats = z["test:success"].astype(bool), z["test:category"]
    names = sorted(set(cats.tolist()))
    preds = {"none": z}
    for rule in rules:
        preds[rule] = np.load(results / f"{combo}_{prim}_{rule}"
                              / f"predictions_{combo}_{prim}.npz")

    def mean_auroc(method: str, c: str) -> float:
        f = preds[method]
        b = 0 if method == "none" else budget
        keys = sorted(k for k in f.files if k.startswith(f"pred:{method}|")
                      and k.endswith(f"|{b}|aff"))
        return float(np.nanmean([_category_auroc(f, k, cats, y, c) for k in keys]))

    lines = [f"# {combo} {prim}: what each rule explored, per category", "",
             f"## Test AUROC per category (%), budget {budget}, mean over seeds", "",
             "| method | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    base = {c: mean_auroc("none", c) for c in names}
    for method in ("none", *rules):
        vals = base if method == "none" else {c: mean_auroc(method, c) for c in names}
        lines.append(f"| {method} | " + " | ".join(f"{100 * vals[c]:.1f}" for c in names) + " |")

    first = defaultdict(list)  # random's first two rounds
    for s in _steps(results, combo, prim, "random"):
        if s["round"] <= 2:
            first[s["group"]].append(s)
    lines += ["", "## The similarity of random's first two rounds of picks", "",
              "| category | picks | mean similarity | picks' accuracy | none's AUROC |",
              "|---|---|---|---|---|"]
    rows = []
    for c in names:
        st = first.get(c, [])
        if not st:
            continue
        sim = float(np.mean([s["similarity"] for s in st]))
        acc = float(np.mean([(s["affordance"] > 0.5) == s["success"] for s in st]))
        rows.append((sim, acc, base[c]))
        lines.append(f"| {c} | {len(st)} | {sim:.2f} | {acc:.2f} | {100 * base[c]:.1f} |")
    r = np.array(rows)
    lines += ["", f"Spearman over categories: similarity vs none's AUROC "
              f"{spearmanr(r[:, 0], r[:, 2])[0]:+.2f}, similarity vs the picks' accuracy "
              f"{spearmanr(r[:, 0], r[:, 1])[0]:+.2f}.", "",
              f"## Where each rule spent its budget (all seeds): interactions / success rate / "
              f"share rated below {LOW}", "",
              "| category | " + " | ".join(rules) + " |", "|---" * (len(rules) + 1) + "|"]
    spent = {rule: defaultdict(list) for rule in rules}
    for rule in rules:
        for s in _steps(results, combo, prim, rule):
            spent[rule][s["group"]].append(s)
    for c in names:
        cells = []
        for rule in rules:
            st = spent[rule].get(c, [])
            if not st:
                cells.append("0")
                continue
            ok = np.mean([s["success"] for s in st])
            low = np.mean([s["affordance"] < LOW for s in st])
            cells.append(f"{len(st)} / {ok:.2f} / {low:.2f}")
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--combo", required=True)
    p.add_argument("--primitive", default="pull", choices=("push", "pull"))
    p.add_argument("--results", type=Path, default=Path("results/combos_today"),
                   help="directory of the per-method results (<combo>_<primitive>_<method>)")
    p.add_argument("--budget", type=int, default=5)
    p.add_argument("--rules", nargs="+", default=list(RULES),
                   help="the rules compared (random among them: its first rounds are read)")
    p.add_argument("--out", type=Path, help="also write the report here (markdown)")
    a = p.parse_args()
    text = report(a.results, a.combo, a.primitive, a.budget, tuple(a.rules))
    print(text)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text)


if __name__ == "__main__":
    main()
