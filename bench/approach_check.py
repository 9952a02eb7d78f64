"""Does checking the approach against the observed cloud cut the invalid trials? (issue 9)

On TEST-split objects of every category (unseen by the shipped models), for push and pull,
with the shipped checkpoints ``checkpoints/w2e_cfw_{push,pull}.pt``, the action each stack
verb would execute is taken with and without the approach check
(:mod:`w2e_ros.core.robot.feasibility`) and both are executed in the simulator:

* manipulate: the planner's choice. Every cloud point x ``--directions`` gripper frames drawn
  as the inference node draws its maps (no mask: a real robot has none), ranked by predicted
  affordance; before = the best, after = the best of the ``--candidates`` highest whose
  approach is clear (the planner's ``approach_candidates``), none clear = refused, nothing
  executed.
* explore: the first action of the similarity strategy on the exploration loop's candidates
  (``points x dirs`` from the proposal distribution, no mask, as the planner explores);
  before = the lowest similarity, after = the lowest similarity among the clear ones (the
  loop with ``check_approach`` drops the others before scoring).

A trial is invalid as the simulator judges it (``TrialResult.valid`` false: the hand touches
the object at the first step, or a push touches a part other than the target). Rates come
with 95 % bootstrap intervals over objects (paired: the same resample for before, after and
their difference). The check's time per object is measured on the candidates it checks.

The thresholds of the check (``ApproachCheck``) were chosen on a calibration set of
EXPLORE-split objects (not the test ones): there the top-affordance and some random map
candidates are executed and a small grid of settings is scored by how many invalid trials
it rejects and how many successes it throws away; that table is rerun and reported too
(``--calibrate-per-category 0`` skips it).

Usage: .venv/bin/python bench/approach_check.py [--per-category 5] [--out DIR]
Writes DIR/results.json and DIR/results.md (default bench/results/approach_check) and the
table of docs/ros_api.md ("The approach check"; ``--readme`` alone re-renders it from the
JSON, ``--readme --check`` tests it).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.targets import Target, stable_seed
from w2e_ros.core.exploration.evaluate import evaluation_targets
from w2e_ros.core.exploration.explore import map_candidates as explore_map_candidates
from w2e_ros.core.exploration.explore import sample_candidates
from w2e_ros.core.model.metrics import bootstrap_ci
from w2e_ros.core.model.network import load_model
from w2e_ros.core.model.policy import ManipulatePolicy, best_first, score_actions
from w2e_ros.core.robot.feasibility import (
    DEFAULT_CHECK,
    ApproachCheck,
    approach_clear,
    approach_hits,
)
from w2e_ros.core.robot.primitives import Action
from w2e_ros.experiments.sim_world import SimWorld
from w2e_ros.paths import default_checkpoint


def map_candidates(cloud, directions: int, rng: np.random.Generator):
    """All points x ``directions`` frames, drawn as the inference node's maps draw them."""
    c = explore_map_candidates(cloud, directions, rng)
    return c.point_index, c.up, c.forward


def heads(model, feats: torch.Tensor, pidx, up, fwd) -> tuple[np.ndarray, np.ndarray]:
    """(C,) affordance probability and similarity of actions on one encoded cloud."""
    logit, sim = score_actions(model, feats, pidx, up, fwd)
    return torch.sigmoid(logit).numpy(), sim.numpy()


def execute(world: SimWorld, target, cloud, pidx, up, fwd, i: int, primitive: str) -> dict:
    res = world.execute(target, Action(cloud.points[pidx[i]].astype(np.float64),
                                       up[i].astype(np.float64), fwd[i].astype(np.float64),
                                       primitive))
    return {"valid": bool(res.valid), "success": bool(res.success), "reason": res.reason}


REFUSED = {"valid": True, "success": False, "reason": "refused: no clear approach",
           "refused": True}


