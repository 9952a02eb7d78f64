"""The ``w2e`` command line: one command, one verb per step of the workflow.

Each verb parses its flags here and calls one function of the core, of the simulator
experiments (``collect``, ``benchmark``, ...) or of the ROS layer (``bringup`` and ``demo``);
heavy modules are imported only when their verb runs, so ``w2e --help`` is instant.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING

from w2e_ros.core.exploration.config import ExploreConfig
from w2e_ros.core.exploration.strategies import describe_rules, registry
from w2e_ros.core.infra.allocator import keep_freed_memory
from w2e_ros.core.infra.settings import add_arguments, from_namespace
from w2e_ros.core.model.config import NETWORK_FLAGS, ModelConfig, TrainConfig, combinations
from w2e_ros.experiments.config import (
    BenchmarkConfig,
    CollectConfig,
    LabelCheckConfig,
    LearnabilityConfig,
    OracleConfig,
)

if TYPE_CHECKING:
    from w2e_ros.experiments.backends import Backend

Handler = Callable[[argparse.Namespace], int | None]


def _add_collect(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "collect", help="run random interactions in the simulator and write training shards",
        description="Collect interactions grouped by observation into resumable shards.")
    add_arguments(p, CollectConfig)
    _add_backend_args(p)
    p.set_defaults(func=_run_collect)


def _run_collect(a: argparse.Namespace) -> int:
    from w2e_ros.experiments.collect import collect

    cfg = from_namespace(CollectConfig, a)
    with _backend(a, cfg.workers) as backend:
        summary = collect(cfg, backend)
    print(summary.table())
    return 0


def _add_backend_args(p: argparse.ArgumentParser) -> None:
    """Where the jobs of ``collect`` and ``benchmark`` run (w2e_ros.experiments.backends)."""
    p.add_argument("--backend", default="local", choices=["local", "ray"],
                   help="local processes, or one Ray task per job (a local Ray instance, or "
                        "the cluster at --address)")
    p.add_argument("--address", default=None,
                   help="with --backend ray: the cluster to join, 'auto' (the one `ray start` "
                        "started on this host) or HOST:PORT of its head; default: a private "
                        "local instance")


def _backend(a: argparse.Namespace, workers: int) -> contextlib.closing[Backend]:
    from w2e_ros.experiments.backends import make_backend

    return contextlib.closing(make_backend(a.backend, workers, a.address))


def _add_network_args(p: argparse.ArgumentParser) -> None:
    """The network's settings (``ModelConfig``) that a run may change from the default."""
    add_arguments(p, ModelConfig, only=NETWORK_FLAGS)


def _network_overrides(a: argparse.Namespace) -> dict:
    """The network's settings as given by the flags of ``_add_network_args``."""
    return {k: tuple(v) if isinstance(v, list) else v
            for k, v in vars(a).items() if k in NETWORK_FLAGS}


def _add_train(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train", help="train the affordance + similarity model (or a baseline) on collected data",
        description="Train one model per primitive. w2e: C_aff trains the affordance head, "
                    "C_sim the similarity head; where2act: affordance on the three training "
                    "categories; fulldata: affordance on all 14 categories. Data-parallel: "
                    "torchrun --nproc_per_node N -m w2e_ros.cli train ... (gloo on CPUs, "
                    "NCCL on GPUs; the batch is --clouds x N).")
    p.add_argument("--data", required=True, help="collection directory (w2e collect --out)")
    p.add_argument("--out", default=None,
                   help="run directory (default runs/<method>_<combo>_<primitive>)")
    add_arguments(p, TrainConfig)
    p.set_defaults(steps=None)  # None: from --epochs when given, else TrainConfig's
    p.add_argument("--epochs", type=float, default=None,
                   help="alternative to --steps: passes over the training interactions")
    p.add_argument("--val-data", nargs="+", default=None,
                   help="collections with held-out instances (e.g. --split test of the "
                        "training categories): validation every --val-every steps, best "
                        "model kept, early stop after --patience validations without gain")
    _add_network_args(p)
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    p.add_argument("--no-progress", action="store_true", help="log lines instead of a bar")
    p.set_defaults(func=_run_train)


