"""Where does an F-score difference come from? Precision, recall and the share of test
interactions predicted to succeed, per method, at one budget of a ``w2e benchmark`` run.

The benchmark's F-score thresholds the affordance at 0.5 (as the paper and the reference
do), so a method can gain F-score by predicting more successes without ranking them any
better (AUROC, AP). This separates the two.

    .venv/bin/python bench/threshold_rates.py results/final --primitive pull --budget 5
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

from w2e_ros.core.model.metrics import fscore


def rates(pred: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """(precision, recall, predicted-positive share) at the 0.5 threshold."""
    f = fscore(pred > 0.5, y)
    return f["precision"], f["recall"], float(np.mean(pred > 0.5))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="w2e benchmark --out directory")
    ap.add_argument("--combo", default="cfw")
    ap.add_argument("--primitive", default="pull")
    ap.add_argument("--budget", type=int, default=5)
    a = ap.parse_args()
    z = np.load(Path(a.out) / f"predictions_{a.combo}_{a.primitive}.npz")
    y = z["test:success"].astype(bool)
    per: dict[str, list[tuple[float, float, float]]] = defaultdict(list)
    for k in z.files:
        if not k.startswith("pred:"):
            continue
        method, _, b, what = k[5:].split("|")
        if what == "aff" and int(b) == a.budget:
            per[method].append(rates(z[k], y))
    print(f"{a.primitive}, budget {a.budget}: mean over seeds, % (test success rate "
          f"{100 * y.mean():.1f})")
    print("| method | seeds | precision | recall | predicted to succeed |")
    print("|---|---|---|---|---|")
    for method, r in per.items():
        p, rc, pp = np.mean(r, axis=0)
        print(f"| {method} | {len(r)} | {100 * p:.1f} | {100 * rc:.1f} | {100 * pp:.1f} |")


if __name__ == "__main__":
    main()