def measure(world: SimWorld, model, target, cloud, primitive: str, args) -> dict:
    """Before / after of both verbs on one object, and the check's time."""
    feats = model.encode(torch.from_numpy(cloud.points[None]))[0]
    row: dict = {"target": target.name, "category": target.category}
    # manipulate: best affordance of the map, then the first clear among the best K
    rng = np.random.default_rng(stable_seed("approach_check", "manipulate", target.name))
    pidx, up, fwd = map_candidates(cloud, args.directions, rng)
    aff, _ = heads(model, feats, pidx, up, fwd)
    order = best_first(aff)[:args.candidates]
    t0 = time.perf_counter()
    ok = approach_clear(cloud.points, cloud.points[pidx[order]], up[order], fwd[order],
                        primitive)
    row["manipulate_check_ms"] = 1e3 * (time.perf_counter() - t0)
    row["manipulate_clear_share"] = float(ok.mean())
    row["manipulate_before"] = execute(world, target, cloud, pidx, up, fwd, int(order[0]),
                                       primitive)
    # the planner's choice: the manipulate policy over the same ranking
    pick = ManipulatePolicy(candidates=args.candidates).pick(aff, cloud.points, pidx, up, fwd,
                                                             primitive)
    row["manipulate_after"] = (execute(world, target, cloud, pidx, up, fwd, pick, primitive)
                               if pick >= 0 else dict(REFUSED))
    row["manipulate_changed"] = not bool(ok[0])
    # explore: lowest similarity among the loop's candidates, then among the clear ones
    rng = np.random.default_rng(stable_seed("approach_check", "explore", target.name))
    cand = sample_candidates(cloud, args.explore_points, args.explore_dirs, rng)
    _, sim = heads(model, feats, cand.point_index, cand.up, cand.forward)
    t0 = time.perf_counter()
    ok = approach_clear(cloud.points, cloud.points[cand.point_index], cand.up, cand.forward,
                        primitive)
    row["explore_check_ms"] = 1e3 * (time.perf_counter() - t0)
    row["explore_clear_share"] = float(ok.mean())
    first = int(np.argmin(sim))
    row["explore_before"] = execute(world, target, cloud, cand.point_index, cand.up,
                                    cand.forward, first, primitive)
    if ok.any():
        pick = int(np.flatnonzero(ok)[np.argmin(sim[ok])])
        row["explore_after"] = execute(world, target, cloud, cand.point_index, cand.up,
                                       cand.forward, pick, primitive)
    else:
        row["explore_after"] = dict(REFUSED)
    row["explore_changed"] = not bool(ok[first])
    return row


def rates(rows: list[dict], verb: str, n_boot: int) -> dict:
    """Invalid and success rates before / after with paired bootstrap intervals."""
    groups = np.arange(len(rows))
    out: dict = {"objects": len(rows),
                 "changed": int(sum(r[f"{verb}_changed"] for r in rows)),
                 "refused": int(sum(r[f"{verb}_after"].get("refused", False) for r in rows))}
    for metric, fn in (("invalid", lambda o: not o["valid"]), ("success", lambda o: o["success"])):
        b = np.array([fn(r[f"{verb}_before"]) for r in rows], float)
        a = np.array([fn(r[f"{verb}_after"]) for r in rows], float)
        for name, v in (("before", b), ("after", a), ("change", a - b)):
            m, lo, hi = bootstrap_ci(lambda i, v=v: float(np.mean(v[i])), groups, n_boot)
            out[f"{metric}_{name}"] = {"mean": m, "lo": lo, "hi": hi}
    reasons: dict[str, dict[str, int]] = {}
    for when in ("before", "after"):
        for r in rows:
            o = r[f"{verb}_{when}"]
            if not o["valid"]:
                reasons.setdefault(when, {}).setdefault(o["reason"], 0)
                reasons[when][o["reason"]] += 1
    out["invalid_reasons"] = reasons
    ms = np.array([r[f"{verb}_check_ms"] for r in rows])
    out["check_ms"] = {"median": float(np.median(ms)), "p90": float(np.percentile(ms, 90)),
                       "max": float(ms.max())}
    out["clear_share"] = float(np.mean([r[f"{verb}_clear_share"] for r in rows]))
    return out


