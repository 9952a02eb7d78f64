"""Per-category success table of random push/pull actions on movable parts.

``python -m sim_bridge.check [--trials 40] [--categories cabinet,door]`` prints, for each
category and primitive, the fraction of valid trials and of successes. It is the quick
sanity check that every family can be moved at all.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sim_bridge.objects import CATEGORIES, make_object, stable_seed
from sim_bridge.sampling import random_action
from sim_bridge.world import ObjectWorld


def category_stats(
    category: str, primitive: str, trials: int, per_view: int = 5, instances=range(30)
) -> dict:
    """Run ``trials`` random actions (``per_view`` per observation) and count outcomes."""
    rng = np.random.default_rng(stable_seed("check", category, primitive))
    valid = success = 0
    reasons: dict[str, int] = {}
    done = 0
    while done < trials:
        inst = int(rng.choice(list(instances)))
        world = ObjectWorld(make_object(category, inst))
        q = world.sample_start_state(rng)
        obs = world.observe(q, rng)
        if not obs.movable.any():
            continue
        for _ in range(min(per_view, trials - done)):
            action, _ = random_action(obs, rng, primitive)
            r = world.run_trial(q, action)
            valid += r.valid
            success += r.success
            reasons[r.reason or "success"] = reasons.get(r.reason or "success", 0) + 1
            done += 1
    return {"valid": valid / trials, "success": success / trials, "reasons": reasons}


def main(argv: list[str] | None = None) -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--categories", default=",".join(CATEGORIES))
    ap.add_argument("--verbose", action="store_true", help="also print failure reasons")
    args = ap.parse_args(argv)
    t0 = time.time()
    print(
        f"{'category':<16} {'push valid':>10} {'push succ':>10} {'pull valid':>10} "
        f"{'pull succ':>10}"
    )
    for cat in args.categories.split(","):
        row = [category_stats(cat, p, args.trials) for p in ("push", "pull")]
        print(
            f"{cat:<16} {row[0]['valid']:>10.2f} {row[0]['success']:>10.2f} "
            f"{row[1]['valid']:>10.2f} {row[1]['success']:>10.2f}",
            flush=True,
        )
        if args.verbose:
            for p, r in zip(("push", "pull"), row, strict=True):
                print(f"    {p}: {r['reasons']}")
    print(f"({args.trials} trials per cell, {time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
