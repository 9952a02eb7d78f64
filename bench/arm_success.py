"""The same actions on the flying gripper and on the simulated Panda: does the arm change
what succeeds?

For TEST instances of a few categories (the simulator's objects centred at the origin, fronts
towards +x), the shipped model ranks its manipulate candidates (all points x ``--directions``
frames, best affordance first, as bench/arm_reach.py does); the first ``--actions``
candidates among the top ``--top`` that a Panda based 0.95 m in front of the object, 0.3 m
below its centre (``sim_bridge.panda.DEFAULT_BASE``) can reach are executed twice from the
same start state: by the flying gripper (``ObjectWorld.run_trial``, the paper's benchmark) and
by the simulated Panda (``sim_bridge.panda.run_arm_trial``: planned by IK, followed by the
force-limited joint drives). Both are judged by the same success rule. Reported per
primitive and category: valid and success rates of each, the paired difference with a 95 %
bootstrap interval over objects, the agreement, and the arm's tracking.

    .venv/bin/python bench/arm_success.py --categories cabinet refrigerator microwave \\
        --per-category 10 --out bench/results/arm_sim
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from arm_reach import ranked  # a sibling script: the same candidate ranking

from sim_bridge.panda import base_in_front, run_arm_trial
from w2e_ros.core.dataset.targets import stable_seed
from w2e_ros.core.exploration.evaluate import evaluation_targets
from w2e_ros.core.model.network import load_model
from w2e_ros.core.robot import kinematics as kin
from w2e_ros.core.robot.primitives import Action
from w2e_ros.experiments.sim_world import SimWorld
from w2e_ros.paths import default_checkpoint


def bootstrap(diff: np.ndarray, seed: int = 0, n: int = 2000) -> tuple[float, float]:
    """95 % interval of the mean of per-object values."""
    if len(diff) == 0:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    means = diff[rng.integers(0, len(diff), size=(n, len(diff)))].mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def summarise(rows: list[dict]) -> dict:
    """Rates over actions; the paired difference's interval over objects."""
    if not rows:
        return {"actions": 0}
    f = np.array([r["flying_success"] for r in rows], float)
    p = np.array([r["panda_success"] for r in rows], float)
    by_obj: dict[str, list[float]] = {}
    for r in rows:
        by_obj.setdefault(r["target"], []).append(r["panda_success"] - r["flying_success"])
    diff = np.array([np.mean(v) for v in by_obj.values()])
    lo, hi = bootstrap(diff)
    return {
        "objects": len(by_obj), "actions": len(rows),
        "flying_valid": float(np.mean([r["flying_valid"] for r in rows])),
        "panda_valid": float(np.mean([r["panda_valid"] for r in rows])),
        "flying_success": float(f.mean()), "panda_success": float(p.mean()),
        "difference": float(diff.mean()), "difference_ci95": [lo, hi],
        "agreement": float(np.mean(f == p)),
        "flying_only": int(np.sum((f == 1) & (p == 0))),
        "panda_only": int(np.sum((f == 0) & (p == 1))),
        "wrist_error_mm_median": float(1000 * np.median([r["wrist_error"] for r in rows
                                                          if r["panda_planned"]] or [np.nan])),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--categories", nargs="+", default=["cabinet", "refrigerator", "microwave"])
    ap.add_argument("--per-category", type=int, default=10)
    ap.add_argument("--primitives", nargs="+", default=["push", "pull"])
    ap.add_argument("--directions", type=int, default=16)
    ap.add_argument("--top", type=int, default=64, help="candidates checked for reach")
    ap.add_argument("--actions", type=int, default=4, help="reachable actions per object")
    ap.add_argument("--out", type=Path, default=Path("bench/results/arm_sim"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    sim = SimWorld()
    rows: list[dict] = []
    t_fly, t_arm = [], []
    for prim in args.primitives:
        model, _ = load_model(default_checkpoint(prim))
        model.eval()
        for target in evaluation_targets(args.categories, args.per_category):
            world = sim.world(target.category, target.instance)
            q = sim.start_state(target)
            base = base_in_front(world.center())
            cloud = sim.observe(target)
            pts, up, fwd = ranked(model, cloud, args.directions,
                                  stable_seed("arm_success", prim, target.name))
            ok = kin.reachable(pts[:args.top], up[:args.top], fwd[:args.top], prim,
                               base_pose=base)
            chosen = np.flatnonzero(ok)[:args.actions]
            for rank in chosen:
                action = Action(pts[rank], up[rank], fwd[rank], prim)
                t0 = time.perf_counter()
                fly = world.run_trial(q, action)
                t1 = time.perf_counter()
                arm = run_arm_trial(world, q, action, base)
                t2 = time.perf_counter()
                t_fly.append(t1 - t0)
                t_arm.append(t2 - t1)
                rows.append({
                    "primitive": prim, "target": target.name, "category": target.category,
                    "rank": int(rank), "flying_valid": bool(fly.valid),
                    "flying_success": bool(fly.success), "flying_reason": fly.reason,
                    "panda_planned": bool(arm.planned), "panda_valid": bool(arm.result.valid),
                    "panda_success": bool(arm.result.success), "panda_reason": arm.result.reason,
                    "flying_motion": float(fly.motion[fly.target_joint])
                    if fly.target_joint >= 0 else 0.0,
                    "panda_motion": float(arm.result.motion[arm.result.target_joint])
                    if arm.result.target_joint >= 0 else 0.0,
                    "wrist_error": float(arm.wrist_error),
                    "tracking_error": float(arm.tracking_error), "arm_seconds": arm.duration})
            print(f"{prim} {target.name}: {ok.mean():.2f} of the top {args.top} reachable; "
                  f"{len(chosen)} executed: flying "
                  f"{sum(r['flying_success'] for r in rows[-len(chosen):]) if len(chosen) else 0}"
                  f", panda "
                  f"{sum(r['panda_success'] for r in rows[-len(chosen):]) if len(chosen) else 0}"
                  " successes", flush=True)
    summary = {}
    for prim in args.primitives:
        r = [x for x in rows if x["primitive"] == prim]
        summary[prim] = {"all": summarise(r),
                         "by_category": {c: summarise([x for x in r if x["category"] == c])
                                         for c in args.categories}}
    res = {"config": {**vars(args), "out": str(args.out), "base_offset": "0.95 m in front, "
                      "0.3 m below the object centre, facing it"},
           "summary": summary,
           "timing": {"flying_s_per_trial_median": float(np.median(t_fly)),
                      "panda_s_per_trial_median": float(np.median(t_arm))},
           "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(res, indent=1))
    (args.out / "results.md").write_text(table(res))
    print(table(res))


def table(res: dict) -> str:
    """The markdown table of the summary."""
    lines = ["| primitive | category | objects | actions | flying valid | Panda valid | "
             "flying success | Panda success | Panda - flying [95 % CI] | agreement | "
             "wrist error (median) |", "|---" * 11 + "|"]
    for prim, s in res["summary"].items():
        for cat, v in [("all", s["all"]), *s["by_category"].items()]:
            if not v.get("actions"):
                continue
            lo, hi = v["difference_ci95"]
            lines.append(
                f"| {prim} | {cat} | {v['objects']} | {v['actions']} | "
                f"{100 * v['flying_valid']:.1f} % | {100 * v['panda_valid']:.1f} % | "
                f"{100 * v['flying_success']:.1f} % | {100 * v['panda_success']:.1f} % | "
                f"{100 * v['difference']:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}] | "
                f"{100 * v['agreement']:.1f} % | {v['wrist_error_mm_median']:.1f} mm |")
    t = res["timing"]
    lines.append("")
    lines.append(f"Per trial (median, 2-core CPU): flying {t['flying_s_per_trial_median']:.2f} s, "
                 f"Panda {t['panda_s_per_trial_median']:.2f} s. Actions: the first "
                 f"{res['config']['actions']} reachable of the shipped model's top "
                 f"{res['config']['top']} candidates per object, the same start state for both.")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
