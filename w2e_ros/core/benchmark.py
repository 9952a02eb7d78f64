"""``w2e benchmark``: methods x budgets x primitives, over combinations and seeds (paper Tab. 1-3).

Methods (model kind, exploration strategy):
  none (w2e, none) - random (w2e, random) - nosim (w2e, where2act rule) -
  similarity (w2e, lowest similarity) - where2act (where2act baseline, its rule) -
  fulldata (fulldata baseline, none).
Every exploring method runs ONCE per (combination, seed, primitive) up to the largest budget
and is evaluated from its snapshots at each budget. Metrics per novel category: F-score on
the held-out test interactions, sample success in the simulator on test objects (the same
candidate actions for every method). Written to ``--out``: ``rows.jsonl`` (one per value),
``tables.md`` (mean +- std), ``metrics_vs_budget.png`` and heatmap PNGs.
"""

from __future__ import annotations

import json
import logging
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from w2e_ros.core.categories import load_categories
from w2e_ros.core.config import ExploreConfig
from w2e_ros.core.data import InteractionData
from w2e_ros.core.evaluate import (
    SuccessProbe,
    evaluation_instances,
    evaluation_targets,
    predict_interactions,
)
from w2e_ros.core.explore import fewshot
from w2e_ros.core.metrics import fscore, mean_std
from w2e_ros.core.model import W2EModel, load_model
from w2e_ros.core.strategies import get_strategy

log = logging.getLogger("w2e.benchmark")

METHOD_SPEC: dict[str, tuple[str, str]] = {
    "none": ("w2e", "none"),
    "random": ("w2e", "random"),
    "where2act": ("where2act", "where2act"),
    "nosim": ("w2e", "nosim"),
    "similarity": ("w2e", "similarity"),
    "fulldata": ("fulldata", "none"),
}


@dataclass
class BenchmarkConfig:
    runs_dir: str = "runs"  # holds <kind>_<combo>_<primitive>/model.pt from `w2e train`
    train_data: str | None = None  # replay during fine-tuning
    test_data: str | None = None  # test-split collection for the F-score
    out: str = "results/benchmark"
    combos: tuple[str, ...] = ("cfw", "csr", "tfr", "tsw")
    seeds: tuple[int, ...] = (0,)
    primitives: tuple[str, ...] = ("push", "pull")
    methods: tuple[str, ...] = tuple(METHOD_SPEC)
    budgets: tuple[int, ...] = (1, 2, 5)
    mode: str = "all"  # all | per-category
    categories: tuple[str, ...] | None = None  # restrict the novel categories (reduced runs)
    explore_objects: int = 10  # explore instances per category
    test_objects: int = 10  # test objects per category for sample success (0: skip)
    validate: bool = False  # judge on held-out EXPLORE instances instead of the test split
    eval_points: int = 256
    eval_dirs: int = 8
    heatmaps: bool = True
    explore: ExploreConfig = field(default_factory=ExploreConfig)


def find_checkpoint(runs_dir: str | Path, kind: str, combo: str, primitive: str) -> Path | None:
    """``runs/<kind>_<combo>_<primitive>/model.pt``; Full-data does not depend on the
    combination, so any ``fulldata_*_<primitive>`` run serves."""
    runs = Path(runs_dir)
    p = runs / f"{kind}_{combo}_{primitive}" / "model.pt"
    if p.exists():
        return p
    if kind == "fulldata":
        found = sorted(runs.glob(f"fulldata_*_{primitive}/model.pt"))
        return found[0] if found else None
    return None


class _Evaluator:
    """Per-category test interactions and success probes of one (combination, primitive)."""

    def __init__(self, cfg: BenchmarkConfig, world: Any, cats: list[str], primitive: str,
                 test: InteractionData | None) -> None:
        self.cats = cats
        self.test = {c: test.select(categories=[c]) for c in cats} if test is not None else {}
        self.probes = {}
        if cfg.test_objects > 0:
            self.probes = {c: SuccessProbe(world, evaluation_targets(
                [c], cfg.test_objects, validate=cfg.validate, explored=cfg.explore_objects),
                primitive, cfg.eval_points, cfg.eval_dirs)
                           for c in cats}

    def category(self, model: W2EModel, c: str) -> dict[str, Any]:
        out: dict[str, Any] = {}
        t = self.test.get(c)
        if t is not None and t.num_interactions:
            aff, _ = predict_interactions(model, t)
            out["counts"] = fscore(aff > 0.5, t.success)
        if c in self.probes:
            out["success"] = self.probes[c].run(model)[c]
        return out


