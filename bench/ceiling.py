"""How much can choosing win at all? (issue 40, item 1). Two kinds of few-shot run beside
``w2e benchmark``'s, judged on the same objects and written in its predictions format:

``refit``: the ``random`` rule with the exploration seeded apart from the fine-tuning. With
``--seeds E --fit-seeds E`` it is the benchmark's ``random`` run of seed E (a check);
with another fit seed the SAME explored set is fitted again, so the spread of the fitted
model's AUROC over explored sets can be split into what the set decides and what the
fine-tuning's own randomness adds.

``lookahead``: a hindsight oracle. Each round it draws ``--candidates`` M batches with the
random rule, executes each (labels: the simulator), fine-tunes a copy of the model on it and
keeps the batch whose copy ranks the labelled PROBE interactions best (pooled AUROC): the
validation collection's interactions of the EXPLORE objects themselves (other observations
of them), never the judged objects. M = 1 is the random rule.

    OMP_NUM_THREADS=1 .venv/bin/python bench/ceiling.py run --mode lookahead --seeds 0 \
        --candidates 4 --out results/ceil_look4 --runs checkpoints \
        --train-data checkpoints/replay_cfw --test-data data/valset/novel_cfw

``summarize`` (after the runs): pooled pull AUROC / F-score of every run, the spread over
random explored sets, best of K, and what the good sets have in common; see --help.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger("w2e.ceiling")


# --- runs ---------------------------------------------------------------------------------

def _config(a: argparse.Namespace):
    from w2e_ros.experiments.config import BenchmarkConfig

    cfg = BenchmarkConfig(runs=a.runs, train_data=a.train_data, test_data=a.test_data,
                          out=a.out, combos=(a.combo,), primitives=(a.primitive,),
                          methods=("random",), budgets=tuple(a.budgets),
                          explore_objects=a.explore_objects, test_objects=a.test_objects,
                          validate=a.validate, heatmaps=False)
    return cfg


def explore_lookahead(explorer, world, targets, cfg, primitive, rng, m: int, probe,
                      on_round=None):
    """The exploration loop of ``core.explore.explore`` (random rule, no bar, flying gripper)
    with each round's batch the best of ``m`` random batches by the probe AUROC after
    fitting on it. Returns the ExplorationResult and the per-round choice log."""
    from w2e_ros.core.exploration.explore import FLYING, Executed, _Run
    from w2e_ros.core.exploration.strategies import get_strategy
    from w2e_ros.core.model.metrics import auroc
    from w2e_ros.core.model.predict import predict_interactions

    run = _Run(explorer, world, list(targets), get_strategy("random"), cfg, primitive, rng,
               FLYING, 0)
    choices = []
    while True:
        t0 = time.perf_counter()
        cands = run.candidates()
        scored = run.model.score(run.clouds, cands)
        obj_mean = [float(np.mean(s.similarity)) if len(s.similarity) else 1.0 for s in scored]
        run.means.append(float(np.mean(obj_mean)))
        if len(run.records) >= run.total:
            break
        options = [run.pick(scored) for _ in range(m)]
        trials = []
        state = torch.get_rng_state()
        for picks in options:
            trial = copy.deepcopy(run.model, {id(run.model.features): run.model.features})
            executed = []
            for a_obj, i in picks:
                obj = run.active[a_obj]
                act = cands[obj].action(run.clouds[obj], i, primitive)
                executed.append(Executed(run.clouds[obj], cands[obj], i,
                                         world.execute(run.targets[obj], act)))
            torch.set_rng_state(state)
            stats = trial.update(executed)
            score = auroc(predict_interactions(trial.model, probe)[0], probe.success)
            trials.append((score, picks, trial, stats, torch.get_rng_state(),
                           int(sum(e.result.success for e in executed))))
        best = int(np.argmax([t[0] for t in trials]))
        score, picks, trial, stats, rng_after, _ = trials[best]
        choices.append({"round": run.round + 1, "probe_auroc": [t[0] for t in trials],
                        "successes": [t[5] for t in trials], "chosen": best})
        run.model = trial
        trial.update = lambda executed, _s=stats: _s  # fitted already: learn() only records
        executed, _ = run.execute(picks, cands, scored, obj_mean, lambda: False)
        run.learn(executed, t0, None)
        del trial.update
        torch.set_rng_state(rng_after)
        log.info("round %d: probe AUROC of the %d candidate batches %s (successes %s), "
                 "chose %d (%.0f s)", run.round, m,
                 " ".join(f"{t[0]:.3f}" for t in trials), [t[5] for t in trials], best,
                 time.perf_counter() - t0)
        if on_round:
            on_round()
        run.reobserve(executed)
    return run.result("budget"), run.model, choices


def run_one(cfg, mode: str, explore_seed: int, fit_seed: int, m: int, test_all, train_all,
            probe_all):
    """One run: predictions per budget (benchmark keys) and the exploration log."""
    from w2e_ros.core.exploration.explore import explore, explore_targets
    from w2e_ros.core.exploration.finetune import (
        W2EExplorer,
        similarity_is_balanced,
        trains_similarity,
    )
    from w2e_ros.core.exploration.strategies import get_strategy
    from w2e_ros.core.model.network import load_model
    from w2e_ros.core.model.training import replay_data
    from w2e_ros.experiments.benchmark import _group, find_checkpoint

    prim, combo = cfg.primitives[0], cfg.combos[0]
    world, novel, ev = _group(cfg, prim, combo, test_all)
    t0 = time.perf_counter()
    torch.manual_seed(fit_seed)
    model, meta = load_model(find_checkpoint(cfg.runs, "w2e", combo, prim))
    ecfg = replace(cfg.explore, budget=max(cfg.budgets), snapshot_budgets=tuple(cfg.budgets),
                   seed=fit_seed)
    replay = replay_data(train_all, meta, prim)
    explorer = W2EExplorer(model, ecfg.finetuning, replay, tuple(meta.get("aff_categories", ())),
                           tuple(meta.get("sim_categories", ())),
                           train_similarity=trains_similarity(meta, ecfg.finetuning),
                           balanced_similarity=similarity_is_balanced(meta), seed=fit_seed)
    targets = explore_targets(novel, cfg.explore_objects)
    rng = np.random.default_rng(explore_seed)
    choices = None
    if mode == "refit":
        res = explore(explorer, world, targets, get_strategy("random"), ecfg, prim, rng=rng)
    else:
        from w2e_ros.core.dataset.categories import load_categories

        cats = load_categories()
        own = {c: set(cats.instances(c, "explore")[:cfg.explore_objects]) for c in novel}
        probe = probe_all.select(primitive=prim, categories=novel)
        inst = probe.instance[probe.obs_index]
        probe = probe.subset(np.array([int(i) in own[str(c)] for i, c in zip(
            inst, probe.interaction_category, strict=True)], bool))
        log.info("lookahead probe: %d interactions (%d successes) of the explore objects",
                 probe.num_interactions, int(probe.success.sum()))
        res, explorer, choices = explore_lookahead(explorer, world, targets, ecfg, prim, rng,
                                                   m, probe)
    preds = {}
    name = mode if mode == "refit" else f"lookahead{m}"
    for b in (0, *cfg.budgets):
        for k, v in ev.predict(explorer.model_at(res.snapshots[b])).items():
            preds[f"{name}|{explore_seed}|{fit_seed}|{b}|{k}"] = v
    logd = {"stopped": res.stopped, "steps": [asdict(x) for x in res.steps],
            "mean_similarity": res.mean_similarity, "fit": explorer.fit_log,
            "explore_seed": explore_seed, "fit_seed": fit_seed, "choices": choices}
    return preds, {f"{name}_e{explore_seed}_f{fit_seed}": logd}, time.perf_counter() - t0


def cmd_run(a: argparse.Namespace) -> None:
    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.experiments.benchmark import _group, _save_predictions
    from w2e_ros.experiments.sim_world import SimWorld

    torch.set_num_threads(a.threads)
    cfg = _config(a)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps({**asdict(cfg), "ceiling": vars(a)},
                                                indent=1, default=str))
    test_all = InteractionData.load(cfg.test_data)
    train_all = InteractionData.load(cfg.train_data)
    prim, combo = cfg.primitives[0], cfg.combos[0]
    ev = _group(cfg, prim, combo, test_all, SimWorld())[2]
    preds, logs = {}, {}
    fit_seeds = a.fit_seeds or a.seeds
    pairs = list(zip(a.seeds, fit_seeds, strict=True))
    for j, (e, f) in enumerate(pairs):
        p, lg, sec = run_one(cfg, a.mode, e, f, a.candidates, test_all, train_all, test_all)
        preds.update(p)
        logs.update(lg)
        _save_predictions(out / f"predictions_{combo}_{prim}.npz", preds, ev)
        (out / f"explored_{combo}_{prim}.json").write_text(json.dumps(logs))
        log.info("[%d/%d] %s explore seed %d fit seed %d done in %.0f s", j + 1, len(pairs),
                 a.mode, e, f, sec)


# --- statistics ---------------------------------------------------------------------------

def _load(path: Path) -> tuple[dict, dict]:
    """Predictions keyed (method, explore seed, fit seed, budget) and the test arrays; the
    benchmark's keys method|seed|budget|what are read as fit seed = explore seed."""
    z = np.load(path)
    preds: dict = {}
    for k in z.files:
        if not k.startswith("pred:"):
            continue
        parts = k[5:].split("|")
        if len(parts) == 4:
            m, s, b, what = parts
            key = (m, int(s), int(s), int(b))
        else:
            m, s, f, b, what = parts
            key = (m, int(s), int(f), int(b))
        preds.setdefault(key, {})[what] = z[k]
    test = {k[5:]: z[k] for k in z.files if k.startswith("test:")}
    return preds, test


