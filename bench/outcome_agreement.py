"""How often does the cloud judge agree with the joint truth? Simulated trials judged both ways.

The trials are drawn exactly as ``w2e collect`` draws them (``observation_trials``: the
proposal distribution of ``w2e_ros/core/exploration/proposals.py`` on the object's camera cloud, the
collection's positive rate), on held-out instances (split ``test``: the cloud judge's
thresholds were chosen on training instances). Every valid trial is judged by the
simulator's joint states (``judge_motion``, the truth) and by the object's camera clouds
before and after it (``judge_clouds``, what a robot without joint sensors does), without and
with the simulator's movable-part mask of the before cloud. Invalid trials (contact at the
first step, a push touching another part) are invalid for both sources and not counted.

Writes ``outcome_agreement.json`` and ``outcome_agreement.md`` into ``--out`` and prints the
table and the wall time.

Usage: python bench/outcome_agreement.py [--observations 4] [--interactions 6]
       [--categories ...] [--split test] [--seed 0] [--out bench/results/outcome]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from dataclasses import asdict
from pathlib import Path

import numpy as np

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.experiments.collect import CollectConfig, observation_trials, plan_chunks
from w2e_ros.experiments.sim_world import SimWorld

ROOT = Path(__file__).resolve().parents[1]


class Confusion:
    """Cloud verdicts against the joint truth."""

    def __init__(self) -> None:
        self.tp = self.fp = self.fn = self.tn = 0

    def add(self, joints: bool, clouds: bool) -> None:
        if joints and clouds:
            self.tp += 1
        elif clouds:
            self.fp += 1
        elif joints:
            self.fn += 1
        else:
            self.tn += 1

    def to_dict(self) -> dict:
        n = self.tp + self.fp + self.fn + self.tn
        agree = (self.tp + self.tn) / max(n, 1)
        chance = (((self.tp + self.fp) * (self.tp + self.fn)
                   + (self.tn + self.fn) * (self.tn + self.fp)) / max(n, 1) ** 2)
        return {"n": n, "tp": self.tp, "fp": self.fp, "fn": self.fn, "tn": self.tn,
                "agreement": agree,
                "precision": self.tp / (self.tp + self.fp) if self.tp + self.fp else None,
                "recall": self.tp / (self.tp + self.fn) if self.tp + self.fn else None,
                "kappa": (agree - chance) / (1 - chance) if chance < 1 else 1.0,
                "positive_rate_joints": (self.tp + self.fn) / max(n, 1),
                "positive_rate_clouds": (self.tp + self.fp) / max(n, 1)}


def run(args: argparse.Namespace) -> dict:
    cfg = CollectConfig(out="", categories=args.categories, split=args.split,
                        observations=args.observations, interactions=args.interactions,
                        seed=args.seed)
    world = SimWorld(num_points=cfg.num_points)  # joints: the truth; the clouds judged below
    groups: dict[str, Confusion] = defaultdict(Confusion)
    disagreements, judge_ms = [], []
    trials = valid = 0
    for chunk in plan_chunks(cfg):
        for category, instance, obs_seed in chunk:
            target, _, done = observation_trials(world, cfg, category, instance, obs_seed)
            for t in done:
                trials += 1
                res = t.result
                if res is None or not res.valid:
                    continue
                valid += 1
                t0 = time.perf_counter()
                judged = world.judge_from_clouds(target, t.action, res)
                judge_ms.append(1e3 * (time.perf_counter() - t0))
                masked = world.judge_from_clouds(target, t.action, res, use_mask=True)
                prim = t.action.primitive
                for key in ("all", f"primitive:{prim}", f"category:{category}"):
                    groups[key].add(res.success, judged.success)
                groups["all+mask"].add(res.success, masked.success)
                if res.success != judged.success:
                    motion = res.motion[res.target_joint] if res.target_joint >= 0 else 0.0
                    disagreements.append({
                        "target": target.name, "primitive": prim,
                        "joints": {"success": bool(res.success), "reason": res.reason,
                                   "motion": round(float(motion), 4),
                                   "contact_displacement_m": round(float(np.linalg.norm(
                                       res.contact_displacement)), 4)},
                        "clouds": {"success": bool(judged.success), "reason": judged.reason,
                                   "motion_m": round(judged.motion, 4),
                                   "cosine": (None if np.isnan(judged.cosine)
                                              else round(judged.cosine, 3))}})
    return {"trials": trials, "valid": valid, "groups": {k: v.to_dict() for k, v in
                                                         sorted(groups.items())},
            "judge_ms_median": float(np.median(judge_ms)) if judge_ms else None,
            "disagreements": disagreements,
            "judge_config": asdict(world.judge),
            "collect": {k: v for k, v in asdict(cfg).items() if k not in ("out", "workers")}}


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.1f}"


def _row(name: str, g: dict) -> str:
    return (f"| {name} | {g['n']} | {g['tp']} | {g['fp']} | {g['fn']} | {g['tn']} | "
            f"{_pct(g['agreement'])} | {_pct(g['precision'])} | {_pct(g['recall'])} | "
            f"{g['kappa']:.2f} | {_pct(g['positive_rate_joints'])} |")


def markdown(doc: dict) -> str:
    g = doc["groups"]
    head = ("| valid trials | n | both success | clouds only | joints only | both failure | "
            "agreement % | precision % | recall % | kappa | joint positive % |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|")
    rows = [_row("all", g["all"])]
    rows += [_row(k.split(":", 1)[1], v) for k, v in g.items() if k.startswith("primitive:")]
    rows.append(_row("all, with the part mask", g["all+mask"]))
    cats = [_row(k.split(":", 1)[1], v) for k, v in g.items() if k.startswith("category:")]
    return "\n".join([head, *rows]) + "\n\nPer category:\n\n" + "\n".join([head, *cats]) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--categories", nargs="+", default=None, help="default: all 14")
    ap.add_argument("--split", default="test", choices=["train", "explore", "test"])
    ap.add_argument("--observations", type=int, default=4, help="per category")
    ap.add_argument("--interactions", type=int, default=6, help="per observation and primitive")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "outcome"))
    args = ap.parse_args(argv)
    for c in args.categories or []:
        load_categories().check_category(c)
    t0 = time.perf_counter()
    doc = run(args)
    doc["seconds"] = round(time.perf_counter() - t0, 1)
    doc["command"] = "python bench/outcome_agreement.py " + " ".join(argv or sys.argv[1:])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "outcome_agreement.json").write_text(json.dumps(doc, indent=1) + "\n")
    table = markdown(doc)
    (out / "outcome_agreement.md").write_text(
        f"`{doc['command'].strip()}`: {doc['trials']} trials, {doc['valid']} valid, "
        f"{doc['seconds']} s.\n\n{table}")
    print(table)
    print(f"{doc['trials']} trials ({doc['valid']} valid) judged both ways in {doc['seconds']} "
          f"s wall time; after-cloud render + judge: median {doc['judge_ms_median']:.1f} ms "
          "per trial")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