def _pool(per_cat: dict[str, dict[str, Any]]) -> dict[str, float]:
    """F-score from pooled counts and success over all objects, across categories."""
    out: dict[str, float] = {}
    counts = [v["counts"] for v in per_cat.values() if "counts" in v]
    if counts:
        tp, fp, fn = (sum(c[k] for c in counts) for k in ("tp", "fp", "fn"))
        p = tp / (tp + fp) if tp + fp else 0.0
        r = tp / (tp + fn) if tp + fn else 0.0
        out["fscore"] = 2 * p * r / (p + r) if p + r else 0.0
    succ = [v["success"] for v in per_cat.values() if "success" in v]
    if succ:
        out["success"] = float(np.mean(succ))  # equal objects per category: = pooled rate
    return out


def run_benchmark(cfg: BenchmarkConfig, world: Any | None = None) -> dict:
    """Run everything the config asks for; returns the summary (also written to disk)."""
    from w2e_ros.core.sim_world import SimWorld

    cats_cfg = load_categories()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(asdict(cfg), indent=1, default=str))
    world = world or SimWorld()
    train_all = InteractionData.load(cfg.train_data) if cfg.train_data else None
    test_all = InteractionData.load(cfg.test_data) if cfg.test_data else None
    rows: list[dict] = []
    rows_f = (out / "rows.jsonl").open("w")
    max_budget = max(cfg.budgets)
    heat_done: set[str] = set()
    t_start = time.perf_counter()
    for prim in cfg.primitives:
        for combo in cfg.combos:
            novel = cats_cfg.novel(combo)
            if cfg.categories:
                novel = [c for c in novel if c in cfg.categories]
            test = None
            if test_all is not None:
                test = InteractionData.concat([test_all.select(
                    primitive=prim, categories=[c],
                    instances=evaluation_instances(c, cfg.validate, cfg.explore_objects))
                    for c in novel])
            ev = _Evaluator(cfg, world, novel, prim, test)
            for seed in cfg.seeds:
                for method in cfg.methods:
                    kind, strat_name = METHOD_SPEC[method]
                    ckpt = find_checkpoint(cfg.runs_dir, kind, combo, prim)
                    if ckpt is None:
                        log.warning("skip %s %s %s: no %s checkpoint in %s (w2e train --method "
                                    "%s --combo %s --primitive %s)", method, combo, prim, kind,
                                    cfg.runs_dir, kind, combo, prim)
                        continue
                    t0 = time.perf_counter()
                    torch.manual_seed(seed)
                    model, meta = load_model(ckpt)
                    strategy = get_strategy(strat_name)
                    ecfg = ExploreConfig(**{**asdict(cfg.explore), "budget": max_budget,
                                            "snapshot_budgets": tuple(cfg.budgets),
                                            "seed": seed})
                    replay = None
                    if train_all is not None and strategy.explores:
                        tc = list(dict.fromkeys(meta.get("aff_categories", []) +
                                                meta.get("sim_categories", [])))
                        replay = train_all.select(primitive=prim, categories=tc)
                    # per category: {budget: model}
                    models: dict[str, dict[int, W2EModel]] = {}
                    explored: dict[str, list] = {}
                    if strategy.explores:
                        runs = fewshot(model, meta, world, novel, strategy, ecfg, prim, replay,
                                       cfg.mode, cfg.explore_objects)
                        for group, (res, explorer) in runs.items():
                            snaps = {b: explorer.model_at(res.snapshots[b])
                                     for b in (0, *cfg.budgets)}
                            for c in (novel if group == "all" else [group]):
                                models[c] = snaps
                                explored[c] = [asdict(s) for s in res.steps]
                    else:
                        models = {c: {b: model for b in (0, *cfg.budgets)} for c in novel}
                    for b in cfg.budgets:
                        per_cat = {c: ev.category(models[c][b], c) for c in novel}
                        pooled = _pool(per_cat)
                        base = {"primitive": prim, "combo": combo, "seed": seed,
                                "method": method, "budget": b}
                        for c, v in [*per_cat.items(), ("all", pooled)]:
                            for metric in ("fscore", "success"):
                                val = v.get(metric, v.get("counts", {}).get(metric))
                                if val is None:
                                    continue
                                row = {**base, "category": c, "metric": metric,
                                       "value": float(val)}
                                rows.append(row)
                                rows_f.write(json.dumps(row) + "\n")
                        rows_f.flush()
                    log.info("%s %s %s seed %d done in %.0f s", prim, combo, method, seed,
                             time.perf_counter() - t0)
                    if explored:
                        (out / f"explored_{prim}_{combo}_{method}_s{seed}.json").write_text(
                            json.dumps(explored, indent=1))
                    if cfg.heatmaps and method == "similarity" and prim not in heat_done:
                        _heatmaps(out, prim, combo, world, novel, models, cfg)
                        heat_done.add(prim)
    rows_f.close()
    summary = summarize(rows, cfg)
    log.info("benchmark done in %.0f s: %s", time.perf_counter() - t_start, out)
    return summary


