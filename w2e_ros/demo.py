"""``w2e demo``: the whole story on a fresh machine, through the ROS stack.

Brings the stack up (sim bridge, segmentation, inference with the shipped checkpoints,
executor, planner), picks a category that the default combination (cfw) never trained on,
and through the Python client:

1. ``manipulate`` unseen TEST instances -> success rate before exploring;
2. for each rule (default: the best measured, ``random``, and the paper's ``similarity``):
   ``explore`` 6 EXPLORE instances of the category (a longer row occludes itself), 5
   interactions per instance, every rule spending the whole budget (equal spend), then
   ``manipulate`` the same TEST instances again (same start states) -> success rate after,
   and ``reset_model`` before the next rule;

and prints each rule's before -> after with a 95 % interval and the paired comparison, beside
what ten seeds of the same run gave (bench/results/demo_seeds), and writes a plot of the
success rates and affordance / similarity heatmaps of one test instance as PNGs.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from pathlib import Path

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.exploration.config import ExploreConfig
from w2e_ros.core.exploration.strategies import BEST_RULE, STRATEGIES, describe_rules
from w2e_ros.paths import default_checkpoint

READY_TIMEOUT_S = 180.0  # bring-up: the nodes, then their services


def add_arguments(p: argparse.ArgumentParser) -> None:
    cats = load_categories()
    # bucket pull: of the novel categories, the one that learns most from its own
    # interactions on the validation split (w2e learnability --validate --per-category;
    # bench/results/demo_choice), never chosen on the test split it is shown on
    p.add_argument("--category", default="bucket", choices=cats.novel(),
                   help="novel category of the default combination (default bucket)")
    p.add_argument("--primitive", default="pull", choices=["push", "pull"])
    p.add_argument("--budget", type=int, default=5,
                   help="exploration interactions per explore instance (the paper's budget)")
    p.add_argument("--similarity-bar", type=float, default=1.0,
                   help="mean similarity at which an object is no longer explored (the "
                        "request's similarity_bar; default 1.0: never, so every rule spends "
                        f"the same budget; the paper stops at {ExploreConfig.similarity_bar})")
    p.add_argument("--explore-instances", type=int, default=6,
                   help="EXPLORE-split instances in the scene while exploring")
    p.add_argument("--test-instances", type=int, default=10,
                   help="unseen TEST-split instances manipulated before and after")
    p.add_argument("--validate", action="store_true",
                   help="manipulate the explore-split instances that are not explored "
                        "instead of TEST-split ones (e.g. --explore-instances 5: explore "
                        "30-34, judge 35-39), to choose settings without the test split")
    p.add_argument("--checkpoint", default=None,
                   help="model of the primitive (default: shipped checkpoints/w2e_cfw_*.pt)")
    p.add_argument("--out", default="results/demo", help="directory for the PNGs and summary")
    p.add_argument("--rules", nargs="+", default=list(dict.fromkeys([BEST_RULE, "similarity"])),
                   choices=list(STRATEGIES), metavar="RULE",
                   help="exploration rules run one after the other from the same model and "
                        f"the same start (default: {BEST_RULE} and similarity): "
                        f"{describe_rules()}")
    p.add_argument("--strategy", default=None, choices=list(STRATEGIES),
                   help="one rule only (as --rules RULE)")
    p.add_argument("--seed", type=int, default=0,
                   help="the planner's seed (candidate sampling, start states)")
    p.add_argument("--replay-data", default="",
                   help="what the inference node replays while fine-tuning: a w2e collect "
                        "or replay-pack directory, shipped (checkpoints/replay_cfw); '': the "
                        "node's default")
    p.add_argument("--params-file", default=None,
                   help="the stack's parameters (default: config/w2e_stack.yaml), e.g. a "
                        "copy with other fine-tuning settings for the inference node")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID of the stack")
    p.add_argument("--quiet-nodes", action="store_true", help="hide the nodes' output")


def _heatmaps(client, category: str, instance: int, primitive: str, out: Path,
              tag: str) -> Path:
    """Load one test instance alone, get its maps from the inference node, draw them."""
    from w2e_ros.core.dataset.targets import stable_seed
    from w2e_ros.core.model.viz import heatmap_figure

    t = client.now_s()
    (oid,) = client.load_scene(category, [instance], seeds=[stable_seed("demo", instance)])
    objs = client.objects([oid], newer_than_s=t)
    (m,) = client.predict_maps(objs, primitive=primitive, num_directions=16)
    return heatmap_figure(m.points, {"affordance": m.affordance, "similarity": m.similarity},
                          out / f"heatmap_{category}_{instance}_{tag}.png",
                          title=f"{category}/{instance} {primitive} {tag} "
                                f"(mean similarity {m.mean_similarity:.2f})")


def _manipulate_each(client, category: str, instances: list[int], primitive: str, tag: str):
    """One instance per call, each alone in the scene (no occlusion by its neighbours, and
    the same start state before and after: the planner seeds it from the instance)."""
    from w2e_ros.client import ManipulateResult

    total = ManipulateResult(True, "")
    for i in instances:
        r = client.manipulate(category, instances=[i], primitive=primitive)
        o = r.outcomes[0] if r.outcomes else None
        print(f"[demo] {tag}: {category}/{i}: " + (
            f"{'moved' if o.success else 'no success'} (motion {o.motion:+.3f}, predicted "
            f"affordance {o.predicted_affordance:.2f}{', ' + o.reason if o.reason else ''})"
            if o else r.message))
        total.outcomes += r.outcomes
        total.seconds += r.seconds
    total.success = all(o.success for o in total.outcomes)
    total.message = f"{sum(o.success for o in total.outcomes)}/{len(instances)} moved"
    return total


def _replay_arg(value: str) -> str:
    """The inference node's replay_data: ``shipped`` as it is, a directory made absolute
    (the nodes run in their own working directory)."""
    return value if value == "shipped" else str(Path(value).resolve())


def _per_instance(instances: list[int], result) -> list[dict]:
    """Each test instance's outcome, so before and after can be paired per instance."""
    return [{"instance": int(i), "success": bool(o.success), "valid": bool(o.valid),
             "motion": float(o.motion), "predicted_affordance": float(o.predicted_affordance),
             "reason": o.reason} for i, o in zip(instances, result.outcomes, strict=True)]


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def run(a: argparse.Namespace) -> int:
    from w2e_ros.bringup import Stack
    from w2e_ros.client import W2EClient
    from w2e_ros.ros.processes import pick_domain_id, ros_env

    # SIGTERM (timeout, a scheduler) stops the demo like Ctrl-C: the stack is torn down; and
    # started in the background of a script a process inherits SIGINT ignored (POSIX)
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    cats = load_categories()
    ckpt = Path(a.checkpoint) if a.checkpoint else default_checkpoint(a.primitive)
    if not ckpt.exists():
        print(f"w2e demo: no {a.primitive} model at {ckpt}; train one (`w2e train`) or pass "
              "--checkpoint", file=sys.stderr)
        return 2
    if a.params_file and not Path(a.params_file).is_file():
        print(f"w2e demo: no parameter file {a.params_file}", file=sys.stderr)
        return 2
    explore = cats.instances(a.category, "explore")[:a.explore_instances]
    try:
        test = cats.evaluation_instances(a.category, a.validate, len(explore))[:a.test_instances]
    except ValueError as e:
        print(f"w2e demo: {e}", file=sys.stderr)
        return 2
    rules = [a.strategy] if a.strategy else list(dict.fromkeys(a.rules))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    domain = a.domain_id if a.domain_id is not None else pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=out / "ros_log")
    extra = {"inference": ["-p", f"{a.primitive}_checkpoint:={ckpt.resolve()}",
                           "-p", f"adapted_dir:={(out / 'adapted').resolve()}"]
             + (["-p", f"replay_data:={_replay_arg(a.replay_data)}"] if a.replay_data
                else []),
             "planner": ["-p", f"exploration_log_dir:={(out / 'exploration').resolve()}",
                         "-p", f"strategy:={rules[0]}", "-p", f"seed:={a.seed}"]}
    total = a.budget * len(explore)
    print(f"[demo] {a.category} ({a.primitive}), model {ckpt}; test {test}, explore {explore}; "
          f"rules {', '.join(rules)}, {total} interactions each")
    t_all = time.perf_counter()
    runs: dict[str, dict] = {}
    # a loaded machine (the inference node reading its checkpoints and replay data beside
    # other jobs) once needed more than 60 s: the services get the same 180 s as the nodes
    with Stack(params=a.params_file, env=env, extra_args=extra,
               output=None if a.quiet_nodes else sys.stdout,
               ready_timeout=READY_TIMEOUT_S), W2EClient(domain_id=domain) as w2e:
        if missing := w2e.missing_services(READY_TIMEOUT_S):
            print(f"w2e demo: the stack did not come up: no {', '.join(missing)} within "
                  f"{READY_TIMEOUT_S:.0f} s (run without --quiet-nodes to see the nodes' "
                  "output)", file=sys.stderr)
            return 1
        print(f"[demo] stack up in {time.perf_counter() - t_all:.0f} s")
        pngs = [_heatmaps(w2e, a.category, test[0], a.primitive, out, "before")]
        before = _manipulate_each(w2e, a.category, test, a.primitive, "before")
        for k, rule in enumerate(rules):
            if k:
                w2e.reset_model()  # every rule starts from the shipped model
            w2e.set_strategy(rule, seed=a.seed)
            t_rule = time.perf_counter()
            print(f"[demo] rule {k + 1}/{len(rules)}: {rule}")
            explored = w2e.explore(
                a.category, instances=explore, primitive=a.primitive, budget=a.budget,
                similarity_bar=a.similarity_bar, session=f"demo_{rule}",
                on_progress=lambda s, t0=t_rule: print(
                    f"[demo]   {s.step}/{total} ({time.perf_counter() - t0:.0f} s): object "
                    f"{s.action.object_id} similarity {s.predicted_similarity:.2f} -> "
                    f"{'success' if s.success else 'no motion'} (motion {s.motion:+.3f})"))
            print(f"[demo] explore ({rule}): {explored.message}")
            after = _manipulate_each(w2e, a.category, test, a.primitive, f"after {rule}")
            pngs.append(_heatmaps(w2e, a.category, test[0], a.primitive, out, f"after_{rule}"))
            runs[rule] = {"after": _per_instance(test, after),
                          "success_rate_after": after.success_rate,
                          "explore": {"ok": explored.success, "message": explored.message,
                                      "interactions": explored.interactions_used,
                                      "final_mean_similarity": explored.final_mean_similarity,
                                      "checkpoint": explored.checkpoint_path},
                          "seconds": {"explore": explored.seconds,
                                      "manipulate_after": after.seconds}}
    first = rules[0]
    summary = {
        "category": a.category, "primitive": a.primitive, "checkpoint": str(ckpt),
        "test_instances": test, "explore_instances": explore, "validate": a.validate,
        "budget": a.budget, "similarity_bar": a.similarity_bar, "rules": rules,
        "seed": a.seed, "replay_data": a.replay_data, "params_file": a.params_file or "",
        "success_rate_before": before.success_rate, "before": _per_instance(test, before),
        "runs": runs,
        # the first rule's run at the top level too (bench/demo_seeds.py reads one rule so)
        "strategy": first, "after": runs[first]["after"],
        "success_rate_after": runs[first]["success_rate_after"],
        "explore": runs[first]["explore"],
        "seconds": {"manipulate_before": before.seconds, "total": time.perf_counter() - t_all},
        "heatmaps": [str(p) for p in pngs],
    }
    summary["plot"] = str(success_plot(summary, out / "success_rates.png"))
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print()
    print(report(summary, recorded_runs()))
    print(f"\nplot: {summary['plot']}; heatmaps: {', '.join(str(p) for p in pngs)}; "
          f"summary: {out / 'summary.json'} ({summary['seconds']['total']:.0f} s)")
    return 0 if all(r["explore"]["ok"] for r in runs.values()) else 1


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson interval of a success rate k/n: honest at 10 trials, unlike k/n +- 2 se."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    mid = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, mid - half), min(1.0, mid + half)


