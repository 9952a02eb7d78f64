"""``w2e benchmark``: methods x budgets x primitives over combinations and seeds (paper Tab. 1-3).

Methods (model kind, exploration strategy):
  none (w2e, none) - random (w2e, random) - nosim (w2e, where2act rule) -
  similarity (w2e, lowest similarity) - oracle (w2e, hindsight: most wrong first) -
  where2act (where2act baseline, its rule) - fulldata (fulldata baseline, none).
Every exploring method runs ONCE per (combination, seed, primitive) up to the largest budget
and is evaluated from its snapshots at each budget (budget 0: before exploring). On the
held-out test interactions: F-score at 0.5, AUROC, average precision, and the similarity's
AUROC for "the prediction is right"; in the simulator: sample success of the best action on
each test object (the same candidates for every method).

Uncertainty: every metric is a mean over seeds with a 95 % bootstrap interval that resamples
test observations (clouds, not rows: rows of one cloud are not independent) or test objects,
and seeds; differences against ``random`` and ``none`` are PAIRED (the same resample for both
methods). Written to ``--out``: ``benchmark.json`` (combination, method, primitive, budget,
metric -> mean, ci_low, ci_high, n_seeds, plus the paired differences), ``predictions_*.npz``
(every prediction, so the statistics can be recomputed), ``tables.md``,
``metrics_vs_budget.png`` and heatmaps.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.exploration.config import SETTINGS_RENAMED, ExploreConfig
from w2e_ros.core.exploration.evaluate import (
    SuccessProbe,
    evaluation_targets,
    predict_interactions,
)
from w2e_ros.core.exploration.explore import fewshot
from w2e_ros.core.exploration.strategies import get_strategy, registry
from w2e_ros.core.infra.settings import flatten, nest
from w2e_ros.core.model.metrics import auroc, average_precision, fscore, r_precision
from w2e_ros.core.model.network import W2EModel, load_model
from w2e_ros.core.model.training import replay_data
from w2e_ros.experiments.backends import Backend, LocalBackend, resolve
from w2e_ros.experiments.config import BENCHMARK_DROPPED, BENCHMARK_RENAMED, BenchmarkConfig

log = logging.getLogger("w2e.benchmark")

METHOD_SPEC: dict[str, tuple[str, str]] = {
    # method -> (trained model kind, strategy): every strategy with our model, the Where2Act
    # baseline with its own rule, and Full-data (novel categories in training) unexplored
    **{name: ("w2e", name) for name in registry(experimental=True)},
    "where2act": ("where2act", "where2act"),
    "fulldata": ("fulldata", "none"),
}
REFERENCES = ("random", "none")  # paired differences are reported against these
# precision and recall at the same 0.5 threshold say which side of the F-score moved, and
# "called" how many test interactions the fit puts above 0.5;
# R-precision is the F-score at the threshold that predicts as many successes as there are
# (the ranking alone: a fit that only shifts the predictions across 0.5 does not move it)
METRICS = ("fscore", "precision", "recall", "called", "rprecision", "auroc", "ap",
           "simcorr_auroc", "success")


def find_checkpoint(runs_dir: str | Path, kind: str, combo: str, primitive: str) -> Path | None:
    """``runs/<kind>_<combo>_<primitive>/model.pt`` (w2e train's runs) or
    ``runs/<kind>_<combo>_<primitive>.pt`` (the shipped ``checkpoints/``); Full-data does not
    depend on the combination, so any ``fulldata_*_<primitive>`` model serves."""
    runs = Path(runs_dir)
    for p in (runs / f"{kind}_{combo}_{primitive}" / "model.pt",
              runs / f"{kind}_{combo}_{primitive}.pt"):
        if p.exists():
            return p
    if kind == "fulldata":
        found = sorted([*runs.glob(f"fulldata_*_{primitive}/model.pt"),
                        *runs.glob(f"fulldata_*_{primitive}.pt")])
        return found[0] if found else None
    return None


class _Evaluator:
    """Test interactions and the success probe of one (combination, primitive)."""

    def __init__(self, cfg: BenchmarkConfig, world: Any, cats: list[str], primitive: str,
                 test: InteractionData | None) -> None:
        self.cats, self.test = cats, test
        self.probe = None
        if cfg.test_objects > 0:
            self.probe = SuccessProbe(world, evaluation_targets(
                cats, cfg.test_objects, validate=cfg.validate, explored=cfg.explore_objects),
                primitive, cfg.eval_points, cfg.eval_dirs,
                use_mask=cfg.explore.use_mask, sampler=cfg.probe,
                check_approach=cfg.explore.check_approach)

    def predict(self, model: W2EModel) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {}
        if self.test is not None and self.test.num_interactions:
            out["aff"], out["sim"] = predict_interactions(model, self.test)
        if self.probe is not None:
            oc = self.probe.outcomes(model)
            out["success"] = np.array([o[0] for o in oc])
            out["valid"] = np.array([o[1] for o in oc])
        return out


def run_benchmark(cfg: BenchmarkConfig, world: Any | None = None,
                  backend: Backend | None = None) -> dict:
    """Run everything the config asks for; returns the summary (also written to disk).

    Every (primitive, combination, seed, method) run is one job of ``backend`` (default:
    one after the other in this process). The collections go to the jobs through
    ``backend.put`` (Ray: the object store, once per host); checkpoints are read from
    ``cfg.runs``, which must be the same path on every host. Results come back here and
    every file is written by this process."""
    from w2e_ros.experiments.sim_world import SimWorld

    backend = backend or LocalBackend(1)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(asdict(cfg), indent=1, default=str))
    world = world or SimWorld()
    train_all = InteractionData.load(cfg.train_data) if cfg.train_data else None
    test_all = InteractionData.load(cfg.test_data) if cfg.test_data else None
    _GROUPS.clear()  # this process's jobs use the caller's world
    groups = {(p, c): _group(cfg, p, c, test_all, world)
              for p in cfg.primitives for c in cfg.combos}
    train_h, test_h = backend.put(train_all), backend.put(test_all)
    jobs = [_Run(cfg, p, c, s, m, train_h, test_h) for p in cfg.primitives
            for c in cfg.combos for s in cfg.seeds for m in cfg.methods]
    preds: dict[tuple[str, str], dict[str, np.ndarray]] = {k: {} for k in groups}
    explored: dict[tuple[str, str], dict[str, Any]] = {k: {} for k in groups}
    heat_done: set[str] = set()
    t_start, done = time.perf_counter(), 0
    log.info("%d runs on the %s backend (%d at a time)", len(jobs), backend.name,
             backend.parallelism)
    with contextlib.closing(backend.map(_run_one, jobs)) as results:
        for i, res in results:
            run, done = jobs[i], done + 1
            prim, combo, key = run.primitive, run.combo, (run.primitive, run.combo)
            if "skipped" in res:
                log.warning(res["skipped"])
                continue
            preds[key].update(res["preds"])
            explored[key].update(res["explored"])
            elapsed = time.perf_counter() - t_start
            log.info("[%d/%d] %s %s %s seed %d done in %.0f s (eta %.0f s)", done, len(jobs),
                     prim, combo, run.method, run.seed, res["seconds"],
                     elapsed / done * (len(jobs) - done))
            _save_predictions(out / f"predictions_{combo}_{prim}.npz", preds[key],
                              groups[key][2])
            (out / f"explored_{combo}_{prim}.json").write_text(json.dumps(explored[key]))
            if res.get("heat") and prim not in heat_done:  # the first similarity run to end
                _heatmaps(out, prim, combo, world, groups[key][1], res["heat"], cfg)
                heat_done.add(prim)
    summary = summarize(out, cfg)
    log.info("benchmark done in %.0f s: %s", time.perf_counter() - t_start, out)
    return summary


@dataclass
class _Run:
    """One (primitive, combination, seed, method) run: a backend job. ``train`` / ``test``
    are ``Backend.put`` handles of the collections (or None)."""

    cfg: BenchmarkConfig
    primitive: str
    combo: str
    seed: int
    method: str
    train: Any
    test: Any


# (config, primitive, combination) -> (world, novel categories, evaluator), per process: a
# worker builds them once and keeps them for the next runs of the same group
_GROUPS: dict[tuple[str, str, str], tuple[Any, list[str], _Evaluator]] = {}
_WORKER_WORLD: Any = None


def _group(cfg: BenchmarkConfig, prim: str, combo: str, test_all: InteractionData | None,
           world: Any | None = None) -> tuple[Any, list[str], _Evaluator]:
    """The world, novel categories and evaluator of one (primitive, combination)."""
    global _WORKER_WORLD
    key = (json.dumps(asdict(cfg), default=str), prim, combo)
    if key not in _GROUPS:
        if world is None:
            from w2e_ros.experiments.sim_world import SimWorld

            _WORKER_WORLD = _WORKER_WORLD or SimWorld()
            world = _WORKER_WORLD
        novel = load_categories().novel(combo)
        if cfg.categories:
            novel = [c for c in novel if c in cfg.categories]
        test = None
        if test_all is not None:
            test = InteractionData.concat([test_all.select(
                primitive=prim, categories=[c],
                instances=load_categories().evaluation_instances(c, cfg.validate,
                                                                 cfg.explore_objects))
                for c in novel])
        _GROUPS[key] = (world, novel, _Evaluator(cfg, world, novel, prim, test))
    return _GROUPS[key]


def _run_one(run: _Run) -> dict[str, Any]:
    """Explore with one method and judge its snapshots: the predictions, the exploration
    log and, for the similarity method, the models the heatmaps show."""
    cfg, prim, combo, seed, method = run.cfg, run.primitive, run.combo, run.seed, run.method
    world, novel, ev = _group(cfg, prim, combo, resolve(run.test))
    max_budget = max(cfg.budgets)
    kind, strat_name = METHOD_SPEC[method]
    ckpt = find_checkpoint(cfg.runs, kind, combo, prim)
    if ckpt is None:
        return {"skipped": f"skip {method} {combo} {prim}: no {kind} checkpoint in "
                           f"{cfg.runs} (w2e train --method {kind} --combo {combo} "
                           f"--primitive {prim})"}
    t0 = time.perf_counter()
    torch.manual_seed(seed)
    model, meta = load_model(ckpt)
    strategy = get_strategy(strat_name, experimental=True)
    ecfg = replace(cfg.explore, budget=max_budget, snapshot_budgets=tuple(cfg.budgets),
                   seed=seed)
    train_all = resolve(run.train)
    replay = None
    if train_all is not None and strategy.explores:
        replay = replay_data(train_all, meta, prim)
    models: dict[str, dict[int, W2EModel]] = {}
    explored_log: dict[str, Any] = {}
    if strategy.explores:
        runs = fewshot(model, meta, world, novel, strategy, ecfg, prim, replay,
                       cfg.mode, cfg.explore_objects)
        for group, (res, explorer) in runs.items():
            snaps = {b: explorer.model_at(res.snapshots[b]) for b in (0, *cfg.budgets)}
            for c in (novel if group == "all" else [group]):
                models[c] = snaps
            explored_log[f"{method}_s{seed}_{group}"] = {
                "stopped": res.stopped, "steps": [asdict(x) for x in res.steps],
                "mean_similarity": res.mean_similarity, "fit": explorer.fit_log}
    else:
        models = {c: {b: model for b in (0, *cfg.budgets)} for c in novel}
    preds: dict[str, np.ndarray] = {}
    for b in (0, *cfg.budgets):
        if cfg.mode == "all":
            p = ev.predict(models[novel[0]][b])
        else:  # each category judged with its own adapted model
            p = _merge_per_category(ev, models, b, novel)
        for k, v in p.items():
            preds[f"{method}|{seed}|{b}|{k}"] = v
    heat = None
    if cfg.heatmaps and method == "similarity":
        heat = {c: {0: models[c][0], max_budget: models[c][max_budget]} for c in novel[:3]}
    return {"preds": preds, "explored": explored_log, "heat": heat,
            "seconds": time.perf_counter() - t0}


def _merge_per_category(ev: _Evaluator, models: dict[str, dict[int, W2EModel]], b: int,
                        cats: list[str]) -> dict[str, np.ndarray]:
    """Per-category mode: every category's rows / objects predicted by its own model."""
    merged: dict[str, np.ndarray] = {}
    for c in cats:
        p = ev.predict(models[c][b])
        for k, v in p.items():
            if k in ("aff", "sim"):
                mask = ev.test.interaction_category == c
            else:
                mask = np.array([t.category == c for t in ev.probe.targets])
            merged.setdefault(k, np.zeros_like(v))[mask] = v[mask]
    return merged


def _save_predictions(path: Path, preds: dict[str, np.ndarray], ev: _Evaluator) -> None:
    arrays = {f"pred:{k}": v for k, v in preds.items()}
    if ev.test is not None:
        arrays["test:success"] = ev.test.success
        arrays["test:valid"] = ev.test.valid
        arrays["test:obs"] = ev.test.obs_index
        arrays["test:category"] = ev.test.interaction_category.astype(str)
    if ev.probe is not None:
        arrays["probe:category"] = np.array([t.category for t in ev.probe.targets], str)
    np.savez_compressed(path, **arrays)


def merge_predictions(out: str | Path, sources: list[str | Path]) -> list[Path]:
    """Copy the runs of other benchmark outputs (the same test set, other methods or seeds,
    run in other processes or on other machines) into ``out``'s predictions files, so one
    ``summarize`` pairs them all. A run present twice must have identical predictions (runs
    are deterministic: the same run made twice); a run that differs, or a different test
    set, is an error and nothing is written. A source ``DIR:METHOD,...`` contributes only
    those methods' runs (e.g. a rerun of one method with another setting beside the rest)."""
    if not sources:
        return []
    out = Path(out)
    merged: dict[str, dict[str, np.ndarray]] = {}
    for src in [str(out), *map(str, sources)]:
        src, _, only = src.partition(":")
        keep = set(only.split(",")) if only else None
        for path in sorted(Path(src).glob("predictions_*.npz")):
            with np.load(path) as z:
                arrays = {k: z[k] for k in z.files if keep is None or not k.startswith("pred:")
                          or k[5:].split("|")[0] in keep}
            into = merged.setdefault(path.name, {})
            for k, v in arrays.items():
                if k in into and not np.array_equal(into[k], v):
                    raise ValueError(
                        f"{path}: run {k[5:]} is also in another source, with other "
                        "predictions" if k.startswith("pred:") else
                        f"{path}: {k} differs from the other sources' (another test set)")
                into[k] = v
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, arrays in merged.items():
        np.savez_compressed(out / name, **arrays)
        written.append(out / name)
    return written


def _heatmaps(out: Path, prim: str, combo: str, world: Any, cats: list[str],
              models: dict[str, dict[int, W2EModel]], cfg: BenchmarkConfig) -> None:
    from w2e_ros.core.model.viz import heatmap_figure, normal_maps

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


def _metric(name: str, p: dict[str, np.ndarray], y: np.ndarray, rows: np.ndarray,
            objs: np.ndarray) -> float:
    if name == "success":
        return float(np.mean(p["success"][objs])) if "success" in p else float("nan")
    if "aff" not in p:
        return float("nan")
    a = p["aff"][rows]
    if name in ("fscore", "precision", "recall"):
        return fscore(a > 0.5, y[rows])[name]
    if name == "auroc":
        return auroc(a, y[rows])
    if name == "ap":
        return average_precision(a, y[rows])
    if name == "called":  # the share of test interactions predicted to succeed
        return float(np.mean(a > 0.5))
    if name == "rprecision":
        return r_precision(a, y[rows])
    if name == "simcorr_auroc":
        return auroc(p["sim"][rows], (a > 0.5) == y[rows])
    raise ValueError(name)


def _stats(path: Path, cfg: BenchmarkConfig, rng: np.random.Generator) -> list[dict]:
    """Means and paired bootstrap intervals of one (combination, primitive) file."""
    z = np.load(path)
    preds: dict[tuple[str, int, int], dict[str, np.ndarray]] = defaultdict(dict)
    for k in z.files:
        if k.startswith("pred:"):
            method, seed, b, what = k[5:].split("|")
            preds[(method, int(seed), int(b))][what] = z[k]
    y = z["test:success"] if "test:success" in z.files else np.zeros(0, bool)
    obs = z["test:obs"] if "test:obs" in z.files else np.zeros(0, int)
    n_obj = len(z["probe:category"]) if "probe:category" in z.files else 0
    members = [np.flatnonzero(obs == o) for o in np.unique(obs)]
    combo, prim = path.stem.split("_")[1:3]
    methods = [m for m in cfg.methods if any(k[0] == m for k in preds)]
    seeds = sorted({k[1] for k in preds})
    budgets = (0, *cfg.budgets)
    all_rows, all_objs = np.arange(len(y)), np.arange(n_obj)

    def value(method: str, b: int, metric: str, rows: np.ndarray, objs: np.ndarray,
              seed_pick: list[int]) -> float:
        vals = [_metric(metric, preds[(method, s, b)], y, rows, objs) for s in seed_pick
                if (method, s, b) in preds]
        return float(np.nanmean(vals)) if vals and np.isfinite(vals).any() else float("nan")

    boots = []
    for _ in range(cfg.bootstrap):
        pick = rng.integers(len(members), size=len(members)) if members else np.zeros(0, int)
        rows = np.concatenate([members[i] for i in pick]) if len(pick) else all_rows
        objs = rng.integers(n_obj, size=n_obj) if n_obj else all_objs
        boots.append((rows, objs, list(rng.choice(seeds, size=len(seeds)))))
    cache: dict[tuple[str, int, str], tuple[float, np.ndarray]] = {}

    def stats(method: str, b: int, metric: str) -> tuple[float, np.ndarray]:
        """Point value and bootstrap values, computed once (the references are paired with
        every method on the same resamples)."""
        key = (method, b, metric)
        if key not in cache:
            cache[key] = (value(method, b, metric, all_rows, all_objs, seeds),
                          np.array([value(method, b, metric, r, o, sp) for r, o, sp in boots]))
        return cache[key]

    out = []
    for metric in METRICS:
        for method in methods:
            for b in budgets:
                point, bs = stats(method, b, metric)
                if not np.isfinite(point):
                    continue
                n_seeds = sum((method, sd, b) in preds for sd in seeds)
                base = {"combination": combo, "primitive": prim, "method": method,
                        "budget": b, "metric": metric, "n_seeds": n_seeds}
                out.append({**base, "mean": point, **_ci(bs), DRAWS: bs})
                for ref in REFERENCES:
                    if ref == method or ref not in methods:
                        continue
                    ref_point, ref_bs = stats(ref, b, metric)
                    out.append({**base, "vs": ref, "mean": point - ref_point,
                                **_ci(bs - ref_bs), DRAWS: bs - ref_bs})
    return out


DRAWS = "_draws"  # a row's bootstrap values while summarizing; never written


def mean_over_combinations(rows: list[dict], combos: list[str]) -> list[dict]:
    """Rows of the mean over ``combos`` for every (primitive, method, budget, metric, vs)
    that all of them report.

    The combinations are independent experiments, so the i-th bootstrap draw of each is
    averaged into the i-th draw of the mean and the interval is taken from those
    (``ci: bootstrap``). A combination known only from an earlier summary has no draws; the
    mean then adds the members' intervals as independent normal errors, the half-width
    sqrt(sum h_i^2) / k from each member's half-width h_i (``ci: normal``)."""
    groups: dict[tuple, dict[str, dict]] = defaultdict(dict)
    for r in rows:
        if r["combination"] in combos:
            groups[(r["primitive"], r["method"], r["budget"], r["metric"],
                    r.get("vs"))][r["combination"]] = r
    out = []
    for (prim, method, b, metric, vs), members in groups.items():
        if len(members) != len(combos):
            continue
        rs = [members[c] for c in combos]
        mean = float(np.mean([r["mean"] for r in rs]))
        draws = [r.get(DRAWS) for r in rs]
        if all(d is not None for d in draws) and len({len(d) for d in draws}) == 1:
            ci, how = _ci(np.mean(draws, axis=0)), "bootstrap"
        else:
            half = np.sqrt(np.sum([((r["ci_high"] - r["ci_low"]) / 2) ** 2 for r in rs]))
            ci, how = {"ci_low": mean - half / len(rs), "ci_high": mean + half / len(rs)}, \
                "normal"
        out.append({"combination": "mean", "primitive": prim, "method": method, "budget": b,
                    "metric": metric, "n_seeds": min(r["n_seeds"] for r in rs),
                    **({"vs": vs} if vs else {}), "mean": mean, **ci, "ci": how,
                    "combinations": list(combos)})
    return out


def _ci(samples: np.ndarray) -> dict[str, float]:
    s = samples[np.isfinite(samples)]
    if not len(s):
        return {"ci_low": float("nan"), "ci_high": float("nan")}
    lo, hi = np.percentile(s, [2.5, 97.5])
    return {"ci_low": float(lo), "ci_high": float(hi)}


def _merge_configs(configs: dict[str, dict]) -> dict:
    """One configuration for runs made by several calls: a setting they share as it is, lists
    (methods, seeds, ...) as their union in order of appearance, nested settings key by key,
    and a setting they disagree on as ``{"differs": {run directory: value}}``."""
    keys = list(dict.fromkeys(k for c in configs.values() for k in c))
    out: dict = {}
    for k in keys:
        vals = {d: c.get(k) for d, c in configs.items()}
        distinct = list({json.dumps(v, sort_keys=True) for v in vals.values()})
        if len(distinct) == 1:
            out[k] = next(iter(vals.values()))
        elif all(isinstance(v, list) for v in vals.values()):
            union = {json.dumps(x): x for v in vals.values() for x in v}
            out[k] = list(union.values())
        elif all(isinstance(v, dict) for v in vals.values()):
            out[k] = _merge_configs(vals)
        else:
            out[k] = {"differs": vals}
    return out


def run_configs(out: str | Path, sources: Sequence[str | Path] = ()) -> dict[str, dict]:
    """The ``config.json`` each benchmark run directory was made with (``out`` and the
    ``--merge`` sources, ``DIR:METHOD,...`` read as DIR), by directory."""
    found: dict[str, dict] = {}
    for src in [str(out), *map(str, sources)]:
        d = Path(src.partition(":")[0])
        if (d / "config.json").exists():
            found[str(d)] = _current_names(json.loads((d / "config.json").read_text()))
    return found


def _current_names(made: dict) -> dict:
    """A stored run configuration under today's setting names (BENCHMARK_RENAMED,
    SETTINGS_RENAMED) and nesting, so runs made before a rename or the fine-tuning settings'
    split merge into one setting."""
    out = {BENCHMARK_RENAMED.get(k, k): v for k, v in made.items()
           if k not in BENCHMARK_DROPPED}
    if isinstance(out.get("explore"), dict):  # flat before the fine-tuning settings nested
        flat = flatten(out["explore"], ExploreConfig)
        out["explore"] = nest({SETTINGS_RENAMED.get(k, k): v for k, v in flat.items()},
                              ExploreConfig)
    return out


def summarize(out: str | Path, cfg: BenchmarkConfig,
              include: list[str | Path] = (), sources: Sequence[str | Path] = ()) -> dict:
    """Statistics of every predictions file in ``out``: benchmark.json, tables.md, curves.

    ``include``: earlier benchmark.json files whose combinations' rows are taken as they
    are (their predictions files are elsewhere or gone); a (combination, primitive, method)
    present both there and in ``out`` is refused rather than counted twice, so a new method
    can join a combination whose other runs are known only from the summary (it then has no
    paired rows against them). With more than one combination,
    rows ``combination: mean`` hold the mean over them (:func:`mean_over_combinations`)."""
    from w2e_ros.core.model.viz import metric_curves

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)  # a table of included summaries alone is new
    rng = np.random.default_rng(0)
    rows: list[dict] = []
    for path in sorted(out.glob("predictions_*.npz")):
        rows += _stats(path, cfg, rng)
    def run(r: dict) -> tuple[str, str, str]:
        return r["combination"], r["primitive"], r["method"]

    own = {run(r) for r in rows}
    included = []  # where the included rows come from and the seeds they were made with
    made = run_configs(out, sources)  # what every run was made with, the included ones too
    for src in include:
        src_doc = json.loads(Path(src).read_text())
        # each run's own record where the summary kept them (its config is already a merge)
        made.update({d: _current_names(c) for d, c in src_doc.get("run_configs", {}).items()}
                    or ({str(src): _current_names(src_doc["config"])}
                        if src_doc.get("config") else {}))
        taken = [r for r in src_doc["rows"] if r["combination"] != "mean"]
        included.append({"source": str(src), "seeds": src_doc.get("config", {}).get("seeds"),
                         "combinations": sorted({r["combination"] for r in taken}),
                         "primitives": sorted({r["primitive"] for r in taken})})
        twice = own & {run(r) for r in taken}
        if twice:
            raise ValueError(f"{src}: {', '.join(sorted(' '.join(t) for t in twice))} also "
                             f"in the predictions files of {out}: include it once")
        rows += taken  # where from: doc["included"] (a key per row would double the file)
        own |= {run(r) for r in taken}
    combos = sorted({r["combination"] for r in rows})
    if len(combos) > 1:
        rows += mean_over_combinations(rows, combos)
    rows = [{k: v for k, v in r.items() if k != DRAWS} for r in rows]
    # what the runs were made with (their own config.json, an included summary's config),
    # not the flags of a --summarize-only call, which need not repeat them; the flags fill
    # only what no run states
    flags = json.loads(json.dumps(asdict(cfg), default=str))
    config = {**flags, **_merge_configs(made)} if made else flags
    found: set[int] = set()
    for path in out.glob("predictions_*.npz"):
        with np.load(path) as z:  # the file's index only, no arrays read
            found |= {int(k.split("|")[1]) for k in z.files if k.startswith("pred:")}
    if found:  # what the files hold (a --summarize-only call may not repeat --seeds)
        config["seeds"] = sorted(found)
    doc = {"config": config, "rows": rows}
    if included:
        doc["included"] = included
    if len(made) > 1:
        doc["run_configs"] = made
    (out / "benchmark.json").write_text(json.dumps(doc, indent=1))
    (out / "tables.md").write_text(benchmark_tables(doc))
    main = "mean" if len(combos) > 1 else (combos[0] if combos else "")
    curves = {(r["primitive"], r["method"], r["budget"], r["metric"]):
              (r["mean"], r["ci_low"], r["ci_high"])
              for r in rows if r["combination"] == main and "vs" not in r}
    if curves:
        metric_curves(curves, cfg.methods, cfg.budgets, out / "metrics_vs_budget.png")
    return doc