def calibrate(world: SimWorld, model, primitive: str, args) -> dict:
    """Explore-split objects: the top and some random map candidates executed, a grid of
    check settings scored on them (rejected share, invalid trials caught, successes lost,
    and what the first clear of the top candidates would have done)."""
    cats = load_categories()
    objects = []
    for cat in args.categories:
        for inst in cats.instances(cat, "explore")[:args.calibrate_per_category]:
            t = Target(cat, inst, 0)
            cloud = world.observe(t)
            feats = model.encode(torch.from_numpy(cloud.points[None]))[0]
            rng = np.random.default_rng(stable_seed("approach_check", "calibrate", t.name))
            pidx, up, fwd = map_candidates(cloud, args.directions, rng)
            aff, _ = heads(model, feats, pidx, up, fwd)
            top = np.argsort(-aff, kind="stable")[:args.calibrate_top]
            pick = np.concatenate([top, rng.choice(len(aff), args.calibrate_random,
                                                   replace=False)])
            out = [execute(world, t, cloud, pidx, up, fwd, int(i), primitive) for i in pick]
            objects.append((cloud.points, cloud.points[pidx[pick]], up[pick], fwd[pick],
                            np.array([not o["valid"] for o in out]),
                            np.array([o["success"] for o in out])))
    grid = [ApproachCheck(m, r, s, 0) for m, r, s in itertools.product(
        (0.0, 0.005, 0.01), (0.025, 0.04, 0.055), (0.0, 0.01, 0.02))]
    grid += [ApproachCheck(DEFAULT_CHECK.margin, DEFAULT_CHECK.contact_radius,
                           DEFAULT_CHECK.standoff, k) for k in (1, 2)]
    table = []
    k = args.calibrate_top
    for chk in [None, *grid]:
        blocked, invalid, success, first = [], [], [], []
        for cloud, p, u, f, inv, suc in objects:
            hit = (approach_hits(cloud, p, u, f, primitive, chk) > chk.max_points
                   if chk is not None else np.zeros(len(p), bool))
            blocked.append(hit)
            invalid.append(inv)
            success.append(suc)
            clear = np.flatnonzero(~hit[:k])
            first.append((inv[clear[0]], suc[clear[0]]) if len(clear) else None)
        b, i, s = (np.concatenate(x) for x in (blocked, invalid, success))
        done = [x for x in first if x is not None]
        table.append({
            "check": chk.to_dict() if chk is not None else None,
            "rejected": float(b.mean()),
            "invalid_caught": float(b[i].mean()) if i.any() else float("nan"),
            "success_among_rejected": float(s[b].mean()) if b.any() else float("nan"),
            "success_among_kept": float(s[~b].mean()) if (~b).any() else float("nan"),
            "first_clear_invalid": int(sum(x[0] for x in done)),
            "first_clear_success": int(sum(x[1] for x in done)),
            "first_clear_refused": len(first) - len(done)})
    return {"objects": len(objects), "candidates_per_object": int(k + args.calibrate_random),
            "grid": table}


