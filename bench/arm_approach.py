"""The whole arm in the approach check (issue 28): what does checking the Panda's links along
the planned trajectory and the table plane refuse, and does it cut the invalid trials?

On TEST-split objects of every category (unseen by the shipped models), for push and pull,
the shipped checkpoints rank the manipulate candidates as the planner gets them (every cloud
point x ``--directions`` frames, drawn as the inference node draws its maps, by predicted
affordance: bench/approach_check.py's ranking). The object stands on a table (its lowest point
in its start state) and a Panda stands on the same table as in the stack
(``kinematics.DEFAULT_BASE_POSE``): 0.95 m in front of the object's centre
(``sim_bridge.panda.base_in_front``), facing it, so the check's ``table_height`` is its default
0. Of the ``--candidates`` best:

* the hand-only check (``check_arm`` false, what ``arm: panda`` did before): the hand's
  approach (:func:`w2e_ros.core.robot.feasibility.approach_hits`) and the reach (IK);
* the whole-arm check (``check_arm`` true): besides, the links along the joint path the planner
  sends and the table plane (:func:`w2e_ros.core.robot.feasibility.arm_collisions`), with the part
  and the waypoint of the first collision.

Executed in the simulator with the Panda (``sim_bridge.panda.run_arm_trial``: the plan the
arm adapter would send, on force-limited joint drives, with ``--free-move`` (default) from the
ready pose; invalid = a touch on the free move to the start pose, contact at the start pose or
a push touching another part): the first ``--actions`` candidates each check accepts (their
union, each once), so the invalid rate of what each accepts, of the policy's choice (the first
accepted) and of what only the hand-only check accepts are measured on the same trials. The
simulated scene has no table, so refusals for the table cannot show up as invalid trials.

    .venv/bin/python bench/arm_approach.py --per-category 4 --out bench/results/arm_approach
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch
from approach_check import heads, map_candidates  # a sibling script: the same ranking

from sim_bridge.panda import ArmSettings, base_in_front, run_arm_trial
from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.targets import stable_seed
from w2e_ros.core.exploration.evaluate import evaluation_targets
from w2e_ros.core.model.metrics import bootstrap_ci
from w2e_ros.core.model.network import load_model
from w2e_ros.core.model.policy import best_first
from w2e_ros.core.robot.feasibility import (
    DEFAULT_CHECK,
    Arm,
    ArmCheck,
    approach_hits,
    arm_collisions,
)
from w2e_ros.core.robot.primitives import Action
from w2e_ros.experiments.sim_world import SimWorld
from w2e_ros.paths import default_checkpoint


def phase(refusal) -> str:
    """Where on the trajectory a collision happened, in words."""
    if refusal.at_start:
        return "at the start pose"
    if refusal.waypoint <= 0:
        return "free move to the start pose"
    return "approach" if refusal.waypoint == 1 else "after contact"


def measure(sim: SimWorld, model, target, primitive: str, args) -> dict:
    """One object and primitive: the checks on the best candidates and the executed trials."""
    world = sim.world(target.category, target.instance)
    q = sim.start_state(target)
    cloud = sim.observe(target)
    bottom = float(min(m.vertices[:, 2].min() for m in world.posed_meshes(q)))
    base = base_in_front(world.center())
    base[2] = bottom  # on the table, as the stack's base (kinematics.DEFAULT_BASE_POSE)
    arm = Arm("panda", tuple(float(v) for v in base))
    check = ArmCheck()  # the table plane at the base's height
    feats = model.encode(torch.from_numpy(cloud.points[None]))[0]
    rng = np.random.default_rng(stable_seed("arm_approach", primitive, target.name))
    pidx, up, fwd = map_candidates(cloud, args.directions, rng)
    aff, _ = heads(model, feats, pidx, up, fwd)
    order = best_first(aff)[:args.candidates]
    pts = cloud.points[pidx[order]].astype(np.float64)
    up, fwd = up[order].astype(np.float64), fwd[order].astype(np.float64)
    clear = approach_hits(cloud.points, pts, up, fwd, primitive) <= DEFAULT_CHECK.max_points
    t0 = time.perf_counter()
    why = dict(zip(np.flatnonzero(clear).tolist(),
                   arm_collisions(cloud.points, pts[clear], up[clear], fwd[clear], primitive,
                                  arm, check), strict=True))
    check_s = time.perf_counter() - t0
    reach = {c: w is None or w.test != "reach" for c, w in why.items()}
    hand_ok = [c for c in why if reach[c]]  # hand-only check: approach clear and reachable
    arm_ok = [c for c in why if why[c] is None]  # whole-arm check
    refused = [{"rank": c, "test": w.test, "part": w.part, "waypoint": w.waypoint,
                "phase": phase(w), "reason": w.reason}
               for c, w in why.items() if w is not None and w.test != "reach"]
    run = sorted(set(hand_ok[:args.actions]) | set(arm_ok[:args.actions]))
    settings = ArmSettings(free_move=args.free_move)
    trials = []
    for c in run:
        t = run_arm_trial(world, q, Action(pts[c], up[c], fwd[c], primitive), base, settings)
        w = why[c]
        trials.append({"rank": c, "hand_ok": True, "arm_ok": w is None,
                       "refused_test": w.test if w else "", "refused_part": w.part if w else "",
                       "refused_phase": phase(w) if w else "",
                       "hand_first": c in hand_ok[:args.actions],
                       "arm_first": c in arm_ok[:args.actions],
                       "planned": bool(t.planned), "valid": bool(t.result.valid),
                       "success": bool(t.result.success), "reason": t.result.reason})
    return {"target": target.name, "category": target.category, "primitive": primitive,
            "candidates": len(order), "hand_blocked": int((~clear).sum()),
            "unreachable": sum(not r for r in reach.values()),
            "hand_accepted": len(hand_ok), "arm_accepted": len(arm_ok),
            "arm_refused": refused, "hand_choice": hand_ok[0] if hand_ok else -1,
            "arm_choice": arm_ok[0] if arm_ok else -1, "check_s": check_s,
            "table_height": check.table_height, "trials": trials}


def rate(rows: list[dict], pick, field: str = "valid") -> tuple[float, float, float, int]:
    """Share of the picked trials that are NOT ``field`` (invalid by default), its 95 %
    bootstrap interval over objects, and the number of trials."""
    t = [(r["target"] + r["primitive"], not x[field]) for r in rows for x in r["trials"]
         if pick(r, x)]
    if not t:
        return float("nan"), float("nan"), float("nan"), 0
    groups, bad = np.array([g for g, _ in t]), np.array([b for _, b in t], float)
    v, lo, hi = bootstrap_ci(lambda i: float(bad[i].mean()), groups)
    return v, lo, hi, len(t)


def summarise(rows: list[dict]) -> dict:
    n = sum(r["candidates"] for r in rows)
    hand_refused = sum(r["hand_blocked"] + r["unreachable"] for r in rows)
    arm_extra = sum(len(r["arm_refused"]) for r in rows)
    refused = [x for r in rows for x in r["arm_refused"]]
    choice = {  # the policy's choice: the first candidate each check accepts
        "hand": rate(rows, lambda r, x: x["rank"] == r["hand_choice"]),
        "arm": rate(rows, lambda r, x: x["rank"] == r["arm_choice"])}
    return {
        "objects": len({r["target"] for r in rows}), "object_primitives": len(rows),
        "candidates": n,
        "hand_only_refused": hand_refused / max(n, 1),
        "hand_blocked": sum(r["hand_blocked"] for r in rows) / max(n, 1),
        "unreachable": sum(r["unreachable"] for r in rows) / max(n, 1),
        "whole_arm_refused": (hand_refused + arm_extra) / max(n, 1),
        "arm_extra_refused": arm_extra / max(n, 1),
        "arm_extra_of_hand_accepted": arm_extra / max(sum(r["hand_accepted"] for r in rows), 1),
        "none_accepted_hand": sum(r["hand_choice"] < 0 for r in rows),
        "none_accepted_arm": sum(r["arm_choice"] < 0 for r in rows),
        "choice_changed": sum(r["hand_choice"] != r["arm_choice"] for r in rows),
        "by_test": dict(Counter(x["test"] for x in refused)),
        "by_part": dict(Counter(x["part"] for x in refused).most_common()),
        "by_phase": dict(Counter(x["phase"] for x in refused)),
        "invalid_hand_accepted": rate(rows, lambda r, x: x["hand_first"]),
        "invalid_arm_accepted": rate(rows, lambda r, x: x["arm_first"]),
        "invalid_only_hand_accepted": rate(rows, lambda r, x: not x["arm_ok"]),
        "invalid_refused_cloud": rate(rows, lambda r, x: x["refused_test"] == "arm"),
        "invalid_refused_table": rate(rows, lambda r, x: x["refused_test"] == "table"),
        "invalid_choice_hand": choice["hand"], "invalid_choice_arm": choice["arm"],
        "failed_choice_hand": rate(rows, lambda r, x: x["rank"] == r["hand_choice"], "success"),
        "failed_choice_arm": rate(rows, lambda r, x: x["rank"] == r["arm_choice"], "success"),
        "check_s_per_object_median": float(np.median([r["check_s"] for r in rows])),
    }


def pct(v: float) -> str:
    return "-" if v != v else f"{100 * v:.1f} %"


def ci(t) -> str:
    v, lo, hi, n = t
    return "- (0 trials)" if n == 0 else f"{pct(v)} [{100 * lo:.1f}, {100 * hi:.1f}] (n={n})"


def table(res: dict) -> str:
    """The markdown of the summary."""
    cfg = res["config"]
    lines = [
        "# The whole arm in the approach check (issue 28)", "",
        f"Command: `{res['command']}` ({res['elapsed_s'] / 60:.1f} min on a 2-core CPU)", "",
        f"TEST objects: {cfg['per_category']} per category x {len(cfg['categories'])} "
        f"categories; the {cfg['candidates']} best of {cfg['directions']} frames x 2048 "
        "points per object and primitive; the Panda 0.95 m in front of the object, both on the "
        "table (the object's lowest point); executed with the simulated Panda (run_arm_trial).", "",
        "| primitive | objects | candidates | refused: hand-only check | refused: whole-arm "
        "check | whole-arm refusals on top (of the hand-accepted) | no candidate accepted "
        "(hand / whole) | choice changed |", "|---" * 8 + "|"]
    for prim, s in res["summary"].items():
        lines.append(
            f"| {prim} | {s['objects']} | {s['candidates']} | {pct(s['hand_only_refused'])} "
            f"(approach {pct(s['hand_blocked'])}, reach {pct(s['unreachable'])}) | "
            f"{pct(s['whole_arm_refused'])} | {pct(s['arm_extra_refused'])} "
            f"({pct(s['arm_extra_of_hand_accepted'])}) | {s['none_accepted_hand']} / "
            f"{s['none_accepted_arm']} | {s['choice_changed']} |")
    lines += ["", "Invalid trials with the simulated Panda (" + (
              "a touch on the free move from the ready pose, " if cfg["free_move"] else "")
              + "contact at the start pose, a push touching another part), 95 % bootstrap "
              "interval over objects:", "",
              "| primitive | the choice, hand-only | the choice, whole-arm | first "
              f"{cfg['actions']} accepted, hand-only | first {cfg['actions']} accepted, "
              "whole-arm | accepted by the hand-only check, refused by the whole-arm one | "
              "of those: a link or the hand in the cloud | of those: the table | choice "
              "failed (hand-only / whole-arm) |",
              "|---" * 9 + "|"]
    for prim, s in res["summary"].items():
        lines.append(
            f"| {prim} | {ci(s['invalid_choice_hand'])} | {ci(s['invalid_choice_arm'])} | "
            f"{ci(s['invalid_hand_accepted'])} | {ci(s['invalid_arm_accepted'])} | "
            f"{ci(s['invalid_only_hand_accepted'])} | "
            f"{ci(s['invalid_refused_cloud'])} | "
            f"{ci(s['invalid_refused_table'])} | {pct(s['failed_choice_hand'][0])} / "
            f"{pct(s['failed_choice_arm'][0])} |")
    lines += ["", "Whole-arm refusals (of candidates the hand-only check accepts) by part, test "
              "and where on the trajectory:", ""]
    for prim, s in res["summary"].items():
        lines.append(f"- {prim}: tests {s['by_test']}; parts {s['by_part']}; "
                     f"{s['by_phase']}; the check's time per object (median) "
                     f"{s['check_s_per_object_median']:.2f} s")
    lines += ["", "The simulated scene has no table: refusals for the table cannot show up as "
              "invalid trials here" + ("" if cfg["free_move"] else "; nor can those on the "
                                       "free move, which was not simulated (--no-free-move)")
              + "; a link that touches the object during a pull after the start pose does not "
              "make it invalid (it may make it fail)."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--categories", nargs="+", default=None, help="default: all")
    ap.add_argument("--per-category", type=int, default=4)
    ap.add_argument("--primitives", nargs="+", default=["push", "pull"])
    ap.add_argument("--directions", type=int, default=16)
    ap.add_argument("--candidates", type=int, default=64, help="best candidates checked")
    ap.add_argument("--actions", type=int, default=3, help="executed per check and object")
    ap.add_argument("--free-move", action=argparse.BooleanOptionalAction, default=True,
                    help="simulate the free move from the ready pose to the start pose (a "
                    "touch on it: invalid)")
    ap.add_argument("--out", type=Path, default=Path("bench/results/arm_approach"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    args.categories = args.categories or list(load_categories().categories)
    sim = SimWorld()
    targets = evaluation_targets(args.categories, args.per_category)
    total, done, t_start = len(targets) * len(args.primitives), 0, time.perf_counter()
    rows: list[dict] = []
    for prim in args.primitives:
        model, _ = load_model(default_checkpoint(prim))
        model.eval()
        for target in targets:
            r = measure(sim, model, target, prim, args)
            rows.append(r)
            done += 1
            el = time.perf_counter() - t_start
            n = sum(x["candidates"] for x in rows)
            extra = sum(len(x["arm_refused"]) for x in rows)
            bad = [(x["rank"] == y["hand_choice"], x["rank"] == y["arm_choice"], not x["valid"])
                   for y in rows for x in y["trials"]]
            ih = np.mean([b for h, _, b in bad if h]) if any(h for h, _, _ in bad) else np.nan
            ia = np.mean([b for _, a, b in bad if a]) if any(a for _, a, _ in bad) else np.nan
            print(f"[{done}/{total}] {prim} {target.name}: hand-only refuses "
                  f"{r['hand_blocked'] + r['unreachable']}/{r['candidates']}, whole-arm "
                  f"{len(r['arm_refused'])} more; {len(r['trials'])} trials | so far: whole-arm "
                  f"adds {100 * extra / max(n, 1):.1f} % refusals, invalid choice hand-only "
                  f"{100 * ih:.0f} % vs whole-arm {100 * ia:.0f} % | {el / 60:.1f} min, ETA "
                  f"{el / done * (total - done) / 60:.1f} min", flush=True)
    summary = {p: summarise([r for r in rows if r["primitive"] == p]) for p in args.primitives}
    res = {"command": "python bench/arm_approach.py " + " ".join(
               (f"--{'' if v else 'no-'}{k.replace('_', '-')}" if isinstance(v, bool) else
                f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}")
               for k, v in vars(args).items() if k != "categories")
           + ("" if args.categories == list(load_categories().categories)
              else " --categories " + " ".join(args.categories)),
           "config": {**vars(args), "out": str(args.out)}, "summary": summary,
           "elapsed_s": time.perf_counter() - t_start, "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(res, indent=1, default=str))
    md = table(res)
    (args.out / "results.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