def benchmark_tables(doc: dict) -> str:
    """Markdown tables of a benchmark.json: metrics per method and budget with intervals,
    and the paired differences against random and none."""
    rows = doc["rows"]
    cfg = doc["config"]
    names = {"fscore": "F-score", "precision": "precision (at 0.5)",
             "recall": "recall (at 0.5)",
             "called": "predicted successes (share of test interactions above 0.5)",
             "rprecision": "R-precision (F-score at as many "
             "predicted successes as there are)", "auroc": "AUROC", "ap": "avg precision",
             "success": "sample success", "simcorr_auroc": "similarity AUROC (correct)"}
    included = doc.get("included", [])
    taken = {(c, p) for i in included for c in i["combinations"] for p in i.get("primitives", [])}
    own = any((r["combination"], r["primitive"]) not in taken for r in rows
              if r["combination"] != "mean")
    lines = ["# Benchmark", "",
             (f"Seeds {cfg['seeds']}; " if own or not included else "")
             + f"budgets {cfg['budgets']} interactions per explore object "
             f"(0 = before exploring); mode {cfg['mode']}; {cfg['explore_objects']} explore "
             f"and {cfg['test_objects']} test objects per category. Values in %, mean "
             "[95 % bootstrap interval over test observations / objects and seeds]."
             + (" VALIDATION: judged on held-out explore instances, not the test split."
                if cfg.get("validate") else "")
             + (" Rows taken from earlier summaries, with the seeds they were made with"
                + (" (the seeds above are those of the other rows)" if own else "") + ":"
                if included else ""), ""]
    lines += [f"- {', '.join(i['combinations'])} {', '.join(i.get('primitives', []))}: "
              f"{i['source']}, seeds {i['seeds']}" for i in included]
    lines += [""] if included else []
    for combo in sorted({r["combination"] for r in rows}, key=lambda c: (c == "mean", c)):
        for prim in ("push", "pull"):
            sel = [r for r in rows if r["combination"] == combo and r["primitive"] == prim]
            if not sel:
                continue
            budgets = sorted({r["budget"] for r in sel})
            lines += [f"## {combo}, {prim}", ""]
            if combo == "mean":
                how = sorted({r.get("ci", "bootstrap") for r in sel})
                lines += [f"Mean over {', '.join(sel[0].get('combinations', []))}; intervals: "
                          + " / ".join({"bootstrap": "bootstrap draws averaged over the "
                                                     "combinations",
                                        "normal": "the combinations' intervals combined as "
                                                  "independent normal errors (a member has "
                                                  "no draws: an included summary)"}[h]
                                       for h in how) + ".", ""]
            for metric in METRICS:
                ms = [r for r in sel if r["metric"] == metric and "vs" not in r]
                if not ms:
                    continue
                lines += [f"**{names[metric]}**", "",
                          "| method | " + " | ".join(f"budget {b}" for b in budgets) + " |",
                          "|---" * (len(budgets) + 1) + "|"]
                for method in dict.fromkeys(r["method"] for r in ms):
                    cells = []
                    for b in budgets:
                        r = next((x for x in ms if x["method"] == method and x["budget"] == b),
                                 None)
                        cells.append(_fmt(r))
                    lines.append(f"| {method} | " + " | ".join(cells) + " |")
                for ref in REFERENCES:
                    ds = [r for r in sel if r["metric"] == metric and r.get("vs") == ref]
                    for method in dict.fromkeys(r["method"] for r in ds):
                        cells = [_fmt(next((x for x in ds if x["method"] == method
                                            and x["budget"] == b), None), signed=True)
                                 for b in budgets]
                        lines.append(f"| {method} - {ref} | " + " | ".join(cells) + " |")
                lines.append("")
    return "\n".join(lines) + "\n"


def _fmt(r: dict | None, signed: bool = False) -> str:
    if r is None or not np.isfinite(r["mean"]):
        return "-"
    f = "{:+.1f}" if signed else "{:.1f}"
    return (f.format(100 * r["mean"]) + f" [{100 * r['ci_low']:.1f}, "
            f"{100 * r['ci_high']:.1f}]")
