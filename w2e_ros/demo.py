"""``w2e demo``: the whole story on a fresh machine, through the ROS stack.

Brings the stack up (sim bridge, segmentation, inference with the shipped checkpoints,
executor, planner), picks a category that the default combination (cfw) never trained on,
and through the Python client:

1. ``manipulate`` unseen TEST instances -> success rate before exploring;
2. ``explore`` 6 EXPLORE instances of the category (a longer row occludes itself), 5
   interactions per instance;
3. ``manipulate`` the same TEST instances again (same start states) -> success rate after;

and writes affordance / similarity heatmaps of one test instance, before and after, as PNGs.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.exploration.config import ExploreConfig
from w2e_ros.core.exploration.strategies import STRATEGIES, describe_rules
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
    p.add_argument("--similarity-bar", type=float, default=ExploreConfig.similarity_bar,
                   help="mean similarity at which an object is no longer explored (the "
                        "request's similarity_bar)")
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
    p.add_argument("--strategy", default="similarity", choices=list(STRATEGIES),
                   help=f"the planner's exploration rule: {describe_rules()}")
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
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    domain = a.domain_id if a.domain_id is not None else pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=out / "ros_log")
    extra = {"inference": ["-p", f"{a.primitive}_checkpoint:={ckpt.resolve()}",
                           "-p", f"adapted_dir:={(out / 'adapted').resolve()}"]
             + (["-p", f"replay_data:={_replay_arg(a.replay_data)}"] if a.replay_data
                else []),
             "planner": ["-p", f"exploration_log_dir:={(out / 'exploration').resolve()}",
                         "-p", f"strategy:={a.strategy}", "-p", f"seed:={a.seed}"]}
    print(f"[demo] {a.category} ({a.primitive}), model {ckpt}; test {test}, explore {explore}")
    t_all = time.perf_counter()
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
        pngs = [_heatmaps(w2e, a.category, test[0], a.primitive, out, "before")]
        before = _manipulate_each(w2e, a.category, test, a.primitive, "before")
        explored = w2e.explore(
            a.category, instances=explore, primitive=a.primitive, budget=a.budget,
            similarity_bar=a.similarity_bar,
            on_progress=lambda s: print(
                f"[demo]   step {s.step}: object {s.action.object_id} similarity "
                f"{s.predicted_similarity:.2f} -> {'success' if s.success else 'no motion'} "
                f"(motion {s.motion:+.3f}), mean similarity {s.mean_similarity:.3f}"))
        print(f"[demo] explore: {explored.message}")
        after = _manipulate_each(w2e, a.category, test, a.primitive, "after")
        pngs.append(_heatmaps(w2e, a.category, test[0], a.primitive, out, "after"))
    summary = {
        "category": a.category, "primitive": a.primitive, "checkpoint": str(ckpt),
        "test_instances": test, "explore_instances": explore, "validate": a.validate,
        "budget": a.budget,
        "similarity_bar": a.similarity_bar, "strategy": a.strategy, "seed": a.seed,
        "replay_data": a.replay_data, "params_file": a.params_file or "",
        "success_rate_before": before.success_rate, "success_rate_after": after.success_rate,
        "before": _per_instance(test, before), "after": _per_instance(test, after),
        "explore": {"ok": explored.success, "message": explored.message,
                    "interactions": explored.interactions_used,
                    "final_mean_similarity": explored.final_mean_similarity,
                    "checkpoint": explored.checkpoint_path},
        "seconds": {"manipulate_before": before.seconds, "explore": explored.seconds,
                    "manipulate_after": after.seconds, "total": time.perf_counter() - t_all},
        "heatmaps": [str(p) for p in pngs],
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"\nsample success on {len(test)} unseen {a.category} instances ({a.primitive}): "
          f"before {before.success_rate:.0%}, after exploring {explored.interactions_used} "
          f"interaction(s) {after.success_rate:.0%}")
    print(f"heatmaps: {', '.join(str(p) for p in pngs)}; summary: {out / 'summary.json'}")
    return 0 if explored.success else 1
