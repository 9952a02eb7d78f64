"""bench/explored_by_category.py reads the benchmark's files as they are written and reports
per category what it must: an inverted category (AUROC below 50) fixed by one rule and not
the other, where each rule spent its budget, and how the similarity relates to what the model
knew."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("explored_by_category",
                                              ROOT / "bench" / "explored_by_category.py")
ebc = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ebc)

CATS = ("bucket", "door", "switch")


def _write(results: Path) -> None:
    rng = np.random.default_rng(0)
    cats = np.repeat(CATS, 40)
    y = np.tile([True] * 10 + [False] * 30, len(CATS))
    score = np.where(y, 0.8, 0.2) + rng.normal(0, 0.01, y.size)  # ranks every category right
    inverted = np.where(cats == "bucket", 1 - score, score)  # ... but bucket upside down
    for method, pred, budgets in (("none", inverted, (0,)), ("random", score, (5,)),
                                  ("similarity", inverted, (5,)), ("nosim", inverted, (5,))):
        out = results / f"tfr_pull_{method}"
        out.mkdir(parents=True)
        arrays = {"test:success": y, "test:category": cats.astype(str)}
        for seed in (0, 1):
            for b in budgets:
                arrays[f"pred:{method}|{seed}|{b}|aff"] = pred.astype(np.float32)
        np.savez(out / "predictions_tfr_pull.npz", **arrays)
        if method == "none":
            continue
        steps = []
        for i in range(12):
            cat = {"random": CATS[i % 3], "similarity": "switch", "nosim": CATS[i % 3]}[method]
            aff = {"random": 0.1 if i % 2 else 0.9, "similarity": 0.9, "nosim": 0.5}[method]
            steps.append({"round": 1 + i // 6, "group": cat, "affordance": aff,
                          "similarity": {"bucket": 0.9, "door": 0.8, "switch": 0.2}[cat],
                          "success": bool(i % 4 == 0)})
        (out / "explored_tfr_pull.json").write_text(json.dumps({f"{method}_s0_all": {
            "steps": steps}}))


def test_report_names_the_inverted_category_and_where_each_rule_spent(tmp_path):
    _write(tmp_path)
    text = ebc.report(tmp_path, "tfr", "pull")
    rows = {line.split(" | ")[0].strip("| "): line for line in text.splitlines()
            if line.startswith("| ")}
    none = [float(x) for x in rows["none"].strip("| ").split(" | ")[1:]]
    random = [float(x) for x in rows["random"].strip("| ").split(" | ")[1:]]
    assert none[0] < 1.0 and none[1] > 99.0  # bucket inverted, door right
    assert random[0] > 99.0  # the rule that fixed it
    # similarity spent all 12 on switch, none rated low; random half of its picks rated low
    assert "| switch | 4 / " in text and " | 12 / " in rows["switch"]
    assert rows["bucket"].split(" | ")[2] == "0"  # similarity never tried bucket
    assert "/ 0.50 |" in rows["bucket"].split(" | ")[1] + " |"
    # random's similarity: bucket (inverted) rated most familiar -> negative correlation
    assert "similarity vs none's AUROC -" in text
