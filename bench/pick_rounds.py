"""What did each rule pick, round by round? Success rate of the executed interactions.

A selection rule teaches the affordance head through the successes it finds (the research
log: the unexpected success is the teaching signal). This reads the exploration logs of
``w2e benchmark`` runs (``explored_<combo>_<primitive>.json``) and prints, per method, the
share of successful interactions in each block of ``--block`` interactions, over seeds.

    .venv/bin/python bench/pick_rounds.py results/val_random results/val_sim_frozen \
        --combo cfw --primitive pull --block 55
"""

from __future__ import annotations

import argparse
import json
import re
from collections import defaultdict
from pathlib import Path

import numpy as np

RUN_KEY = re.compile(r"_s-?\d+_.*$")  # the _s<seed>_<group> end of a run's key


def blocks(steps: list[dict], size: int) -> list[tuple[int, int]]:
    """(successes, interactions) per block of ``size`` executed interactions."""
    ok = [bool(s["success"]) for s in steps]
    return [(sum(ok[i:i + size]), len(ok[i:i + size])) for i in range(0, len(ok), size)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", help="w2e benchmark --out directories")
    ap.add_argument("--combo", default="cfw")
    ap.add_argument("--primitive", default="pull")
    ap.add_argument("--block", type=int, default=55, help="interactions per block")
    a = ap.parse_args()
    per: dict[str, list[list[tuple[int, int]]]] = defaultdict(list)
    for d in a.dirs:
        f = Path(d) / f"explored_{a.combo}_{a.primitive}.json"
        for key, run in json.loads(f.read_text()).items():
            # keys are <method>_s<seed>_<group>; a method name may hold "_s" itself
            method = f"{RUN_KEY.sub('', key)} ({Path(d).name})"
            per[method].append(blocks(run["steps"], a.block))
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


if __name__ == "__main__":
    main()