def _run_train(a: argparse.Namespace) -> int:
    import math

    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.model.training import load_training_data, run_name, train

    steps = a.steps
    if steps is None and a.epochs is not None:
        n = load_training_data(a.data, a.method, a.combo, a.primitive).num_interactions
        steps = max(1, math.ceil(a.epochs * n / (a.clouds * a.per_cloud)))
    cfg = from_namespace(TrainConfig, a, steps=TrainConfig.steps if steps is None else steps)
    out = a.out or f"runs/{run_name(a.method, a.combo, a.primitive)}"
    val = None
    if a.val_data:
        val = InteractionData.concat([InteractionData.load(d) for d in a.val_data])
        val = val.select(primitive=a.primitive)
    mcfg = from_namespace(ModelConfig, a)
    path = train(cfg, a.data, out, resume=a.resume, val_data=val, progress=not a.no_progress,
                 model_cfg=mcfg)
    if os.environ.get("RANK", "0") == "0":  # torchrun: process 0 speaks for the run
        print(f"model: {path}")
    return 0


_RUN_SETTINGS = ("budget", "seed", "snapshot_budgets")
"""ExploreConfig settings a verb sets from its own flags (benchmark: --budgets, --seeds)."""


def _add_explore_args(p: argparse.ArgumentParser, skip: tuple[str, ...] = _RUN_SETTINGS) -> None:
    """The few-shot loop's settings (ExploreConfig and its FinetuneConfig), shared by
    ``fewshot``, ``learnability`` and ``benchmark``: one flag per setting, named, typed,
    defaulted and explained by the dataclass field (w2e_ros.core.infra.settings)."""
    add_arguments(p, ExploreConfig, skip)


def _explore_config(a: argparse.Namespace, **kw: object) -> ExploreConfig:
    return from_namespace(ExploreConfig, a, **kw)


def _add_fewshot(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fewshot", help="few-shot exploration of the novel categories in the simulator",
        description="Explore novel categories with a trained model, fine-tuning on every "
                    "interaction; saves the adapted model after each snapshot budget.")
    p.add_argument("--model", required=True, help="checkpoint (w2e train's model.pt)")
    p.add_argument("--replay-data", default=None,
                   help="training collection replayed during fine-tuning (~1%%)")
    p.add_argument("--strategy", default="similarity", choices=list(registry(experimental=True)),
                   metavar="RULE", help=f"exploration rule: {describe_rules(experimental=True)}")
    p.add_argument("--mode", default="all", choices=["all", "per-category"],
                   help="all novel categories in one run, or one run per category")
    p.add_argument("--categories", nargs="+", default=None,
                   help="novel categories to explore (default: the 11 not in the combination)")
    p.add_argument("--objects", type=int, default=10, help="explore instances per category")
    _add_explore_args(p, skip=("snapshot_budgets",))  # with --budget and --seed
    p.add_argument("--out", required=True, help="directory for adapted models and records")
    p.add_argument("--threads", type=int, default=2)
    p.set_defaults(func=_run_fewshot)


