"""What did each rule pick, round by round? Success rate of the executed interactions.

A selection rule teaches the affordance head through the successes it finds (the research
log: the unexpected success is the teaching signal). This reads the exploration logs of
``w2e benchmark`` runs (``explored_<combo>_<primitive>.json``) and prints, per method, the
share of successful interactions in each block of ``--block`` interactions, over seeds;
``--allocation`` adds where the picks went (objects touched, objects with a success, spread
over categories, the model's predicted success of the picks) and each category's share of the
pulls with their success.

    .venv/bin/python bench/pick_rounds.py results/val_random results/val_sim_frozen \
        --combo cfw --primitive pull --block 55
"""

from __future__ import annotations

import argparse
import json
import re
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

RUN_KEY = re.compile(r"_s-?\d+_.*$")  # the _s<seed>_<group> end of a run's key


def blocks(steps: list[dict], size: int) -> list[tuple[int, int]]:
    """(successes, interactions) per block of ``size`` executed interactions."""
    ok = [bool(s["success"]) for s in steps]
    return [(sum(ok[i:i + size]), len(ok[i:i + size])) for i in range(0, len(ok), size)]


def spread(steps: list[dict]) -> dict[str, float]:
    """Where one run's picks went: objects, objects with a success, category entropy, the
    share of its 3 most explored categories, predicted and real success of the picks."""
    targets = [s["target"] for s in steps]
    cats = Counter(t.split("/")[0] for t in targets)
    p = np.array(list(cats.values()), float) / max(len(targets), 1)
    return {"objects": len(set(targets)),
            "objects_with_success": len({s["target"] for s in steps if s["success"]}),
            "entropy": float(-(p * np.log(p)).sum()),
            "top3": sum(sorted(cats.values())[-3:]) / max(len(targets), 1),
            "predicted": float(np.mean([s["affordance"] for s in steps])),
            "success": float(np.mean([bool(s["success"]) for s in steps]))}


def allocation(runs: dict[str, list[list[dict]]]) -> None:
    """The tables of ``--allocation``: per method the mean of :func:`spread` over its runs,
    then per category (the first method's order) the share of pulls and their success."""
    print("\nWhere the picks went, mean over runs\n")
    print("| method | objects touched | objects with a success | category entropy (nats) | "
          "share of the 3 most explored categories | predicted success of the picks | "
          "real success of the picks |")
    print("|---|---|---|---|---|---|---|")
    for method, rs in runs.items():
        m = {k: np.mean([spread(r)[k] for r in rs]) for k in spread(rs[0])}
        print(f"| {method} | {m['objects']:.1f} | {m['objects_with_success']:.1f} | "
              f"{m['entropy']:.2f} | {100 * m['top3']:.0f} % | {m['predicted']:.3f} | "
              f"{100 * m['success']:.1f} % |")
    counts = {}
    for method, rs in runs.items():
        n, ok = Counter(), Counter()
        for s in (s for r in rs for s in r):
            n[s["target"].split("/")[0]] += 1
            ok[s["target"].split("/")[0]] += bool(s["success"])
        counts[method] = (n, ok)
    first = next(iter(counts.values()))[0]
    print("\nShare of the interactions per category (their success), all runs\n")
    print("| category | " + " | ".join(counts) + " |")
    print("|---|" + "---|" * len(counts))
    for cat, _ in first.most_common():
        cells = [f"{100 * n[cat] / sum(n.values()):.0f} % ({100 * ok[cat] / n[cat]:.0f} %)"
                 if n[cat] else "0 %" for n, ok in counts.values()]
        print(f"| {cat} | " + " | ".join(cells) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", help="w2e benchmark --out directories")
    ap.add_argument("--combo", default="cfw")
    ap.add_argument("--primitive", default="pull")
    ap.add_argument("--block", type=int, default=55, help="interactions per block")
    ap.add_argument("--allocation", action="store_true",
                    help="also where the picks went: objects, categories, predicted success")
    a = ap.parse_args()
    per: dict[str, list[list[tuple[int, int]]]] = defaultdict(list)
    steps: dict[str, list[list[dict]]] = defaultdict(list)
    for d in a.dirs:
        f = Path(d) / f"explored_{a.combo}_{a.primitive}.json"
        for key, run in json.loads(f.read_text()).items():
            # keys are <method>_s<seed>_<group>; a method name may hold "_s" itself
            method = f"{RUN_KEY.sub('', key)} ({Path(d).name})"
            per[method].append(blocks(run["steps"], a.block))
            if run["steps"]:
                steps[method].append(run["steps"])
    n_blocks = max(len(b) for runs in per.values() for b in runs)
    print(f"Success of the executed interactions (%), blocks of {a.block}, summed over seeds")
    print("| method | seeds | spent | " + " | ".join(f"{i * a.block + 1}-{(i + 1) * a.block}"
                                                   for i in range(n_blocks)) + " | all |")
    print("|---|---|---|" + "---|" * (n_blocks + 1))
    for method, runs in per.items():
        cells = []
        for i in range(n_blocks):
            s = sum(r[i][0] for r in runs if len(r) > i)
            n = sum(r[i][1] for r in runs if len(r) > i)
            cells.append(f"{100 * s / n:.1f}" if n else "-")
        tot_s = sum(x[0] for r in runs for x in r)
        tot_n = sum(x[1] for r in runs for x in r)
        spent = np.mean([sum(x[1] for x in r) for r in runs])
        print(f"| {method} | {len(runs)} | {spent:.0f} | " + " | ".join(cells)
              + f" | {100 * tot_s / max(tot_n, 1):.1f} |")
    if a.allocation:
        allocation(steps)


if __name__ == "__main__":
    main()