def _auroc_fast(score: np.ndarray, y: np.ndarray) -> float:
    from scipy.stats import rankdata

    n1 = int(y.sum())
    n0 = len(y) - n1
    if n1 == 0 or n0 == 0:
        return float("nan")
    r = rankdata(score)
    return float((r[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def _f(score: np.ndarray, y: np.ndarray) -> float:
    p = score > 0.5
    tp = float(np.sum(p & y))
    return 2 * tp / max(float(np.sum(p) + np.sum(y)), 1.0)


def _spearman(x, y) -> float:
    from scipy.stats import spearmanr

    if np.std(x) == 0 or np.std(y) == 0:
        return float("nan")
    return float(spearmanr(x, y).statistic)


def cmd_summarize(a: argparse.Namespace) -> None:  # noqa: C901 (one report, read top down)
    rng = np.random.default_rng(a.boot_seed)
    preds, test, logs = {}, None, {}
    for d in a.dirs:
        p, t = _load(Path(d) / f"predictions_{a.combo}_{a.primitive}.npz")
        if test is not None and not np.array_equal(t["success"], test["success"]):
            raise SystemExit(f"{d}: another judged set")
        test = t
        for k, v in p.items():
            preds.setdefault(k, v)
        ex = Path(d) / f"explored_{a.combo}_{a.primitive}.json"
        if ex.exists():
            for k, v in json.loads(ex.read_text()).items():
                logs[(Path(d).name, k)] = v
    y, obs, cat = test["success"].astype(bool), test["obs"], test["category"]
    members = [np.flatnonzero(obs == o) for o in np.unique(obs)]
    boots = [np.concatenate([members[i] for i in rng.integers(len(members), size=len(members))])
             for _ in range(a.bootstrap)]
    budgets = sorted({k[3] for k in preds})
    cache: dict = {}

    def metric(key, name, rows=None):
        ck = (key, name, None if rows is None else id(rows))
        if ck not in cache:
            s = preds[key]["aff"]
            r = slice(None) if rows is None else rows
            cache[ck] = (_auroc_fast(s[r], y[r]) if name == "auroc" else _f(s[r], y[r])) * 100
        return cache[ck]

    def ci(draws):
        return np.percentile(draws, [2.5, 97.5])

    none_key = next(k for k in preds if k[0] == "none" and k[3] == 0)
    rand = sorted({(k[1]) for k in preds if k[0] == "random"})
    report = {"judged": {"interactions": int(len(y)), "positives": int(y.sum()),
                         "observations": len(members)}, "budgets": {}}
    lines = ["# How much can choosing win at all? (cfw pull, validation split)", "",
             f"Judged: {len(y)} pull interactions ({int(y.sum())} successes) on "
             f"{len(members)} observations of held-out explore instances; every run is judged "
             "on the same interactions. Intervals: 95 % bootstrap over judged observations "
             f"({a.bootstrap} resamples), paired (the same resample for both sides); where "
             "seeds are averaged, seeds are resampled too.", ""]
    for b in budgets:
        if b == 0:
            continue
        keys = [("random", s, s, b) for s in rand if ("random", s, s, b) in preds]
        seeds = [k[1] for k in keys]
        au = np.array([metric(k, "auroc") for k in keys])
        fs = np.array([metric(k, "fscore") for k in keys])
        n_au, n_f = metric(none_key, "auroc"), metric(none_key, "fscore")
        # per-seed draws on the shared observation resamples: (B, S)
        d_au = np.array([[metric(k, "auroc", r) for k in keys] for r in boots])
        d_nau = np.array([metric(none_key, "auroc", r) for r in boots])
        d_f = np.array([[metric(k, "fscore", r) for k in keys] for r in boots])
        d_nf = np.array([metric(none_key, "fscore", r) for r in boots])
        seed_pick = [rng.integers(len(keys), size=len(keys)) for _ in boots]
        mean_gain = np.array([d_au[i, sp].mean() - d_nau[i] for i, sp in enumerate(seed_pick)])
        mean_fgain = np.array([d_f[i, sp].mean() - d_nf[i] for i, sp in enumerate(seed_pick)])
        rb = {"seeds": seeds, "auroc": au.tolist(), "fscore": fs.tolist(),
              "none": {"auroc": n_au, "fscore": n_f},
              "random_mean_minus_none": {"auroc": [float(au.mean() - n_au), *ci(mean_gain)],
                                         "fscore": [float(fs.mean() - n_f), *ci(mean_fgain)]},
              "auroc_sd": float(au.std(ddof=1)), "fscore_sd": float(fs.std(ddof=1)),
              "below_none": int(np.sum(au < n_au)),
              "below_none_sig": int(np.sum(np.percentile(d_au - d_nau[:, None], 97.5,
                                                          axis=0) < 0)),
              "above_none_sig": int(np.sum(np.percentile(d_au - d_nau[:, None], 2.5,
                                                          axis=0) > 0))}
        # observation-resampling sd of one run's AUROC (how much of the seed spread one
        # judged set's noise would explain): mean over seeds of the bootstrap sd
        rb["judge_sd_auroc"] = float(np.mean(d_au.std(axis=0)))
        # best / worst single set vs the mean of the others, paired over observations
        ib, iw = int(np.argmax(au)), int(np.argmin(au))
        rb["best"] = {"seed": seeds[ib], "auroc": float(au[ib]),
                      "minus_random_mean": [float(au[ib] - au.mean()),
                                            *ci(d_au[:, ib] - d_au.mean(axis=1))]}
        rb["worst"] = {"seed": seeds[iw], "auroc": float(au[iw]),
                       "minus_random_mean": [float(au[iw] - au.mean()),
                                             *ci(d_au[:, iw] - d_au.mean(axis=1))]}
        # best of K on validation: expected AUROC of the chosen set, by resampling K of S
        bok = {}
        for kk in a.best_of:
            if kk > len(keys):
                continue
            sel = [rng.choice(len(keys), size=kk, replace=False) for _ in range(4000)]
            chosen = np.array([au[s].max() for s in sel])
            bok[kk] = {"expected": float(chosen.mean()),
                       "minus_random_mean": float(chosen.mean() - au.mean()),
                       "p10_p90": np.percentile(chosen, [10, 90]).tolist()}
        rb["best_of_k"] = bok
        report["budgets"][b] = rb
    # refits: the same explored set, another fine-tuning seed
    refit = sorted({(k[1], k[2]) for k in preds if k[0] == "refit" and k[1] != k[2]})
    if refit:
        bmax = max(budgets)
        rows = []
        for e, f in refit:
            if ("random", e, e, bmax) in preds:
                rows.append((e, f, metric(("random", e, e, bmax), "auroc"),
                             metric(("refit", e, f, bmax), "auroc")))
        if rows:
            r = np.array(rows)
            x, z = r[:, 2], r[:, 3]
            # variance split: within-set (fit) variance from the pairs, total from all seeds
            within = float(np.mean((x - z) ** 2) / 2)
            total = float(np.var(report["budgets"][bmax]["auroc"], ddof=1))
            report["refit"] = {"budget": bmax, "pairs": rows, "spearman_fit1_fit2":
                               _spearman(x, z), "pearson": float(np.corrcoef(x, z)[0, 1]),
                               "within_set_var": within, "total_var": total,
                               "set_share_of_var": float(max(0.0, 1 - within / total))}
    # lookahead oracle runs
    look = sorted({k[0] for k in preds if k[0].startswith("lookahead")})
    report["lookahead"] = {}
    for name in look:
        for b in budgets:
            if b == 0:
                continue
            keys = sorted(k for k in preds if k[0] == name and k[3] == b)
            rkeys = [("random", s, s, b) for s in rand if ("random", s, s, b) in preds]
            if not keys or not rkeys:
                continue
            la = np.array([metric(k, "auroc") for k in keys])
            ra = np.array([metric(k, "auroc") for k in rkeys])
            d = []
            for r_ in boots:
                lp = rng.integers(len(keys), size=len(keys))
                rp = rng.integers(len(rkeys), size=len(rkeys))
                d.append(np.mean([metric(keys[i], "auroc", r_) for i in lp])
                         - np.mean([metric(rkeys[i], "auroc", r_) for i in rp]))
            report["lookahead"].setdefault(name, {})[b] = {
                "seeds": [k[1] for k in keys], "auroc": la.tolist(),
                "minus_random_mean": [float(la.mean() - ra.mean()), *ci(np.array(d))],
                "fscore": [metric(k, "fscore") for k in keys]}
    # the oracle's choices: did it pick the batches with more successes?
    ch = [c for (dname, k), v in logs.items() if k.startswith("lookahead") and v.get("choices")
          for c in v["choices"]]
    if ch:
        succ = np.array([c["successes"] for c in ch], float)
        chosen = np.array([c["successes"][c["chosen"]] for c in ch], float)
        rank = [float(np.mean(np.array(c["successes"]) < c["successes"][c["chosen"]])
                      + 0.5 * np.mean(np.array(c["successes"]) == c["successes"][c["chosen"]]))
                for c in ch]
        spread = [max(c["probe_auroc"]) - min(c["probe_auroc"]) for c in ch]
        report["lookahead_choices"] = {
            "rounds": len(ch), "successes_chosen_mean": float(chosen.mean()),
            "successes_candidates_mean": float(succ.mean()),
            "chosen_success_rank_mean": float(np.mean(rank)),  # 0.5: no preference
            "probe_auroc_spread_mean": float(np.mean(spread) * 100),
            "spearman_successes_probe_gain": _spearman(
                (succ - succ.mean(axis=1, keepdims=True)).ravel(),
                np.array([np.array(c["probe_auroc"]) - np.mean(c["probe_auroc"])
                          for c in ch]).ravel())}
    # what the good sets have in common, at each budget: properties of the explored set up
    # to that budget's snapshot (from the exploration logs), against its AUROC gain over none
    report["properties"], report["correlation_with_gain"], report["per_category"] = {}, {}, {}
    for b in budgets:
        if b == 0:
            continue
        rb = report["budgets"][b]
        props = {}
        for s in rb["seeds"]:
            lg = next((v for (dname, k), v in logs.items()
                       if k in (f"random_s{s}_all", f"refit_e{s}_f{s}")), None)
            if lg is None:
                continue
            st_all = lg["steps"]
            rounds = np.array([x["round"] for x in st_all])
            upto = next(r for r in sorted(set(rounds)) if np.sum(rounds <= r) >= b * 55)
            st = [x for x in st_all if x["round"] <= upto]
            props[s] = _properties(st)
        report["properties"][b] = props
        seeds = [s for s in rb["seeds"] if s in props]
        if not seeds:
            continue
        gain = np.array([rb["auroc"][rb["seeds"].index(s)] - rb["none"]["auroc"]
                         for s in seeds])
        corr = {}
        names = [k for k, v in props[seeds[0]].items() if not isinstance(v, dict)]
        for nm in names:
            x = np.array([props[s][nm] for s in seeds], float)
            if not np.isfinite(x).all() or np.std(x) == 0:
                continue
            bs = []
            for _ in range(a.bootstrap):
                i = rng.integers(len(seeds), size=len(seeds))
                v = _spearman(x[i], gain[i])
                if np.isfinite(v):
                    bs.append(v)
            corr[nm] = [_spearman(x, gain), *ci(np.array(bs))]
        report["correlation_with_gain"][b] = corr
        # within categories: a category's AUROC gain (its judged rows only) against the
        # successes / pulls the set spent on it, over sets (Spearman per category)
        percat = {}
        for c in np.unique(cat):
            rows_c = np.flatnonzero(cat == c)
            if y[rows_c].sum() < 5:
                continue
            n0 = _auroc_fast(preds[none_key]["aff"][rows_c], y[rows_c]) * 100
            g = np.array([_auroc_fast(preds[("random", s, s, b)]["aff"][rows_c], y[rows_c])
                          * 100 - n0 for s in seeds])
            ns = np.array([props[s]["per_category_successes"].get(c, 0) for s in seeds])
            npl = np.array([props[s]["per_category_pulls"].get(c, 0) for s in seeds])
            percat[c] = {"positives": int(y[rows_c].sum()), "none_auroc": n0,
                         "gain_mean": float(g.mean()), "gain_sd": float(g.std(ddof=1)),
                         "spearman_gain_vs_own_successes": _spearman(ns, g),
                         "spearman_gain_vs_own_pulls": _spearman(npl, g),
                         "mean_own_successes": float(ns.mean())}
        report["per_category"][b] = percat
    if a.test_dirs:
        report["test"] = _on_test(a, report, rng)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ceiling.json").write_text(json.dumps(report, indent=1, default=float))
    lines += _tables(report)
    (out / "tables.md").write_text("\n".join(lines) + "\n")
    _plot(report, out / "ceiling.png")
    print("\n".join(lines))


def _properties(st: list[dict]) -> dict:
    """What an explored set is: its successes, allocation and the model's scores of it."""
    succ = np.array([x["success"] for x in st], bool)
    valid = np.array([x["valid"] for x in st], bool)
    groups = np.array([x["group"] for x in st])
    tg = np.array([x["target"] for x in st])
    aff = np.array([x["affordance"] for x in st])
    sim = np.array([x["similarity"] for x in st])
    cats, cnt = np.unique(groups, return_counts=True)
    share = cnt / cnt.sum()
    _, tcnt = np.unique(tg, return_counts=True)
    scnt = np.unique(tg[succ], return_counts=True)[1] if succ.any() else np.zeros(1, int)
    sc = np.array([succ[groups == c].sum() for c in cats], float)
    ss = sc[sc > 0] / max(sc.sum(), 1)
    return {
        "pulls": len(st), "success_share": float(succ.mean()), "successes": int(succ.sum()),
        "valid_share": float(valid.mean()),
        "categories_with_success": int(np.sum(sc > 0)),
        "objects_with_success": int(len(np.unique(tg[succ]))),
        "category_entropy": float(-(share * np.log(share)).sum()),
        "success_category_entropy": float(-(ss * np.log(ss)).sum()) if len(ss) else 0.0,
        "top_category_success_share": float(sc.max() / max(sc.sum(), 1)),
        "objects_touched": int(len(tcnt)), "max_on_one_object": int(tcnt.max()),
        "max_successes_one_object": int(scnt.max()),
        "mean_pred_affordance": float(aff.mean()),
        "mean_pred_aff_successes": float(aff[succ].mean()) if succ.any() else float("nan"),
        "mean_pred_aff_failures": float(aff[~succ].mean()) if (~succ).any() else float("nan"),
        "unexpected_successes": int(np.sum(succ & (aff < 0.5))),
        "confident_failures": int(np.sum(~succ & (aff > 0.5))),
        "mean_similarity_picks": float(sim.mean()),
        "success_aff_auroc": _auroc_fast(aff, succ) if 0 < succ.sum() < len(succ)
        else float("nan"),
        "per_category_successes": {str(c): int(succ[groups == c].sum()) for c in cats},
        "per_category_pulls": {str(c): int((groups == c).sum()) for c in cats},
    }


def _on_test(a: argparse.Namespace, rep: dict, rng: np.random.Generator) -> dict:
    """The same explored sets judged on the TEST split: does a set's validation AUROC say
    how it does on test, and what does choosing the best of K on validation give there?"""
    preds, test = {}, None
    for d in a.test_dirs:
        p, t = _load(Path(d) / f"predictions_{a.combo}_{a.primitive}.npz")
        test = t
        for k, v in p.items():
            preds.setdefault(k, v)
    y, obs = test["success"].astype(bool), test["obs"]
    members = [np.flatnonzero(obs == o) for o in np.unique(obs)]
    none_key = next(k for k in preds if k[0] == "none" and k[3] == 0)
    out = {"judged": {"interactions": int(len(y)), "positives": int(y.sum()),
                      "observations": len(members)}, "budgets": {}}
    for b, r in rep["budgets"].items():
        seeds = [s for s in r["seeds"] if ("random", s, s, b) in preds]
        if len(seeds) < 3:
            continue
        val = np.array([r["auroc"][r["seeds"].index(s)] for s in seeds])
        tst = np.array([_auroc_fast(preds[("random", s, s, b)]["aff"], y) * 100 for s in seeds])
        tf = np.array([_f(preds[("random", s, s, b)]["aff"], y) * 100 for s in seeds])
        n_au = _auroc_fast(preds[none_key]["aff"], y) * 100
        n_f = _f(preds[none_key]["aff"], y) * 100
        # bootstrap over sets (and test observations) for the Spearman
        bs = []
        for _ in range(a.bootstrap):
            i = rng.integers(len(seeds), size=len(seeds))
            v = _spearman(val[i], tst[i])
            if np.isfinite(v):
                bs.append(v)
        bok = {}
        for kk in a.best_of:
            if kk > len(seeds):
                continue
            sel = [rng.choice(len(seeds), size=kk, replace=False) for _ in range(4000)]
            pick = [s[np.argmax(val[s])] for s in sel]
            bok[kk] = {"val_expected_minus_mean": float(np.mean(val[pick]) - val.mean()),
                       "test_expected_minus_mean": float(np.mean(tst[pick]) - tst.mean()),
                       "test_expected": float(np.mean(tst[pick]))}
        # test: the val-best set against the mean of all sets, paired over test observations
        ib = int(np.argmax(val))
        draws, gdraws = [], []
        for _ in range(a.bootstrap):
            rows = np.concatenate([members[i] for i in rng.integers(len(members),
                                                                       size=len(members))])
            vals = [_auroc_fast(preds[("random", s, s, b)]["aff"][rows], y[rows]) for s in seeds]
            draws.append((vals[ib] - np.mean(vals)) * 100)
            sp = rng.integers(len(seeds), size=len(seeds))
            gdraws.append((np.mean(np.array(vals)[sp])
                           - _auroc_fast(preds[none_key]["aff"][rows], y[rows])) * 100)
        cat = test["category"]
        percat = {}
        for c in np.unique(cat):
            rows_c = np.flatnonzero(cat == c)
            if y[rows_c].sum() < 5:
                continue
            n0 = _auroc_fast(preds[none_key]["aff"][rows_c], y[rows_c]) * 100
            g = np.array([_auroc_fast(preds[("random", s, s, b)]["aff"][rows_c], y[rows_c])
                          * 100 - n0 for s in seeds])
            percat[str(c)] = {"positives": int(y[rows_c].sum()), "none_auroc": n0,
                              "gain_mean": float(g.mean()), "gain_sd": float(g.std(ddof=1))}
        out.setdefault("per_category", {})[b] = percat
        out["budgets"][b] = {
            "seeds": seeds, "val_auroc": val.tolist(), "test_auroc": tst.tolist(),
            "test_fscore": tf.tolist(), "test_none": {"auroc": n_au, "fscore": n_f},
            "spearman_val_test": [_spearman(val, tst), *np.percentile(bs, [2.5, 97.5])],
            "test_sd": float(tst.std(ddof=1)), "best_of_k": bok,
            "random_mean_minus_none": [float(tst.mean() - n_au),
                                       *np.percentile(gdraws, [2.5, 97.5])],
            "val_best": {"seed": seeds[ib], "val_minus_mean": float(val[ib] - val.mean()),
                         "test_minus_mean": [float(tst[ib] - tst.mean()),
                                             *np.percentile(draws, [2.5, 97.5])]}}
    return out


def _tables(rep: dict) -> list[str]:
    L = ["## Random explored sets (one per seed; none = the shipped model, not explored)", "",
         "| budget | sets | none AUROC | random AUROC mean | median | sd over sets | min | max | "
         "random mean − none [95 %] | sets below none (paired 95 % below / above) | "
         "one run's judging sd | none F | random F mean | F sd | F min | F max | "
         "F: random mean − none [95 %] |", "|" + "---|" * 17]
    for b, r in rep["budgets"].items():
        au, fs = np.array(r["auroc"]), np.array(r["fscore"])
        g, fg = r["random_mean_minus_none"]["auroc"], r["random_mean_minus_none"]["fscore"]
        L.append(f"| {b} | {len(au)} | {r['none']['auroc']:.1f} | {au.mean():.1f} | "
                 f"{np.median(au):.1f} | "
                 f"{r['auroc_sd']:.1f} | {au.min():.1f} | {au.max():.1f} | "
                 f"{g[0]:+.1f} [{g[1]:+.1f}, {g[2]:+.1f}] | {r['below_none']} "
                 f"({r['below_none_sig']} / {r['above_none_sig']}) | "
                 f"{r['judge_sd_auroc']:.1f} | {r['none']['fscore']:.1f} | {fs.mean():.1f} | "
                 f"{r['fscore_sd']:.1f} | {fs.min():.1f} | {fs.max():.1f} | "
                 f"{fg[0]:+.1f} [{fg[1]:+.1f}, {fg[2]:+.1f}] |")
    L += ["", "## Best of K random sets chosen on validation AUROC (K of the sets above, "
          "4000 draws without replacement)", "",
          "| budget | best single set (seed): AUROC, − random mean [95 %] | worst (seed) | "
          + " | ".join(f"best of {k}: expected AUROC (− random mean)"
                       for k in next(iter(rep["budgets"].values()))["best_of_k"]) + " |",
          "|" + "---|" * (3 + len(next(iter(rep["budgets"].values()))["best_of_k"]))]
    for b, r in rep["budgets"].items():
        bb, ww = r["best"], r["worst"]
        cells = [f"{v['expected']:.1f} ({v['minus_random_mean']:+.1f})"
                 for v in r["best_of_k"].values()]
        L.append(f"| {b} | {bb['auroc']:.1f} (s{bb['seed']}), {bb['minus_random_mean'][0]:+.1f} "
                 f"[{bb['minus_random_mean'][1]:+.1f}, {bb['minus_random_mean'][2]:+.1f}] | "
                 f"{ww['auroc']:.1f} (s{ww['seed']}), {ww['minus_random_mean'][0]:+.1f} "
                 f"[{ww['minus_random_mean'][1]:+.1f}, {ww['minus_random_mean'][2]:+.1f}] | "
                 + " | ".join(cells) + " |")
    if "refit" in rep:
        r = rep["refit"]
        L += ["", f"## The same explored set fitted twice (budget {r['budget']}: fine-tuning "
              "seed = explore seed, and another)", "",
              "| explore seed | fit seed | AUROC (fit = explore seed) | AUROC (other fit seed) |",
              "|---|---|---|---|"]
        L += [f"| {int(e)} | {int(f)} | {x:.1f} | {z:.1f} |" for e, f, x, z in r["pairs"]]
        L += ["", f"Spearman between the two fits of a set: {r['spearman_fit1_fit2']:+.2f} "
              f"(Pearson {r['pearson']:+.2f}); variance over sets {r['total_var']:.1f}, of it "
              f"within one set (fine-tuning seed) {r['within_set_var']:.1f}: the set itself "
              f"explains ~{100 * r['set_share_of_var']:.0f} %."]
    if rep.get("lookahead"):
        L += ["", "## Lookahead oracle (each round the best of M random batches by the AUROC "
              "on labelled interactions of the explore objects)", "",
              "| oracle | budget | seeds | AUROC per seed | mean − random mean [95 %] |",
              "|---|---|---|---|---|"]
        for name, per in rep["lookahead"].items():
            for b, r in per.items():
                d = r["minus_random_mean"]
                L.append(f"| {name} | {b} | {r['seeds']} | "
                         + ", ".join(f"{v:.1f}" for v in r["auroc"])
                         + f" | {d[0]:+.1f} [{d[1]:+.1f}, {d[2]:+.1f}] |")
    if rep.get("test"):
        t = rep["test"]
        L += ["", "## The same sets on the TEST split (choosing on validation, measured on test)",
              "", f"Test: {t['judged']['interactions']} pull interactions "
              f"({t['judged']['positives']} successes), {t['judged']['observations']} "
              "observations of test-split instances; the explored sets are the validation "
              "runs' own (same seed, same explore objects, same fits).", "",
              "| budget | sets | test none AUROC | test random mean (sd) | random mean − none "
              "[95 %] | Spearman val vs test "
              "[95 %] | val-best set (seed): val − mean | its test − mean [95 %] | "
              + " | ".join(f"best of {k}: val − mean / test − mean" for k in a_best(t))
              + " |", "|" + "---|" * (8 + len(a_best(t)))]
        for b, r in t["budgets"].items():
            ta = np.array(r["test_auroc"])
            sp, vb, rg = r["spearman_val_test"], r["val_best"], r["random_mean_minus_none"]
            L.append(f"| {b} | {len(ta)} | {r['test_none']['auroc']:.1f} | {ta.mean():.1f} "
                     f"({r['test_sd']:.1f}) | {rg[0]:+.1f} [{rg[1]:+.1f}, {rg[2]:+.1f}]"
                     f" | {sp[0]:+.2f} [{sp[1]:+.2f}, {sp[2]:+.2f}] | "
                     f"s{vb['seed']}: {vb['val_minus_mean']:+.1f} | "
                     f"{vb['test_minus_mean'][0]:+.1f} [{vb['test_minus_mean'][1]:+.1f}, "
                     f"{vb['test_minus_mean'][2]:+.1f}] | "
                     + " | ".join(f"{v['val_expected_minus_mean']:+.1f} / "
                                  f"{v['test_expected_minus_mean']:+.1f}"
                                  for v in r["best_of_k"].values()) + " |")
    if rep.get("test") and rep["test"].get("per_category"):
        pcs = rep["test"]["per_category"]
        bmax = max(pcs)
        L += ["", f"Per category on the TEST split, budget {bmax}: AUROC of none and the mean "
              "gain over none of the same sets (its own judged rows)", "",
              "| category | test positives | none AUROC | gain mean | gain sd over sets |",
              "|---|---|---|---|---|"]
        for c, r in pcs[bmax].items():
            L.append(f"| {c} | {r['positives']} | {r['none_auroc']:.1f} | "
                     f"{r['gain_mean']:+.1f} | {r['gain_sd']:.1f} |")
    if rep.get("lookahead_choices"):
        c = rep["lookahead_choices"]
        L += ["", f"The oracle's {c['rounds']} choices: successes in the chosen batch "
              f"{c['successes_chosen_mean']:.1f} vs {c['successes_candidates_mean']:.1f} in the "
              f"average candidate (rank of the chosen batch by successes "
              f"{c['chosen_success_rank_mean']:.2f}; 0.5 = no preference); the candidates' probe "
              f"AUROC spans {c['probe_auroc_spread_mean']:.1f} points a round on average; "
              f"Spearman of a batch's successes with its probe AUROC (both centred per round) "
              f"{c['spearman_successes_probe_gain']:+.2f}."]
    if rep.get("correlation_with_gain"):
        bs_ = list(rep["correlation_with_gain"])
        L += ["", "## What the good sets have in common (Spearman of each property of the "
              "explored set, up to the budget's snapshot, with the set's AUROC gain over none; "
              "95 % bootstrap over sets)", "",
              "| property | " + " | ".join(f"budget {b}: mean [min, max] | Spearman [95 %]"
                                           for b in bs_) + " |",
              "|---|" + "---|---|" * len(bs_)]
        names = list(rep["correlation_with_gain"][bs_[-1]])
        for nm in names:
            cells = []
            for b in bs_:
                v = np.array([p[nm] for p in rep["properties"][b].values()], float)
                c = rep["correlation_with_gain"][b].get(nm)
                cells.append(f"{np.nanmean(v):.3g} [{np.nanmin(v):.3g}, {np.nanmax(v):.3g}]")
                cells.append("-" if c is None else f"{c[0]:+.2f} [{c[1]:+.2f}, {c[2]:+.2f}]")
            L.append(f"| {nm} | " + " | ".join(cells) + " |")
        for b, pc in rep["per_category"].items():
            L += ["", f"Per category, budget {b} (its own judged rows): AUROC of none, the gain "
                  "over none across sets, and its Spearman with the successes / pulls the set "
                  "spent on that category", "",
                  "| category | judged positives | none AUROC | gain mean | gain sd over sets | "
                  "mean own successes | Spearman vs own successes | vs own pulls |",
                  "|---|---|---|---|---|---|---|---|"]
            for c, r in pc.items():
                L.append(f"| {c} | {r['positives']} | {r['none_auroc']:.1f} | "
                         f"{r['gain_mean']:+.1f} | {r['gain_sd']:.1f} | "
                         f"{r['mean_own_successes']:.1f} | "
                         f"{r['spearman_gain_vs_own_successes']:+.2f} | "
                         f"{r['spearman_gain_vs_own_pulls']:+.2f} |")
    return L


def a_best(t: dict) -> list:
    return list(next(iter(t["budgets"].values()))["best_of_k"])


def _plot(rep: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    bs = list(rep["budgets"])
    for j, b in enumerate(bs):
        r = rep["budgets"][b]
        x = np.full(len(r["auroc"]), j) + np.linspace(-0.15, 0.15, len(r["auroc"]))
        ax[0].scatter(x, r["auroc"], s=14, color="tab:blue",
                      label="random sets" if j == 0 else None)
        ax[0].hlines(r["none"]["auroc"], j - 0.3, j + 0.3, color="k",
                     label="none" if j == 0 else None)
        for name, per in rep.get("lookahead", {}).items():
            if b in per:
                ax[0].scatter(np.full(len(per[b]["auroc"]), j + 0.3), per[b]["auroc"],
                              marker="^", color="tab:red", s=24,
                              label=name if j == 0 else None)
    ax[0].set_xticks(range(len(bs)), [f"budget {b}" for b in bs])
    ax[0].set_ylabel("pooled pull AUROC (%)")
    ax[0].set_title("cfw pull, validation: one point per explored set")
    ax[0].legend(fontsize=8)
    if "refit" in rep:
        pr = np.array(rep["refit"]["pairs"])
        ax[1].scatter(pr[:, 2], pr[:, 3])
        lo, hi = pr[:, 2:].min() - 1, pr[:, 2:].max() + 1
        ax[1].plot([lo, hi], [lo, hi], "k:")
        ax[1].set_xlabel("AUROC, fit seed = explore seed")
        ax[1].set_ylabel("AUROC, the same set, another fit seed")
        ax[1].set_title(f"budget {rep['refit']['budget']}: set vs fine-tuning noise")
    if rep.get("test"):
        b = max(rep["test"]["budgets"])
        r = rep["test"]["budgets"][b]
        ax[2].scatter(r["val_auroc"], r["test_auroc"], color="tab:green")
        ax[2].set_xlabel("validation AUROC of the set")
        ax[2].set_ylabel("test AUROC of the same set")
        ax[2].set_title(f"budget {b}: Spearman {r['spearman_val_test'][0]:+.2f}")
    fig.tight_layout()
    try:
        from w2e_ros.core.model.viz import write_figure

        write_figure(fig, path, 110)
    except ImportError:
        fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="refit or lookahead runs")
    r.add_argument("--mode", choices=("refit", "lookahead"), required=True)
    r.add_argument("--seeds", type=int, nargs="+", required=True, help="exploration seeds")
    r.add_argument("--fit-seeds", type=int, nargs="+", help="fine-tuning seeds (default: "
                   "the exploration seeds), one per --seeds")
    r.add_argument("--candidates", type=int, default=4, help="lookahead: batches per round")
    r.add_argument("--runs", default="checkpoints")
    r.add_argument("--train-data", default="checkpoints/replay_cfw")
    r.add_argument("--test-data", default="data/valset/novel_cfw")
    r.add_argument("--validate", action=argparse.BooleanOptionalAction, default=True)
    r.add_argument("--combo", default="cfw")
    r.add_argument("--primitive", default="pull")
    r.add_argument("--budgets", type=int, nargs="+", default=[1, 2, 5])
    r.add_argument("--explore-objects", type=int, default=5)
    r.add_argument("--test-objects", type=int, default=0,
                   help="sample-success objects per category (0: AUROC / F only, faster)")
    r.add_argument("--threads", type=int, default=1)
    r.add_argument("--out", required=True)
    r.set_defaults(func=cmd_run)
    s = sub.add_parser("summarize", help="the tables from benchmark and ceiling runs")
    s.add_argument("dirs", nargs="+", help="w2e benchmark / ceiling run --out directories "
                   "(the same judged set)")
    s.add_argument("--combo", default="cfw")
    s.add_argument("--primitive", default="pull")
    s.add_argument("--test-dirs", nargs="*", default=[], help="the same runs judged on the "
                   "test split (w2e benchmark without --validate)")
    s.add_argument("--best-of", type=int, nargs="+", default=[5, 10, 20])
    s.add_argument("--bootstrap", type=int, default=500)
    s.add_argument("--boot-seed", type=int, default=0)
    s.add_argument("--out", required=True)
    s.set_defaults(func=cmd_summarize)
    a = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: "
                        "%(message)s", datefmt="%H:%M:%S")
    a.func(a)


if __name__ == "__main__":
    main()