def _run_fewshot(a: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    import torch

    from w2e_ros.core.dataset.categories import load_categories
    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.exploration.explore import fewshot
    from w2e_ros.core.exploration.strategies import get_strategy
    from w2e_ros.core.model.network import load_model, save_model
    from w2e_ros.core.model.training import replay_data
    from w2e_ros.experiments.sim_world import SimWorld

    torch.set_num_threads(a.threads)
    model, meta = load_model(a.model)
    primitive = meta.get("primitive", "push")
    cats = a.categories or load_categories().novel(meta.get("combo"))
    replay = None
    if a.replay_data:
        replay = replay_data(InteractionData.load(a.replay_data), meta, primitive)
    cfg = _explore_config(a, snapshot_budgets=tuple(b for b in (1, 2, 5) if b <= a.budget)
                          or (a.budget,))
    rule = get_strategy(a.strategy, experimental=True)
    runs = fewshot(model, meta, SimWorld(model.cfg.num_points), cats, rule, cfg, primitive,
                   replay, a.mode, a.objects)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    for group, (res, explorer) in runs.items():
        for b, snap in res.snapshots.items():
            save_model(out / f"{group}_budget{b}.pt", explorer.model_at(snap),
                       {**meta, "fewshot": group, "budget": b, "strategy": a.strategy})
        (out / f"{group}_records.json").write_text(json.dumps(res.to_dict(), indent=1))
        ok = sum(s.success for s in res.steps)
        print(f"{group}: {len(res.steps)} interactions ({ok} successful), stopped at "
              f"{res.stopped}, mean similarity {res.mean_similarity[0]:.3f} -> "
              f"{res.mean_similarity[-1]:.3f}")
    print(f"adapted models: {out}")
    return 0


def _add_learnability(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "learnability", help="test metrics after fine-tuning on N explored interactions",
        description="Diagnostic before any strategy comparison: fine-tune the model on N "
                    "interactions from a collection on the EXPLORE instances of the novel "
                    "categories (random, or the N the model gets most wrong: oracle) and "
                    "score it on the TEST interactions. Writes a table, JSON and a plot.")
    add_arguments(p, LearnabilityConfig, skip=_RUN_SETTINGS)
    p.add_argument("--per-category", action="store_true",
                   help="one curve per novel category, each fine-tuned on its own "
                        "interactions only (out/<category>/ and out/per_category.md)")
    p.add_argument("--threads", type=int, default=2)
    p.set_defaults(func=_run_learnability)


def _run_learnability(a: argparse.Namespace) -> int:
    from pathlib import Path

    import torch

    from w2e_ros.experiments.learnability import run_learnability, run_per_category

    torch.set_num_threads(a.threads)
    cfg = from_namespace(LearnabilityConfig, a)
    if a.per_category:
        summary = run_per_category(cfg)
        print(Path(a.out, "per_category.md").read_text())
    else:
        summary = run_learnability(cfg)
        print(Path(a.out, "learnability.md").read_text())
    return 0 if summary["curves"] else 1


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate", help="F-score on held-out interactions and sample success in the simulator",
        description="Evaluate one model on unseen TEST instances of the novel categories.")
    p.add_argument("--model", required=True, help="checkpoint (train or fewshot output)")
    p.add_argument("--test-data", default=None,
                   help="collection of test-split interactions (w2e collect --split test)")
    p.add_argument("--categories", nargs="+", default=None,
                   help="categories to evaluate (default: the combination's novel ones)")
    p.add_argument("--objects", type=int, default=10,
                   help="test objects per category for the sample success rate (0: skip)")
    p.add_argument("--points", type=int, default=256, help="candidate points per object")
    p.add_argument("--dirs", type=int, default=8, help="candidate actions per point")
    p.add_argument("--json", default=None, help="write the full result here")
    p.add_argument("--threads", type=int, default=2)
    p.set_defaults(func=_run_evaluate)


def _run_evaluate(a: argparse.Namespace) -> int:
    import json

    import torch

    from w2e_ros.core.dataset.categories import load_categories
    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.exploration.evaluate import (
        SuccessProbe,
        evaluate,
        evaluation_targets,
    )
    from w2e_ros.core.model.network import load_model
    from w2e_ros.experiments.sim_world import SimWorld

    torch.set_num_threads(a.threads)
    model, meta = load_model(a.model)
    primitive = meta.get("primitive", "push")
    cats = a.categories or load_categories().novel(meta.get("combo"))
    test = None
    if a.test_data:
        data = InteractionData.load(a.test_data)
        test = InteractionData.concat([data.select(primitive=primitive, categories=[c],
                                                   instances=load_categories()
                                                   .evaluation_instances(c))
                                       for c in cats])
    probe = None
    if a.objects > 0:
        probe = SuccessProbe(SimWorld(model.cfg.num_points), evaluation_targets(cats, a.objects),
                             primitive, a.points, a.dirs)
    res = evaluate(model, test, probe)
    print(f"{'category':<16} {'F-score':>8} {'P':>6} {'R':>6} {'n':>6} {'success':>8}")
    for c in [*cats, "all", "mean"]:
        f = res.get("fscore", {}).get(c, {})
        s = res.get("success", {}).get(c, float("nan"))
        print(f"{c:<16} {100 * f.get('fscore', float('nan')):8.1f} "
              f"{100 * f.get('precision', float('nan')):6.1f} "
              f"{100 * f.get('recall', float('nan')):6.1f} {f.get('n', 0):6d} {100 * s:8.1f}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"model": a.model, "meta": meta, **res}, fh, indent=1)
    return 0


def _add_benchmark(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "benchmark", help="all methods x budgets x primitives over combinations and seeds",
        description="Few-shot benchmark (paper Tables 1-3): markdown tables, a metric-vs-budget "
                    "plot and heatmaps in --out. Reduce combos/seeds/objects for a quick run.")
    add_arguments(p, BenchmarkConfig, skip=_RUN_SETTINGS)  # with the loop's settings
    p.add_argument("--summarize-only", action="store_true",
                   help="recompute benchmark.json / tables / curves from the predictions "
                        "files already in --out (e.g. after runs in parallel processes)")
    p.add_argument("--merge", nargs="+", default=[], metavar="DIR[:METHOD,...]",
                   help="with --summarize-only: first copy the runs in these benchmark "
                        "outputs' predictions files into --out (same test set); DIR:m1,m2 "
                        "copies only those methods' runs")
    p.add_argument("--include-summary", nargs="+", default=[], metavar="JSON",
                   help="with --summarize-only: add the rows of the combinations in these "
                        "earlier benchmark.json files (their predictions files are not in "
                        "--out), e.g. for the mean over all four combinations")
    p.add_argument("--threads", type=int, default=2,
                   help="torch CPU threads (local backend; a Ray task uses one)")
    _add_backend_args(p)
    p.set_defaults(func=_run_benchmark)


def _run_benchmark(a: argparse.Namespace) -> int:
    from pathlib import Path

    import torch

    from w2e_ros.experiments.benchmark import merge_predictions, run_benchmark, summarize

    torch.set_num_threads(a.threads)
    cfg = from_namespace(BenchmarkConfig, a)
    if (a.merge or a.include_summary) and not a.summarize_only:
        print("w2e benchmark: --merge and --include-summary go with --summarize-only",
              file=sys.stderr)
        return 2
    if a.summarize_only:
        try:
            merge_predictions(a.out, a.merge)
            summarize(a.out, cfg, include=a.include_summary, sources=a.merge)
        except ValueError as e:
            print(f"w2e benchmark: {e}", file=sys.stderr)
            return 2
    else:
        with _backend(a, 1) as backend:  # local: the runs one after the other
            run_benchmark(cfg, backend=backend)
    print((Path(a.out) / "tables.md").read_text())
    return 0


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="bring up the ROS stack, manipulate / explore / manipulate a novel category",
        description="Success rate on unseen test instances before and after few-shot "
                    "exploration, through the ROS stack; heatmap PNGs before/after.")
    from w2e_ros.demo import add_arguments

    add_arguments(p)
    p.set_defaults(func=lambda a: __import__("w2e_ros.demo", fromlist=["run"]).run(a))