def _count(outcomes: list[dict]) -> int:
    return sum(o["success"] for o in outcomes)


def recorded_runs(path: Path | None = None) -> dict | None:
    """The demo's ten-seed record (bench/demo_seeds.py), where the source tree has it."""
    path = path or Path(__file__).resolve().parents[1] / "bench" / "results" / "demo_seeds" / \
        "demo_seeds.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def report(summary: dict, recorded: dict | None = None) -> str:
    """What the run showed, in words a user reads: each rule's before -> after with its 95 %
    interval and the per-instance pairing, each rule against the first (rule - baseline), and
    what ten seeds of the same demo gave, so that one run is read as one draw."""
    before = summary["before"]
    n = len(before)
    b = _count(before)
    lines = [f"success on {n} unseen {summary['category']} instances ({summary['primitive']}), "
             f"95 % Wilson intervals:"]
    lo, hi = wilson(b, n)
    lines.append(f"  before exploring: {b}/{n} [{lo:.0%}, {hi:.0%}]")
    rules = summary["rules"]
    for rule in rules:
        r = summary["runs"][rule]
        k = _count(r["after"])
        lo, hi = wilson(k, n)
        pairs = list(zip(r["after"], before, strict=True))
        gained = sum(o["success"] and not p["success"] for o, p in pairs)
        lost = sum(p["success"] and not o["success"] for o, p in pairs)
        lines.append(f"  after {r['explore']['interactions']} interactions with {rule}: "
                     f"{k}/{n} [{lo:.0%}, {hi:.0%}] (instances gained {gained}, lost {lost})")
    base = rules[0]
    for rule in rules[1:]:
        diff = _count(summary["runs"][rule]["after"]) - _count(summary["runs"][base]["after"])
        lines.append(f"  {rule} - {base}, after: {diff:+d} of {n} (same instances, same spend)")
    if recorded:
        lines.append("one run is one draw; ten seeds of the demo (bench/results/demo_seeds, "
                     "bar 0.9, so similarity spent less):")
        for rule, r in recorded.get("strategies", {}).items():
            after = [s["after"] for s in r["per_seed"]]
            lines.append(f"  {rule}: {r['before']}/{r['trials']} -> {r['after']}/{r['trials']}, "
                         f"one seed's after from {min(after)} to {max(after)} of "
                         f"{r['trials'] // len(after)}")
    return "\n".join(lines)


