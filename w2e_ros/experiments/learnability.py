"""``w2e learnability``: can the model learn a novel category from N interactions at all?

Before asking which exploration rule is best, this fine-tunes the trained model (with the
few-shot fine-tuning of ``finetune.py``) on N interactions drawn from a collection on the
EXPLORE instances of the novel categories, and scores the result on the held-out TEST
interactions: F-score, AUROC, average precision. ``selection="random"`` draws the N
uniformly; ``selection="oracle"`` takes the N the base model gets most wrong (hindsight
labels), the most a selection rule could gain from the same pool; it takes the model's missed
successes first, so at small N it is all successes (one class). ``oracle_stratified`` takes the
most wrong of each class in the pool's own class mix: the model's mistakes without a class
shift, the bound a rule that finds mistakes (not successes) could reach. If the random curve does
not rise with N, no exploration strategy can help and training must be fixed first.

Two more selections ask WHY the oracle wins. ``confident`` takes the N the base model rates
most likely to succeed (no labels: a rule a robot could follow); ``half_success`` draws the N
at random with half of them successes (hindsight), which separates "the explored set holds
more successes" from "the explored set holds the model's mistakes".

Three label-free ones screen similarity rules cheaply, all at once rather than in rounds:
``unfamiliar`` (the N lowest similarities over the whole pool: Where2Explore's rule without the
bar), ``unfamiliar_half`` (half of them, the other half random: the spread of random with some
of the similarity's successes) and ``unfamiliar_failure`` (the least familiar of the actions the
model predicts to fail: where an unexpected success, the teaching signal, would hide if the
similarity knew where the model's "no" is wrong). ``uncertain_failure`` is its control: the
predicted failures closest to 0.5, the affordance's own doubt without the similarity.
"""

from __future__ import annotations

import copy
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.exploration.config import LEARNABILITY_SELECTIONS
from w2e_ros.core.exploration.finetune import W2EExplorer, similarity_is_balanced, trains_similarity
from w2e_ros.core.exploration.strategies import Scored, get_strategy
from w2e_ros.core.model.metrics import auroc, classification_metrics, within_class_auroc
from w2e_ros.core.model.network import W2EModel, load_model
from w2e_ros.core.model.predict import predict_interactions
from w2e_ros.core.model.training import replay_data
from w2e_ros.experiments.config import LearnabilityConfig

log = logging.getLogger("w2e.learnability")


def _metrics(aff: np.ndarray, sim: np.ndarray, data: InteractionData) -> dict[str, float]:
    y, valid = data.success, data.valid
    out = {k: v for k, v in classification_metrics(aff, y).items()
           if k in ("fscore", "auroc", "ap", "precision", "recall")}
    vm = classification_metrics(aff[valid], y[valid])
    out.update(valid_fscore=vm["fscore"], valid_auroc=vm["auroc"], valid_ap=vm["ap"])
    out["simcorr_auroc"] = auroc(sim, (aff > 0.5) == y)
    out["confidence_simcorr_auroc"] = auroc(np.abs(aff - 0.5), (aff > 0.5) == y)  # baseline
    out["simcorr_within_auroc"] = within_class_auroc(sim, (aff > 0.5) == y, aff > 0.5)
    return out


LABEL_FREE_RULES = {"unfamiliar": "similarity", "unfamiliar_half": "similarity",
                    "unfamiliar_failure": "similarity_failure",
                    "uncertain_failure": "nosim_failure"}
"""Each label-free selection and the exploration strategy whose ranking it applies (the half
one takes the other half at random)."""


