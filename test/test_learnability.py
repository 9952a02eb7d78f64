"""``w2e learnability`` on a tiny synthetic setup: curves over N, random and oracle picks."""

from __future__ import annotations

import json

import pytest
import torch
from synthetic import synthetic_data

from w2e_ros.core.exploration.config import ExploreConfig, FinetuneConfig
from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel, save_model
from w2e_ros.experiments.learnability import LearnabilityConfig, run_learnability

torch.set_num_threads(2)
SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))
NOVEL = ("kettle", "bucket")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("learn")
    torch.manual_seed(0)
    meta = {"method": "w2e", "combo": "cfw", "primitive": "push",
            "aff_categories": ["cabinet"], "sim_categories": ["cabinet", "faucet", "window"]}
    save_model(d / "model.pt", W2EModel(SMALL), meta)
    # the pool on explore instances (30..), the judge on test instances (40..), and a
    # training-split cloud of each novel category that neither may use
    synthetic_data(NOVEL, obs_per_cat=3, per_obs=24, seed=5, instance_start=30).save_shard(
        d / "pool" / "shard-00000.npz")
    synthetic_data(NOVEL, obs_per_cat=1, per_obs=24, seed=6, instance_start=0).save_shard(
        d / "pool" / "shard-00001.npz")
    synthetic_data(NOVEL, obs_per_cat=3, per_obs=24, seed=7, instance_start=40).save_shard(
        d / "test" / "shard-00000.npz")
    return d


def test_learnability_curves_rise_with_the_explored_interactions(setup):
    d = setup
    cfg = LearnabilityConfig(
        model=str(d / "model.pt"), pool_data=str(d / "pool"), test_data=str(d / "test"),
        out=str(d / "out"), sizes=(0, 12, 1000), seeds=(0,), selections=("random", "oracle"),
        categories=NOVEL, references=(str(d / "model.pt"),),  # the base, drawn as a line
        # no prior: 60 steps must fit the synthetic pool (the default prior holds a fit near
        # the trained weights on purpose, test_finetune checks it)
        explore=ExploreConfig(finetuning=FinetuneConfig(
            finetune_steps=60, finetune_min_steps=60, finetune_lr=3e-3, anchor=0.0, prior=0.0)))
    summary = run_learnability(cfg)
    rows = [json.loads(s) for s in (d / "out" / "rows.jsonl").read_text().splitlines()]
    assert [(r["selection"], r["n"]) for r in rows] == [
        ("random", 0), ("random", 12), ("random", 144),  # N capped at the pool (3 x 2 x 24)
        ("oracle", 0), ("oracle", 12), ("oracle", 144)]
    base = rows[0]
    assert rows[3]["auroc"] == base["auroc"] and "fit_acc" not in base  # N=0: the base model
    full = rows[2]
    assert full["fit_acc"] > 0.8  # it fits the pool ...
    assert full["auroc"] > base["auroc"] + 0.04  # ... and that carries to unseen instances
    # all of the pool is the same set whichever rule picks it
    assert rows[5]["auroc"] == pytest.approx(full["auroc"], abs=0.05)
    assert set(summary["curves"]) == {"random", "oracle"}
    assert set(summary["curves"]["random"]) == {"0", "12", "144"}
    for f in ("learnability.json", "learnability.md", "learnability_push.png"):
        assert (d / "out" / f).stat().st_size > 0
    # what each selection held, and the selection paired with random at the same seed and N
    from w2e_ros.core.dataset.interactions import InteractionData
    pool_rate = InteractionData.load(str(d / "pool")).select(
        primitive="push", instances=list(range(30, 40))).positive_rate()
    assert "picked_success" not in base
    assert full["picked_success"] == pytest.approx(pool_rate)
    assert full["picked_unexpected"] <= full["picked_success"]
    table = (d / "out" / "learnability.md").read_text()
    diff = 100 * (rows[4]["auroc"] - rows[1]["auroc"])
    assert "| oracle | 12 | 1 | " in table and f"{diff:+.1f} ± 0.0" in table
    # a reference model's row: its metrics, a dash where it picked nothing
    ref = next(line for line in table.splitlines() if "(reference)" in line)
    assert f"{100 * base['auroc']:.1f}" in ref and ref.rstrip(" |").endswith("–")


def test_learnability_refuses_an_empty_pool(setup):
    d = setup
    cfg = LearnabilityConfig(model=str(d / "model.pt"), pool_data=str(d / "pool"),
                             test_data=str(d / "test"), out=str(d / "out2"),
                             categories=("door",))
    with pytest.raises(ValueError, match="no push interactions of door"):
        run_learnability(cfg)


def _cli(d, out, *args: str) -> None:
    """``w2e learnability`` as typed, on the synthetic pool and test data, one seed."""
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "w2e_ros.cli", "learnability", "--model", str(d / "model.pt"),
         "--pool-data", str(d / "pool"), "--test-data", str(d / "test"), "--categories",
         *NOVEL, "--seeds", "0", "--anchor", "0", "--threads", "1", *args, "--out", str(out)],
        capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]


def test_per_category_cli_writes_one_curve_per_category(setup):
    """``w2e learnability --per-category`` as typed: each category fine-tuned on its own
    interactions, every category's curve in one table."""
    d = setup
    out = d / "percat"
    _cli(d, out, "--sizes", "0", "1000", "--selections", "random", "--per-category",
         "--finetune-steps", "40")
    summary = json.loads((out / "per_category.json").read_text())
    assert set(summary["curves"]) == set(NOVEL)
    for c in NOVEL:  # its own pool only: 3 observations x 24 interactions of c
        rows = [json.loads(s) for s in (out / c / "rows.jsonl").read_text().splitlines()]
        assert [row["n"] for row in rows] == [0, 72]
    table = (out / "per_category.md").read_text()
    assert all(f"| {c} |" in table for c in NOVEL) and "N = 72" in table
    assert (out / "per_category_push.png").stat().st_size > 0


def test_pool_selections_pick_what_they_say():
    import numpy as np

    from w2e_ros.experiments.learnability import select_pool

    rng = np.random.default_rng(0)
    predicted = rng.random(200)
    success = rng.random(200) < 0.1
    for sel in ("random", "oracle", "oracle_stratified", "confident", "half_success"):
        rows = select_pool(sel, 40, predicted, success, np.random.default_rng(1))
        assert len(np.unique(rows)) == 40 and np.all(np.diff(rows) > 0), sel
    conf = select_pool("confident", 40, predicted, success, rng)
    assert set(conf) == set(np.argsort(-predicted)[:40])  # no labels used
    wrong = np.abs(predicted - success)
    assert wrong[select_pool("oracle", 40, predicted, success, rng)].min() >= np.sort(wrong)[-40]
    # the most wrong of each class, in the pool's class mix (oracle alone: all successes)
    strat = select_pool("oracle_stratified", 40, predicted, success, rng)
    k = int(round(40 * success.mean()))
    assert success[strat].sum() == k
    assert set(strat[success[strat]]) == set(np.flatnonzero(success)[
        np.argsort(-wrong[success])[:k]])
    half = select_pool("half_success", 40, predicted, success, rng)
    assert success[half].sum() == 20  # the pool's rate is ~10 %
    few = select_pool("half_success", 100, predicted, success, rng)  # positives run short
    assert len(few) == 100 and success[few].sum() == success.sum()
    with pytest.raises(ValueError, match="unknown selection"):
        select_pool("best", 4, predicted, success, rng)


def test_unfamiliar_selections_use_the_similarity_not_the_labels():
    import numpy as np

    from w2e_ros.experiments.learnability import select_pool

    rng = np.random.default_rng(0)
    predicted, similarity = rng.random(200), rng.random(200)
    success = rng.random(200) < 0.1
    least = set(np.argsort(similarity)[:40])
    assert set(select_pool("unfamiliar", 40, predicted, success, rng, similarity)) == least
    flipped = select_pool("unfamiliar", 40, predicted, ~success, rng, similarity)
    assert set(flipped) == least  # labels play no part
    half = select_pool("unfamiliar_half", 40, predicted, success, rng, similarity)
    assert len(np.unique(half)) == 40 and set(np.argsort(similarity)[:20]) <= set(half)
    assert len(set(half) - least) >= 10  # the other half is random, mostly outside
    fail = select_pool("unfamiliar_failure", 40, predicted, success, rng, similarity)
    no = np.flatnonzero(predicted <= 0.5)
    assert set(fail) == set(no[np.argsort(similarity[no])[:40]])
    doubt = select_pool("uncertain_failure", 40, predicted, success, rng)
    assert set(doubt) == set(no[np.argsort(-predicted[no])[:40]])
    with pytest.raises(ValueError, match="needs the pool's similarity"):
        select_pool("unfamiliar", 4, predicted, success, rng)


def test_cli_label_free_selection_picks_predicted_failures(setup):
    """``w2e learnability --selections random unfamiliar_failure`` as typed: the label-free
    rule takes the actions the base model predicts to fail first (where a success is one the
    model did not expect), and the table pairs it with random."""
    d = setup
    out = d / "unfamiliar"
    _cli(d, out, "--sizes", "12", "--selections", "random", "unfamiliar_failure",
         "--finetune-steps", "20")
    rows = {row["selection"]: row for row in
            map(json.loads, (out / "rows.jsonl").read_text().splitlines())}
    # the base model's predicted failures in the pool: the rule takes all it can of them
    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.model.network import load_model
    from w2e_ros.core.model.predict import predict_interactions
    pool = InteractionData.load(str(d / "pool")).select(primitive="push",
                                                        instances=list(range(30, 40)))
    said_no = int((predict_interactions(load_model(str(d / "model.pt"))[0], pool)[0]
                   <= 0.5).sum())
    picked = rows["unfamiliar_failure"]
    assert picked["picked_predicted_failure"] == pytest.approx(min(said_no, 12) / 12)
    assert 0 < said_no < 12  # this pool: the rule takes them all, then predicted successes
    assert picked["picked_predicted_failure"] > rows["random"]["picked_predicted_failure"]
    assert "| unfamiliar_failure | 12 | 1 | " in (out / "learnability.md").read_text()