def _add_bringup(sub: argparse._SubParsersAction) -> None:
    from w2e_ros.bringup import DESCRIPTION, add_arguments

    p = sub.add_parser("bringup", help="start the ROS node stack (python -m w2e_ros.bringup)",
                       description=DESCRIPTION)
    add_arguments(p)  # the module's own flags: one definition for both command lines
    p.set_defaults(func=lambda a: __import__("w2e_ros.bringup", fromlist=["run"]).run(a))


def _add_record(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", help="record stack topics to an MCAP rosbag",
                       description="Record topics (serialized, with their message definitions "
                                   "and QoS) to an MCAP file that ros2 bag / Foxglove read.")
    p.add_argument("out", help="output .mcap file")
    p.add_argument("--topics", nargs="+", default=None,
                   help="topics (default: camera/points objects object_joint_states "
                        "exploration_progress affordance_map similarity_map)")
    p.add_argument("--duration", type=float, default=0.0, help="seconds (0: until Ctrl-C)")
    p.add_argument("--namespace", default="", help="namespace of the stack")
    p.add_argument("--domain-id", type=int, default=None)
    p.add_argument("--discovery-timeout", type=float, default=10.0,
                   help="seconds to wait for the topics' publishers")
    p.set_defaults(func=_run_record)


def _run_record(a: argparse.Namespace) -> int:
    from w2e_ros.ros.bag import DEFAULT_TOPICS, record_main

    return record_main(a.out, list(a.topics or DEFAULT_TOPICS), a.duration, a.namespace,
                       a.domain_id, a.discovery_timeout)


def _add_replay(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="publish an MCAP rosbag onto its topics",
                       description="Replay recorded messages with their recorded QoS and "
                                   "timing (scaled by --rate; 0: as fast as possible).")
    p.add_argument("bag", help=".mcap file (w2e record)")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor (0: no waiting)")
    p.add_argument("--topics", nargs="+", default=None, help="only these topics")
    p.add_argument("--loop", action="store_true", help="replay until Ctrl-C")
    p.add_argument("--namespace", default="")
    p.add_argument("--domain-id", type=int, default=None)
    p.set_defaults(func=_run_replay)


def _run_replay(a: argparse.Namespace) -> int:
    from w2e_ros.ros.bag import replay_main

    return replay_main(a.bag, a.rate, a.topics, a.loop, a.namespace, a.domain_id)