def _heatmaps(out: Path, prim: str, combo: str, world: Any, cats: list[str],
              models: dict[str, dict[int, W2EModel]], cfg: BenchmarkConfig) -> None:
    from w2e_ros.core.viz import heatmap_figure, normal_maps

    for c in cats[:3]:
        target = evaluation_targets([c], 1, validate=cfg.validate,
                                    explored=cfg.explore_objects)[0]
        cloud = world.observe(target)
        before, after = models[c][0], models[c][max(models[c])]
        a0, s0 = normal_maps(before, cloud.points, cloud.normals)
        a1, s1 = normal_maps(after, cloud.points, cloud.normals)
        heatmap_figure(cloud.points, {"affordance before": a0, "similarity before": s0,
                                      f"affordance after {max(models[c])}": a1,
                                      f"similarity after {max(models[c])}": s1,
                                      "movable (truth)": cloud.movable.astype(float)},
                       out / f"heatmap_{prim}_{combo}_{c}.png",
                       title=f"{prim} on unseen {target.name} (similarity exploration)",
                       camera_pose=getattr(cloud, "camera_pose", None))


def summarize(rows: list[dict], cfg: BenchmarkConfig) -> dict:
    """Mean +- std over combinations x seeds; markdown tables and the curves plot."""
    from w2e_ros.core.viz import metric_curves

    out = Path(cfg.out)
    groups: dict[tuple, list[float]] = defaultdict(list)
    for r in rows:
        groups[(r["primitive"], r["method"], r["budget"], r["metric"], r["category"])].append(
            r["value"])
    stats = {k: mean_std(v) for k, v in groups.items()}
    overall = {k[:4]: v for k, v in stats.items() if k[4] == "all"}
    lines = ["# Benchmark", "",
             f"Mean +- std over combinations {', '.join(cfg.combos)} x seeds "
             f"{', '.join(map(str, cfg.seeds))}; budgets {' / '.join(map(str, cfg.budgets))}; "
             f"mode {cfg.mode}; {cfg.explore_objects} explore and {cfg.test_objects} test "
             "objects per category. Values in %."
             + (" VALIDATION: judged on held-out explore instances, not the test split."
                if cfg.validate else ""), ""]
    cols = [(m, p) for m in ("fscore", "success") for p in cfg.primitives]
    names = {"fscore": "F-score", "success": "sample success"}
    lines.append("| method | " + " | ".join(f"{names[m]} {p}" for m, p in cols) + " |")
    lines.append("|---" * (len(cols) + 1) + "|")
    for method in cfg.methods:
        cells = []
        for m, p in cols:
            vals = [overall.get((p, method, b, m)) for b in cfg.budgets]
            cells.append(" / ".join(f"{100 * v[0]:.1f}±{100 * v[1]:.1f}" if v else "-"
                                    for v in vals))
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    b = max(cfg.budgets)
    cats = sorted({k[4] for k in stats if k[4] != "all"})
    for m in ("fscore", "success"):
        for p in cfg.primitives:
            lines += ["", f"## {names[m]}, {p}, per category (budget {b})", "",
                      "| method | " + " | ".join(cats) + " |", "|---" * (len(cats) + 1) + "|"]
            for method in cfg.methods:
                cells = [stats.get((p, method, b, m, c)) for c in cats]
                lines.append(f"| {method} | " + " | ".join(
                    f"{100 * v[0]:.1f}" if v else "-" for v in cells) + " |")
    (out / "tables.md").write_text("\n".join(lines) + "\n")
    if overall:
        metric_curves(overall, cfg.methods, cfg.budgets, out / "metrics_vs_budget.png")
    summary = {"|".join(map(str, k)): {"mean": v[0], "std": v[1]} for k, v in stats.items()}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary
