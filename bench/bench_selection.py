"""Time one round's choice of every exploration rule over a realistic pool (issue 40: "a
round's choice over all candidates well under a second on 2 cores").

Synthetic pool: ``--objects`` objects x ``--candidates`` candidates each, 128-d features
drawn around a few hundred centres (the encoder's features cluster by part and geometry),
affordance skewed low as on pulls; the round's budget is half the objects (the loop's
default round), at most two picks per object, and ``--explored`` interactions already taken.
Prints the median wall time per rule over ``--repeats`` rounds.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_selection.py --objects 110 --candidates 300
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from w2e_ros.core.exploration.strategies import Scored, registry

FEATURE_DIM = 128
FEATURE_CENTRES = 300
PER_OBJECT = 2


def synthetic_round(objects: int, candidates: int, explored: int,
                    rng: np.random.Generator) -> tuple[list[Scored], list[np.ndarray],
                                                       np.ndarray]:
    """(scored objects, hindsight labels, explored features (E, F))."""
    centres = rng.normal(0, 1, (FEATURE_CENTRES, FEATURE_DIM)).astype(np.float32)

    def feats(n: int) -> np.ndarray:
        return centres[rng.integers(FEATURE_CENTRES, size=n)] + rng.normal(
            0, 0.3, (n, FEATURE_DIM)).astype(np.float32)

    scored = [Scored(affordance=rng.beta(0.5, 4.0, candidates).astype(np.float32),
                     similarity=rng.random(candidates).astype(np.float32),
                     familiarity=-rng.random(candidates).astype(np.float32),
                     features=feats(candidates)) for _ in range(objects)]
    labels = [(rng.random(candidates) < 0.1).astype(np.float32) for _ in range(objects)]
    return scored, labels, feats(explored)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--objects", type=int, default=110)
    ap.add_argument("--candidates", type=int, default=300, help="candidates per object")
    ap.add_argument("--explored", type=int, default=275, help="interactions already taken")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rules", nargs="*", default=None, help="default: every exploring rule")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    rng = np.random.default_rng(0)
    scored, labels, explored = synthetic_round(a.objects, a.candidates, a.explored, rng)
    k = max(1, a.objects // 2)
    print(f"{a.objects} objects x {a.candidates} candidates, {FEATURE_DIM}-d features, "
          f"k = {k}, {a.explored} explored, {a.threads} thread(s)")
    for name, st in registry(experimental=True).items():
        if not st.explores or (a.rules and name not in a.rules):
            continue
        times = []
        for r in range(a.repeats):
            t0 = time.perf_counter()
            st.select(scored, k, PER_OBJECT, np.random.default_rng(r),
                      labels if st.needs_labels else None, explored)
            times.append(time.perf_counter() - t0)
        print(f"{name:24s} {1000 * float(np.median(times)):8.1f} ms")


if __name__ == "__main__":
    main()