def _add_calibrate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate", help="re-fit a trained model's similarity head to its affordance head's "
                          "correctness (about a minute)",
        description="Fit the similarity head anew on the training interactions of the model's "
                    "similarity categories: target = the affordance head is right. With "
                    "--balanced successes and failures weigh half each, so 'predicts fail "
                    "and is right because most actions fail' no longer reads as familiar. "
                    "A where2act model (affordance on all training categories) gets a "
                    "similarity fitted on those categories: the 'wide' variant, which "
                    "explores with every w2e strategy (bench/RESEARCH.md).")
    p.add_argument("--model", required=True, help="checkpoint to calibrate")
    p.add_argument("--data", required=True, help="its training collection (w2e collect --out)")
    p.add_argument("--out", required=True, help="where to write the calibrated checkpoint")
    p.add_argument("--balanced", action="store_true")
    p.add_argument("--combo", default=None, choices=combinations(),
                   help="fit the similarity on another training combination with the same "
                        "C_aff (cfw / csr share cabinet, tfr / tsw table): a w2e model's "
                        "affordance head trains on C_aff alone, so the combinations differ "
                        "only in the similarity (default: the model's own)")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.set_defaults(func=_run_calibrate)


def _run_calibrate(a: argparse.Namespace) -> int:
    import json

    import torch

    from w2e_ros.core.model.network import load_model, save_model
    from w2e_ros.core.model.training import (
        calibrate_similarity,
        load_training_data,
        method_categories,
        retarget,
    )

    torch.set_num_threads(a.threads)
    model, meta = load_model(a.model)
    if a.combo is not None:
        meta = retarget(meta, a.combo, source=a.model)
    method, combo = str(meta.get("method", "w2e")), str(meta.get("combo", "cfw"))
    aff_cats, sim_cats = method_categories(method, combo)
    if not sim_cats:
        if method != "where2act":
            raise ValueError(f"{a.model}: a {method} model has no similarity categories")
        # "wide": the affordance head knows every training category; the similarity is
        # fitted to where that head is right on them (no category is held out from it)
        sim_cats = aff_cats
    primitive = meta.get("primitive")
    if not primitive:
        raise ValueError(f"{a.model} does not name its primitive (not a w2e train checkpoint)")
    data = load_training_data(a.data, method, combo, primitive)
    stats = calibrate_similarity(model, data, sim_cats, a.steps, a.seed, balanced=a.balanced)
    stats["balanced"] = float(a.balanced)
    path = save_model(a.out, model, {**meta, "aff_categories": list(aff_cats),
                                     "sim_categories": list(sim_cats), "calibration": stats})
    print(f"{path}: {json.dumps({k: round(v, 4) for k, v in stats.items()})}")
    return 0


def _add_replay_pack(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay-pack", help="the ~1 %% of training interactions fine-tuning replays, small "
                            "enough to ship beside a checkpoint",
        description="Sample distinct training interactions (per primitive, with only their "
                    "clouds) into a collection directory the inference node's replay_data "
                    "takes; it replays all of a pack.")
    p.add_argument("--data", required=True, help="training collection (w2e collect --out)")
    p.add_argument("--model", required=True,
                   help="checkpoint whose method and combination pick the categories")
    p.add_argument("--primitives", nargs="+", default=["push", "pull"])
    p.add_argument("--fraction", type=float, default=0.01)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="directory (one shard is written)")
    p.set_defaults(func=_run_replay_pack)


def _run_replay_pack(a: argparse.Namespace) -> int:
    from pathlib import Path

    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.model.network import load_model
    from w2e_ros.core.model.training import replay_pack

    if not 0 < a.fraction <= 1:
        raise ValueError(f"--fraction must be in (0, 1], got {a.fraction}")
    _, meta = load_model(a.model, "cpu")
    pack = replay_pack(InteractionData.load(a.data), str(meta.get("method", "w2e")),
                       str(meta.get("combo", "cfw")), a.primitives, a.fraction, a.seed)
    out = Path(a.out)
    for old in out.glob("shard-*.npz"):
        old.unlink()
    path = pack.save_shard(out / "shard-00000.npz")
    print(f"{path}: {pack.num_interactions} interactions ({', '.join(a.primitives)}, "
          f"{pack.positive_rate():.0%} successful) on {pack.num_observations} clouds, "
          f"{path.stat().st_size / 1e6:.1f} MB")
    return 0


_FIT_TRAIN_SETTINGS = ("lr", "flip_share", "clouds", "per_cloud")
"""The TrainConfig settings ``w2e ceiling fit`` takes as flags."""