def timing(args) -> dict:
    """Throughput of the check alone: ``--time-candidates`` random candidates on a real
    2048-point cloud (median of 5)."""
    world = SimWorld()
    cloud = world.observe(Target("cabinet", 40, 0))
    rng = np.random.default_rng(0)
    cand = sample_candidates(cloud, args.time_candidates // 8, 8, rng)
    out = {}
    for prim in args.primitives:
        ts = []
        for _ in range(6):
            t0 = time.perf_counter()
            approach_clear(cloud.points, cloud.points[cand.point_index], cand.up, cand.forward,
                           prim)
            ts.append(time.perf_counter() - t0)
        out[prim] = {"candidates": len(cand), "points": len(cloud.points),
                     "seconds": float(np.median(ts[1:]))}
    return out


def _pct(d: dict) -> str:
    return f"{100 * d['mean']:.1f} [{100 * d['lo']:.1f}, {100 * d['hi']:.1f}]"


def render_main(res: dict) -> list[str]:
    """The before / after table and what it was measured on (results.md and docs/ros_api.md)."""
    lines = ["| verb | primitive | n | invalid before | invalid after | change | "
             "success before | success after | change | action changed | refused | "
             "check ms / object (median, max) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for verb in ("manipulate", "explore"):
        for prim, r in res["results"][verb].items():
            n = f"{r['objects']}" + (" pairs" if prim == "both" else "")
            lines.append(
                f"| {verb} | {prim} | {n} | {_pct(r['invalid_before'])} | "
                f"{_pct(r['invalid_after'])} | {_pct(r['invalid_change'])} | "
                f"{_pct(r['success_before'])} | {_pct(r['success_after'])} | "
                f"{_pct(r['success_change'])} | {r['changed']} | {r['refused']} | "
                f"{r['check_ms']['median']:.1f}, {r['check_ms']['max']:.1f} |")
    c = res["config"]
    t = res["timing"]
    lines += ["", f"Rates in % with 95 % bootstrap intervals over objects (paired: the same "
              f"resample for before, after and the change); n: objects, both: object x "
              f"primitive pairs. {c['per_category']} TEST instances x {len(c['categories'])} "
              f"categories; manipulate checks the {c['candidates']} best of "
              f"{c['directions']} frames x 2048 points, explore the "
              f"{c['explore_points']} x {c['explore_dirs']} loop candidates. Action changed: "
              f"the check moved the choice off a blocked action; refused: no clear candidate "
              f"(nothing executed). Check {json.dumps(c['check'])}; throughput of the check "
              f"alone: " + ", ".join(
                  f"{p} {v['candidates']} candidates x {v['points']} points in "
                  f"{1e3 * v['seconds']:.0f} ms" for p, v in t.items()) + "."]
    return lines


def render(res: dict) -> str:
    lines = render_main(res)
    if res.get("calibration"):
        lines += ["", "Calibration (EXPLORE-split objects, not the test ones): per setting, "
                  "the share of executed candidates rejected, of the invalid ones caught, the "
                  "success rate among the rejected and the kept ones, and the first clear of "
                  "the top candidates per object (invalid / success / refused).", "",
                  "| primitive | margin | contact radius | standoff | max points | rejected | "
                  "invalid caught | success rejected | success kept | first clear: "
                  "invalid / success / refused |", "|---|---|---|---|---|---|---|---|---|---|"]
        for prim, cal in res["calibration"].items():
            for g in cal["grid"]:
                ck = g["check"]
                cells = ("no check", "", "", "") if ck is None else (
                    ck["margin"], ck["contact_radius"], ck["standoff"], ck["max_points"])
                mark = " (default)" if ck == res["config"]["check"] else ""
                lines.append(
                    f"| {prim}{mark} | {cells[0]} | {cells[1]} | {cells[2]} | {cells[3]} | "
                    f"{100 * g['rejected']:.0f} | {100 * g['invalid_caught']:.0f} | "
                    f"{100 * g['success_among_rejected']:.0f} | "
                    f"{100 * g['success_among_kept']:.0f} | {g['first_clear_invalid']} / "
                    f"{g['first_clear_success']} / {g['first_clear_refused']} "
                    f"(of {cal['objects']}) |")
    return "\n".join(lines) + "\n"


def to_json(res: dict) -> str:
    """Indented, but one line per object, floats to 4 significant digits (a small file)."""
    def small(x):
        if isinstance(x, float):
            return float(f"{x:.4g}")
        if isinstance(x, dict):
            return {k: small(v) for k, v in x.items()}
        if isinstance(x, list):
            return [small(v) for v in x]
        return x

    res = small(res)
    head = json.dumps({k: v for k, v in res.items() if k != "objects"}, indent=1)[:-2]
    objs = ",\n".join(f' "{p}": [\n' + ",\n".join("  " + json.dumps(r) for r in rows) + "\n ]"
                      for p, rows in res["objects"].items())
    return head + ',\n "objects": {\n' + objs + "\n }\n}\n"


README = Path(__file__).resolve().parents[1] / "docs" / "ros_api.md"  # holds the table
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "approach_check"
BEGIN, END = "<!-- approach_check:begin -->", "<!-- approach_check:end -->"


def readme(results: Path, check: bool) -> int:
    """Rewrite (or, with ``check``, compare) docs/ros_api.md's block from the committed JSON."""
    res = json.loads(results.read_text())
    text = README.read_text()
    if BEGIN not in text or END not in text:
        print(f"{README} has no {BEGIN} ... {END} block", file=sys.stderr)
        return 1
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    new = head + BEGIN + "\n" + "\n".join(render_main(res)) + "\n" + END + tail
    if check:
        if new != text:
            print(f"{README}'s approach-check block is not {results} rendered: run "
                  "bench/approach_check.py --readme", file=sys.stderr)
            return 1
        return 0
    README.write_text(new)
    return 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--per-category", type=int, default=5, help="TEST instances per category")
    ap.add_argument("--categories", nargs="+", default=None, help="default: all")
    ap.add_argument("--primitives", nargs="+", default=["push", "pull"])
    ap.add_argument("--directions", type=int, default=16, help="frames per point (maps)")
    ap.add_argument("--candidates", type=int, default=256,
                    help="best map actions checked (the planner's approach_candidates)")
    ap.add_argument("--explore-points", type=int, default=256)
    ap.add_argument("--explore-dirs", type=int, default=8)
    ap.add_argument("--calibrate-per-category", type=int, default=3,
                    help="EXPLORE instances per category for the calibration (0: skip)")
    ap.add_argument("--calibrate-top", type=int, default=24)
    ap.add_argument("--calibrate-random", type=int, default=8)
    ap.add_argument("--time-candidates", type=int, default=2048)
    ap.add_argument("--bootstrap", type=int, default=2000)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(DEFAULT_OUT))
    ap.add_argument("--readme", action="store_true",
                    help="only rewrite docs/ros_api.md's block from OUT/results.json")
    ap.add_argument("--check", action="store_true",
                    help="with --readme: exit 1 when docs/ros_api.md's block is stale")
    args = ap.parse_args()
    if args.readme:
        sys.exit(readme(Path(args.out) / "results.json", args.check))
    torch.set_num_threads(args.threads)
    args.categories = args.categories or list(load_categories().categories)
    t_start = time.perf_counter()
    world = SimWorld()
    targets = evaluation_targets(args.categories, args.per_category)
    clouds = {t.name: world.observe(t) for t in targets}
    rows: dict[str, list[dict]] = {}
    calibration = {}
    for prim in args.primitives:
        model, _ = load_model(default_checkpoint(prim), "cpu")
        model.eval()
        with torch.no_grad():
            rows[prim] = [measure(world, model, t, clouds[t.name], prim, args) for t in targets]
            if args.calibrate_per_category:
                calibration[prim] = calibrate(world, model, prim, args)
        print(f"{prim}: {len(targets)} objects measured ({time.perf_counter() - t_start:.0f} s)",
              flush=True)
    n_boot = args.bootstrap
    results = {verb: {prim: rates(rows[prim], verb, n_boot) for prim in args.primitives}
               for verb in ("manipulate", "explore")}
    for verb in results:
        results[verb]["both"] = rates([r for p in args.primitives for r in rows[p]], verb, n_boot)
    res = {"config": {"per_category": args.per_category, "categories": args.categories,
                      "primitives": args.primitives, "directions": args.directions,
                      "candidates": args.candidates, "explore_points": args.explore_points,
                      "explore_dirs": args.explore_dirs, "bootstrap": n_boot,
                      "check": DEFAULT_CHECK.to_dict(),
                      "checkpoints": [f"checkpoints/w2e_cfw_{p}.pt" for p in args.primitives]},
           "results": results, "timing": timing(args), "calibration": calibration,
           "objects": rows, "seconds": time.perf_counter() - t_start}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(to_json(res))
    if out.resolve() == DEFAULT_OUT.resolve():  # the committed results: docs/ros_api.md follows
        readme(out / "results.json", check=False)
    md = render(res)
    (out / "results.md").write_text("# Approach check: invalid and success rates before / "
                                    "after\n\nCommand: `.venv/bin/python bench/"
                                    "approach_check.py`\n\n" + md)
    print(md)
    print(f"wrote {out}/results.json, results.md in {res['seconds']:.0f} s")


if __name__ == "__main__":
    main()