def select_pool(selection: str, n: int, predicted: np.ndarray, success: np.ndarray,
                rng: np.random.Generator, similarity: np.ndarray | None = None) -> np.ndarray:
    """Indices of the ``n`` pool interactions a selection fine-tunes on (sorted), from the
    base model's ``predicted`` success probability and ``similarity``, and the pool's labels
    (hindsight rules only)."""
    ok = np.asarray(success, bool)
    if selection in LABEL_FREE_RULES:  # the loop's own rule, applied once to the pool
        if similarity is None and selection != "uncertain_failure":
            raise ValueError(f"selection {selection!r} needs the pool's similarity")
        sim = np.zeros(len(ok)) if similarity is None else similarity
        rule = get_strategy(LABEL_FREE_RULES[selection], experimental=True)
        key = (rule.keys(Scored(predicted, sim), rng)
               + rng.random(len(ok)) * 1e-6)  # ties at random
        order = np.argsort(key, kind="stable")
        if selection != "unfamiliar_half":
            return np.sort(order[:n])
        first = order[:n // 2]
        rest = np.setdiff1d(np.arange(len(ok)), first)
        return np.sort(np.concatenate([first, rng.choice(rest, size=n - len(first),
                                                         replace=False)]))
    if selection == "random":
        rows = rng.choice(len(ok), size=n, replace=False)
    elif selection in ("oracle", "confident"):  # most wrong / most likely first, ties random
        key = np.abs(predicted - ok) if selection == "oracle" else predicted
        rows = np.argsort(-(key + rng.random(len(ok)) * 1e-6))[:n]
    elif selection == "oracle_stratified":  # the most wrong of each class, random's class mix
        pos, neg = np.flatnonzero(ok), np.flatnonzero(~ok)
        k = min(len(pos), max(int(round(n * len(pos) / len(ok))), n - len(neg)))
        wrong = np.abs(predicted - ok) + rng.random(len(ok)) * 1e-6
        rows = np.concatenate([pos[np.argsort(-wrong[pos])[:k]],
                               neg[np.argsort(-wrong[neg])[:n - k]]])
    elif selection == "half_success":
        pos, neg = np.flatnonzero(ok), np.flatnonzero(~ok)
        k = min(len(pos), max(n // 2, n - len(neg)))  # half, unless one class runs short
        rows = np.concatenate([rng.choice(pos, size=k, replace=False),
                               rng.choice(neg, size=n - k, replace=False)])
    else:
        raise ValueError(f"unknown selection {selection!r} "
                         f"({' | '.join(LEARNABILITY_SELECTIONS)})")
    return np.sort(rows)


def run_learnability(cfg: LearnabilityConfig) -> dict:
    """Every (selection, seed, N): fine-tune a copy of the model on N pool interactions and
    evaluate it; writes rows.jsonl, learnability.json, learnability.md and .png to ``out``."""
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    model, meta = load_model(cfg.model)
    prim = meta.get("primitive", "push")
    cats_cfg = load_categories()
    novel = list(cfg.categories or cats_cfg.novel(meta.get("combo")))
    n_pool_obj = 5 if cfg.validate else cfg.explore_objects
    pool_all = InteractionData.load(cfg.pool_data)
    pool = InteractionData.concat([pool_all.select(
        primitive=prim, categories=[c],
        instances=cats_cfg.instances(c, "explore")[:n_pool_obj]) for c in novel])
    test_all = InteractionData.load(cfg.test_data)
    test = InteractionData.concat([test_all.select(
        primitive=prim, categories=[c],
        instances=cats_cfg.evaluation_instances(c, cfg.validate, n_pool_obj)) for c in novel])
    if not pool.num_interactions or not test.num_interactions:
        raise ValueError(f"no {prim} interactions of {', '.join(novel)} in the pool "
                         f"({cfg.pool_data}) or the test data ({cfg.test_data})")
    replay = None
    if cfg.replay_data:
        replay = replay_data(InteractionData.load(cfg.replay_data), meta, prim)
    base_aff, base_sim = predict_interactions(model, test)
    pool_aff, pool_sim = predict_interactions(model, pool)
    log.info("%s: pool %d interactions (%.1f%% positive) on %d clouds, test %d (%.1f%% "
             "positive)", prim, pool.num_interactions, 100 * pool.positive_rate(),
             pool.num_observations, test.num_interactions, 100 * test.positive_rate())
    refs = {}
    for r in cfg.references:
        rm, rmeta = load_model(r)
        ra, rs = predict_interactions(rm, test)
        refs[str(rmeta.get("method", Path(r).parent.name))] = _metrics(ra, rs, test)
    rows: list[dict] = []
    rows_f = (out / "rows.jsonl").open("w")
    t_start = time.perf_counter()
    jobs = [(sel, seed, n) for sel in cfg.selections for seed in cfg.seeds
            for n in cfg.sizes]
    initial = {k: v.detach().clone() for k, v in model.state_dict().items()}
    for j, (sel, seed, n) in enumerate(jobs):
        t0 = time.perf_counter()
        n_eff = min(n, pool.num_interactions)
        picked: dict[str, float] = {}
        if n_eff == 0:
            aff, sim, fit = base_aff, base_sim, {}
        else:
            rows_sel = select_pool(sel, n_eff, pool_aff, pool.success,
                                   np.random.default_rng(seed), pool_sim)
            picked = _picked(pool.success[rows_sel], pool_aff[rows_sel])
            m = copy.deepcopy(model)
            m.load_state_dict(initial)
            fit = _fine_tune(m, meta, cfg, replay, pool, rows_sel, seed)
            aff, sim = predict_interactions(m, test)
        row = {"primitive": prim, "selection": sel, "seed": seed, "n": n_eff,
               **_metrics(aff, sim, test),
               **{k: fit[k] for k in ("fit_acc", "fit_auroc", "fit_steps") if k in fit},
               **picked,
               "seconds": time.perf_counter() - t0}
        rows.append(row)
        rows_f.write(json.dumps(row) + "\n")
        rows_f.flush()
        done = j + 1
        eta = (time.perf_counter() - t_start) / done * (len(jobs) - done)
        log.info("[%d/%d] %s %s seed %d N=%d: F %.3f AUROC %.3f AP %.3f (fit acc %.2f) "
                 "%.1f s, eta %.0f s", done, len(jobs), prim, sel, seed, n_eff, row["fscore"],
                 row["auroc"], row["ap"], fit.get("fit_acc", float("nan")), row["seconds"],
                 eta)
    rows_f.close()
    summary = _summarize(rows, refs, cfg, prim)
    log.info("learnability done in %.0f s: %s", time.perf_counter() - t_start, out)
    return summary


def _picked(success: np.ndarray, predicted: np.ndarray) -> dict[str, float]:
    """What a selection holds: successes, the base model's predicted failures, and the
    successes among those (the unexpected ones, the teaching signal)."""
    ok, said_no = success.astype(bool), predicted <= 0.5
    return {"picked_success": float(ok.mean()),
            "picked_predicted_failure": float(said_no.mean()),
            "picked_unexpected": float((ok & said_no).mean())}


def _fine_tune(model: W2EModel, meta: dict, cfg: LearnabilityConfig,
               replay: InteractionData | None, pool: InteractionData, rows: np.ndarray,
               seed: int) -> dict[str, float]:
    """Fine-tune ``model`` in place on the pool's ``rows``, as an exploring round does."""
    fcfg = cfg.explore.finetuning
    explorer = W2EExplorer(model, fcfg, replay, meta.get("aff_categories", ()),
                           meta.get("sim_categories", ()),
                           train_similarity=trains_similarity(meta, fcfg), seed=seed,
                           balanced_similarity=similarity_is_balanced(meta))
    explorer.add_data(pool, rows)
    return explorer.fit()


def run_per_category(cfg: LearnabilityConfig) -> dict:
    """The curve of each novel category on its own (the paper's per-category setting):
    ``out/<category>/`` as ``run_learnability`` writes it, plus ``per_category.md`` /
    ``.json`` with every category's metrics against N side by side."""
    from w2e_ros.core.model.viz import per_category_figure

    out = Path(cfg.out)
    model_meta = load_model(cfg.model)[1]
    cats = list(cfg.categories or load_categories().novel(model_meta.get("combo")))
    curves: dict[str, dict] = {}
    for c in cats:
        sub = LearnabilityConfig(**{**asdict(cfg), "categories": (c,), "out": str(out / c),
                                    "explore": cfg.explore})
        curves[c] = run_learnability(sub)
    prim = model_meta.get("primitive", "push")
    sel = cfg.selections[0]
    sizes = sorted({int(n) for c in cats for n in curves[c]["curves"][sel]})
    lines = [f"# Per-category learnability ({prim}, {sel} selection)", "",
             "Each novel category fine-tuned on N of its own explore interactions, judged on "
             f"its {'validation' if cfg.validate else 'test'} instances; AUROC / F-score in %, "
             f"mean over seeds {list(cfg.seeds)}.", "",
             "| category | " + " | ".join(f"N = {n}" for n in sizes) + " |",
             "|---" * (len(sizes) + 1) + "|"]
    for c in cats:
        cv = curves[c]["curves"][sel]
        lines.append(f"| {c} | " + " | ".join(
            f"{100 * cv[str(n)]['auroc'][0]:.1f} / {100 * cv[str(n)]['fscore'][0]:.1f}"
            if str(n) in cv else "-" for n in sizes) + " |")
    (out / "per_category.md").write_text("\n".join(lines) + "\n")
    summary = {"primitive": prim, "selection": sel,
               "curves": {c: curves[c]["curves"][sel] for c in cats}}
    (out / "per_category.json").write_text(json.dumps(summary, indent=1))
    per_category_figure(summary, out / f"per_category_{prim}.png")
    return summary


def _mean_std(values: list[float]) -> tuple[float, float]:
    """Over seeds, NaN where a metric has no value (the picks' success at N = 0)."""
    v = np.asarray(values, np.float64)
    v = v[~np.isnan(v)]
    return (float(v.mean()), float(v.std())) if len(v) else (float("nan"), float("nan"))


def _paired_lines(rows: list[dict], selections: Sequence[str]) -> list[str]:
    """Each selection minus random at the same (seed, N), spread over seeds. A rule that is
    deterministic on the fixed pool picks the same N for every seed, so that spread is the
    fit's alone and understates the rule's (measured: a screen win that vanished in the
    loop, whose seeds draw new candidates): a rule is judged in ``w2e benchmark``."""
    if "random" not in selections or len(selections) < 2:
        return []
    ref = {(r["seed"], r["n"]): r for r in rows if r["selection"] == "random"}
    lines = ["", "Paired against random (same seed and N): mean ± std over seeds, in points. "
             "A selection that is deterministic on this pool varies only in its fit, so the "
             "spread understates it; judge a rule in the loop (w2e benchmark).", "",
             "| selection | N | seeds | F-score | AUROC | AP |",
             "|---|---|---|---|---|---|"]
    for sel in selections:
        if sel == "random":
            continue
        for n in sorted({r["n"] for r in rows if r["selection"] == sel and r["n"]}):
            pairs = [(r, ref[(r["seed"], n)]) for r in rows
                     if r["selection"] == sel and r["n"] == n and (r["seed"], n) in ref]
            if not pairs:
                continue
            cells = []
            for m in ("fscore", "auroc", "ap"):
                d = 100 * np.array([a[m] - b[m] for a, b in pairs])
                cells.append(f"{d.mean():+.1f} ± {d.std():.1f}")
            lines.append(f"| {sel} | {n} | {len(pairs)} | " + " | ".join(cells) + " |")
    return lines


def _summarize(rows: list[dict], refs: dict, cfg: LearnabilityConfig, prim: str) -> dict:
    from w2e_ros.core.model.viz import learnability_figure

    out = Path(cfg.out)
    metrics = ("fscore", "auroc", "ap", "valid_auroc", "simcorr_auroc", "picked_success")
    summary: dict = {"primitive": prim, "references": refs, "curves": {}}
    lines = [f"# Learnability ({prim})", "",
             f"Fine-tuned on N pool interactions ({cfg.explore.finetuning.finetune} "
             "fine-tuning), judged "
             f"on {'held-out explore (validation)' if cfg.validate else 'test'} instances of "
             f"the novel categories; mean ± std over seeds {list(cfg.seeds)}. Values in %.", "",
             "| selection | N | " + " | ".join(metrics) + " |",
             "|---" * (len(metrics) + 2) + "|"]
    for sel in cfg.selections:
        curve = {}
        for n in sorted({r["n"] for r in rows if r["selection"] == sel}):
            rs = [r for r in rows if r["selection"] == sel and r["n"] == n]
            curve[n] = {m: _mean_std([r[m] for r in rs if m in r]) for m in metrics}
            lines.append(f"| {sel} | {n} | " + " | ".join(
                "–" if np.isnan(curve[n][m][0])
                else f"{100 * curve[n][m][0]:.1f} ± {100 * curve[n][m][1]:.1f}" for m in metrics)
                + " |")
        summary["curves"][sel] = {str(k): v for k, v in curve.items()}
    for name, v in refs.items():
        lines.append(f"| {name} (reference) | - | " + " | ".join(  # picked_*: no picks
            f"{100 * v[m]:.1f}" if m in v else "–" for m in metrics) + " |")
    lines += _paired_lines(rows, cfg.selections)
    (out / "learnability.md").write_text("\n".join(lines) + "\n")
    (out / "learnability.json").write_text(json.dumps(summary, indent=1))
    learnability_figure(summary, out / f"learnability_{prim}.png")
    return summary
