"""How much of what the model proposes can a Panda reach, and what does the IK cost?

For TEST instances of every category (the simulator's objects, centred at the origin, fronts
towards +x), the shipped model's manipulate candidates (all points x ``--directions`` frames,
best affordance first, as the inference node's maps draw them) are checked for reach by a
Panda based at ``--base-pose`` (default: 0.95 m in front of the object, 0.3 m below its
centre, facing it) with :func:`w2e_ros.core.robot.kinematics.reachable`; the best reachable one is
what ``manipulate`` with ``arm: panda`` executes. Timing: :func:`plan_trajectory` of the top
reachable candidate per object (per IK'd pose along the path) and the batched check per
candidate.

    .venv/bin/python bench/arm_reach.py --per-category 3 --out bench/results/arm_reach
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.targets import stable_seed
from w2e_ros.core.exploration.evaluate import evaluation_targets
from w2e_ros.core.model.network import load_model
from w2e_ros.core.robot import kinematics as kin
from w2e_ros.core.robot.actions import encode_rotation, sample_forward, sample_up
from w2e_ros.core.robot.feasibility import Arm, first_feasible
from w2e_ros.experiments.sim_world import SimWorld
from w2e_ros.paths import default_checkpoint

BASE = (0.95, 0.0, -0.3, 0.0, 0.0, 1.0, 0.0)  # x y z qx qy qz qw: facing -x, at the object


@torch.no_grad()
def ranked(model, cloud, directions: int, seed: int):
    """Candidates (points, up, forward) of the whole map, best affordance first."""
    rng = np.random.default_rng(seed)
    pidx = np.repeat(np.arange(len(cloud.points)), directions)
    up = sample_up(cloud.normals[pidx], rng)
    fwd = sample_forward(up, rng)
    feats = model.encode(torch.from_numpy(cloud.points[None]))[0]
    logit, _ = model.heads(feats[torch.from_numpy(pidx.astype(np.int64))],
                           torch.from_numpy(encode_rotation(up, fwd)))
    order = np.argsort(-torch.sigmoid(logit).numpy(), kind="stable")
    return cloud.points[pidx[order]].astype(np.float64), up[order], fwd[order]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--per-category", type=int, default=3)
    ap.add_argument("--directions", type=int, default=16)
    ap.add_argument("--top", type=int, default=64, help="candidates whose reach is measured")
    ap.add_argument("--candidates", type=int, default=256, help="manipulate's approach_candidates")
    ap.add_argument("--base-pose", type=float, nargs=7, default=list(BASE))
    ap.add_argument("--out", type=Path, default=Path("bench/results/arm_reach"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    cats = list(load_categories().categories)
    world = SimWorld()
    arm = Arm("panda", tuple(args.base_pose))
    rows, plan_ms, check_ms = [], [], []
    for prim in ("push", "pull"):
        model, _ = load_model(default_checkpoint(prim))
        model.eval()
        for target in evaluation_targets(cats, args.per_category):
            cloud = world.observe(target)
            pts, up, fwd = ranked(model, cloud, args.directions,
                                  stable_seed("arm_reach", prim, target.name))
            t0 = time.perf_counter()
            ok = kin.reachable(pts[:args.top], up[:args.top], fwd[:args.top], prim,
                               base_pose=arm.base_pose)
            check_ms.append(1e3 * (time.perf_counter() - t0) / args.top)
            k, _ = first_feasible(None, pts[:args.candidates], up[:args.candidates],
                                  fwd[:args.candidates], prim, arm, check=None)
            if k >= 0:
                W, acts = kin.primitive_waypoints(pts[k], up[k], fwd[k], prim)
                t0 = time.perf_counter()
                plan = kin.plan_trajectory(W[0], arm.base_pose, dwell_at=acts)
                if plan:
                    plan_ms.append(1e3 * (time.perf_counter() - t0) / (len(plan.times) - 1))
            rows.append({"primitive": prim, "target": target.name, "category": target.category,
                         "top_reachable_share": float(ok.mean()), "top1_reachable": bool(ok[0]),
                         "first_reachable_rank": int(k)})
            print(f"{prim} {target.name}: {ok.mean():.2f} of the top {args.top} reachable, "
                  f"best reachable rank {k}", flush=True)
    summary = {}
    for prim in ("push", "pull"):
        r = [x for x in rows if x["primitive"] == prim]
        summary[prim] = {
            "objects": len(r),
            "top_reachable_share": float(np.mean([x["top_reachable_share"] for x in r])),
            "top1_reachable": float(np.mean([x["top1_reachable"] for x in r])),
            "none_reachable_in_candidates": int(sum(x["first_reachable_rank"] < 0 for x in r)),
            "median_first_reachable_rank": float(np.median(
                [x["first_reachable_rank"] for x in r if x["first_reachable_rank"] >= 0]
                or [-1])),
            "by_category": {c: float(np.mean([x["top_reachable_share"] for x in r
                                              if x["category"] == c])) for c in cats}}
    res = {"config": {**vars(args), "out": str(args.out)}, "summary": summary,
           "timing": {"plan_ms_per_pose_median": float(np.median(plan_ms)),
                      "plan_ms_per_pose_max": float(np.max(plan_ms)),
                      "check_ms_per_candidate_median": float(np.median(check_ms))},
           "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(res, indent=1))
    print(json.dumps({k: v for k, v in res.items() if k != "rows"}, indent=1))


if __name__ == "__main__":
    main()