def success_plot(summary: dict, path: Path) -> Path:
    """Bars of the success rate before and after each rule, with the Wilson intervals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(summary["before"])
    labels = ["before"] + [f"after {r}\n({summary['runs'][r]['explore']['interactions']} "
                           "interactions)" for r in summary["rules"]]
    counts = [_count(summary["before"])] + [_count(summary["runs"][r]["after"])
                                            for r in summary["rules"]]
    rates = [k / n for k in counts]
    cis = [wilson(k, n) for k in counts]
    err = [[r - lo for r, (lo, _) in zip(rates, cis, strict=True)],
           [hi - r for r, (_, hi) in zip(rates, cis, strict=True)]]
    fig, ax = plt.subplots(figsize=(1.8 + 1.6 * len(labels), 3.6))
    ax.bar(range(len(labels)), rates, yerr=err, capsize=6,
           color=["#999999"] + ["#d95f02", "#1b9e77", "#7570b3", "#e7298a"][:len(labels) - 1])
    for i, k in enumerate(counts):
        ax.text(i, rates[i] + 0.02, f"{k}/{n}", ha="center", va="bottom")
    ax.set_xticks(range(len(labels)), labels)
    ax.set_ylim(0, 1)
    ax.set_ylabel("success on unseen instances")
    ax.set_title(f"{summary['category']} {summary['primitive']}, seed {summary['seed']} "
                 "(95 % Wilson intervals)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