def _add_ceiling(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "ceiling", help="diagnose the model's ceiling: labels, a local oracle, a fit test",
        description="labels: replay stored valid trials as they were, with the contact moved "
                    "3 / 10 mm along the surface and the approach turned 5 / 15 deg, and "
                    "report the share of labels kept. oracle: score each trial by the success "
                    "rate of contacts around it (what a model that cannot place the contact "
                    "finer than r could know). fit: train a fresh model on ~2,000 "
                    "training interactions and report how well it ranks them (train AUROC).")
    cs = p.add_subparsers(dest="check", required=True)
    lab = cs.add_parser("labels", help="label smoothness of the simulator")
    add_arguments(lab, LabelCheckConfig)
    lab.set_defaults(func=_run_ceiling_labels)
    orc = cs.add_parser("oracle", help="how well the outcomes around a contact predict it")
    add_arguments(orc, OracleConfig)
    orc.set_defaults(func=_run_ceiling_oracle)
    fit = cs.add_parser("fit", help="can the network fit a small training set?")
    fit.add_argument("--data", required=True, help="training collection")
    fit.add_argument("--out", default="results/ceiling_fit")
    fit.add_argument("--primitive", default="pull", choices=["push", "pull"])
    fit.add_argument("--method", default="where2act", choices=["w2e", "where2act", "fulldata"])
    fit.add_argument("--combo", default="cfw", choices=combinations())
    fit.add_argument("--interactions", type=int, default=2000)
    fit.add_argument("--steps", type=int, default=1500)
    fit.add_argument("--eval-every", type=int, default=250)
    add_arguments(fit, TrainConfig, only=_FIT_TRAIN_SETTINGS)
    _add_network_args(fit)
    fit.add_argument("--frozen-encoder", default="", metavar="MODEL_PT|random",
                     help="fit only a fresh head, full batch, on the frozen features of this "
                          "checkpoint (or of random initial weights): representation vs "
                          "optimisation")
    fit.add_argument("--seed", type=int, default=0)
    fit.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    fit.set_defaults(func=_run_ceiling_fit)


def _run_ceiling_labels(a: argparse.Namespace) -> int:
    from w2e_ros.experiments.ceiling import label_smoothness, labels_table

    res = label_smoothness(from_namespace(LabelCheckConfig, a))
    print(labels_table(res))
    print(f"{res['seconds']:.0f} s; written to {a.out}/labels.json and labels.md")
    return 0


def _run_ceiling_oracle(a: argparse.Namespace) -> int:
    from w2e_ros.experiments.ceiling import local_oracle, oracle_table

    cfg = from_namespace(OracleConfig, a)
    res = local_oracle(cfg)
    print(oracle_table(res, cfg.radii))
    print(f"{res['seconds']:.0f} s; written to {a.out}/oracle.json and oracle.md")
    return 0


def _run_ceiling_fit(a: argparse.Namespace) -> int:
    import torch

    from w2e_ros.experiments.ceiling import FitTestConfig, fit_test

    torch.set_num_threads(a.threads)
    res = fit_test(FitTestConfig(
        data=a.data, out=a.out, primitive=a.primitive, method=a.method, combo=a.combo,
        interactions=a.interactions, steps=a.steps, eval_every=a.eval_every, seed=a.seed,
        train={k: getattr(a, k) for k in (*_FIT_TRAIN_SETTINGS, "threads")},
        model=_network_overrides(a), frozen_encoder=a.frozen_encoder))
    for r in res["curve"]:
        print(f"step {r['step']:>6}  loss {r['train_loss']:.4f}  train AUROC {r['auroc']:.4f}  "
              f"AP {r['ap']:.4f}  ({r['seconds']:.0f} s)")
    print(f"{res['interactions']} interactions on {res['observations']} clouds "
          f"({res['positives']} positive): train AUROC {res['final_auroc']:.4f}; "
          f"written to {a.out}/fit.json")
    return 0


VERBS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_collect, _add_train, _add_calibrate, _add_replay_pack, _add_learnability, _add_fewshot,
    _add_evaluate, _add_benchmark, _add_ceiling, _add_demo, _add_bringup, _add_record,
    _add_replay]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="w2e", description="Where2Explore: few-shot affordance learning (w2e_ros).")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for add in VERBS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    keep_freed_memory()  # the verbs that run the network page-fault without it (allocator.py)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError) as exc:  # bad input: a clear message, no trace
        logging.getLogger("w2e").debug("details", exc_info=True)
        print(f"w2e {args.verb}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
