"""Ceiling diagnostics: perturbations are what they claim, label checks replay real trials,
the fit test fits."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from synthetic import synthetic_data

from w2e_ros.core.robot.primitives import Action
from w2e_ros.experiments.ceiling import (
    PERTURBATIONS,
    _pick_trials,
    fit_subset,
    perturb,
    summarize_labels,
)


@pytest.mark.parametrize("shift,turn", [(0.003, 0.0), (0.01, 0.0), (0.0, 5.0), (0.0, 15.0)])
def test_perturb_moves_along_the_surface_and_turns_by_the_stated_angle(shift, turn):
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        up = -n
        fwd = np.cross(up, rng.normal(size=3))
        fwd /= np.linalg.norm(fwd)
        a = Action(point=rng.normal(size=3), up=up, forward=fwd, primitive="pull")
        b = perturb(a, n, shift, turn, rng)
        d = b.point - a.point
        assert np.linalg.norm(d) == pytest.approx(shift, abs=1e-9)
        assert abs(d @ n) < 1e-9  # along the surface, not into it
        # atan2(|a x b|, a . b) stays accurate near 0 where arccos(a . b) turns the last bit of
        # rounding into ~1e-6 deg (CPU-dependent); 1e-4 deg is still 1/50,000 of the 5 deg step
        angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a.up, b.up)), a.up @ b.up))
        assert angle == pytest.approx(turn, abs=1e-4)
        # still a gripper frame: unit, orthogonal
        assert np.linalg.norm(b.up) == pytest.approx(1) and abs(b.up @ b.forward) < 1e-9
        assert b.primitive == "pull"


def test_replay_keeps_the_action_exactly():
    rng = np.random.default_rng(1)
    a = Action(point=np.ones(3), up=np.array([0, 0, -1.0]), forward=np.array([1.0, 0, 0]))
    b = perturb(a, np.array([0, 0, 1.0]), 0.0, 0.0, rng)
    assert np.array_equal(a.point, b.point) and np.array_equal(a.up, b.up)


def test_pick_trials_takes_valid_trials_spread_over_categories_with_positives():
    data = synthetic_data(obs_per_cat=4, per_obs=24)
    rows = _pick_trials(data, "push", 30, 0.5, np.random.default_rng(0))
    assert len(rows) == 30 and data.valid[rows].all()
    assert (data.primitive[rows] == "push").all()
    cats = data.interaction_category[rows]
    assert len(np.unique(cats)) == len(np.unique(data.interaction_category))
    assert data.success[rows].sum() >= min(15, data.success[data.valid
                                                             & (data.primitive == "push")].sum())


def test_summary_counts_kept_labels_per_category_and_for_successes():
    rows = [{"primitive": "pull", "category": "a", "label": True,
             **{n: True for n, _, _ in PERTURBATIONS}},
            {"primitive": "pull", "category": "b", "label": True,
             **{n: n != "shift_10mm" for n, _, _ in PERTURBATIONS}},
            {"primitive": "pull", "category": "b", "label": False,
             **{n: n == "turn_15deg" for n, _, _ in PERTURBATIONS}}]
    s = summarize_labels(rows)["primitives"]["pull"]
    assert s["all"]["n"] == 3 and s["all"]["positives"] == 2
    assert s["all"]["replay"] == 1.0
    assert s["all"]["shift_10mm"] == pytest.approx(2 / 3)
    assert s["all"]["shift_10mm_pos"] == pytest.approx(1 / 2)
    assert s["b"]["turn_15deg"] == pytest.approx(1 / 2)
    assert s["a"]["turn_15deg_pos"] == 1.0


def test_fit_subset_keeps_whole_observations():
    data = synthetic_data(obs_per_cat=4, per_obs=24)
    sub = fit_subset(data, 100, seed=0)
    assert 100 <= sub.num_interactions < 100 + 24 * 2
    counts = np.bincount(sub.obs_index)
    full = np.bincount(data.obs_index)
    assert sorted(counts.tolist()) == sorted(full[:len(counts)].tolist())


@pytest.mark.slow
def test_w2e_ceiling_labels_replays_simulated_trials_and_the_replay_repeats(tmp_path):
    """The command as typed on a real collection: every replayed label equals the stored one."""
    from w2e_ros.experiments.collect import CollectConfig, collect

    collect(CollectConfig(out=str(tmp_path / "data"), categories=["cabinet", "bucket"],
                          split="test", observations=2, interactions=12, workers=1))
    out = tmp_path / "labels"
    proc = subprocess.run([sys.executable, "-m", "w2e_ros.cli", "ceiling", "labels", "--data",
                           str(tmp_path / "data"), "--out", str(out), "--trials", "8"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads((out / "labels.json").read_text())
    for prim in ("push", "pull"):
        cell = res["primitives"][prim]["all"]
        assert cell["n"] > 0
        assert cell["replay"] == 1.0  # deterministic: the stored trial gives the stored label
    assert "shift_3mm" in (out / "labels.md").read_text()


@pytest.mark.slow
def test_w2e_ceiling_fit_fits_a_small_training_set(tmp_path):
    """A fresh network must rank the interactions it trained on far above chance."""
    from w2e_ros.experiments.collect import CollectConfig, collect

    collect(CollectConfig(out=str(tmp_path / "data"), categories=["cabinet", "faucet", "window"],
                          observations=3, interactions=24, primitives=("push",), workers=1))
    out = tmp_path / "fit"
    proc = subprocess.run([sys.executable, "-m", "w2e_ros.cli", "ceiling", "fit", "--data",
                           str(tmp_path / "data"), "--out", str(out), "--primitive", "push",
                           "--interactions", "150", "--steps", "120", "--eval-every", "60",
                           "--clouds", "2"],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads((out / "fit.json").read_text())
    assert 150 <= res["interactions"] < 216  # whole observations, not all of them
    assert res["curve"][-1]["auroc"] > 0.8, res["curve"]
    assert res["curve"][-1]["train_loss"] < res["curve"][0]["train_loss"] + 0.05


def test_a_fresh_head_on_frozen_random_features_fits_what_they_separate(tmp_path):
    """The representation half of the fit test: full-batch head training on cached features
    reaches a near-perfect train AUROC when the rows are separable (synthetic handles)."""
    from w2e_ros.experiments.ceiling import FitTestConfig, fit_test

    synthetic_data(obs_per_cat=4, per_obs=24).save_shard(tmp_path / "data" / "shard-00000.npz")
    res = fit_test(FitTestConfig(data=str(tmp_path / "data"), out=str(tmp_path / "fit"),
                                 primitive="push", interactions=200, steps=600, eval_every=300,
                                 frozen_encoder="random", model={"sa_npoint": (64, 16, 8, 4)}),
                   progress=False)
    assert res["interactions"] >= 200
    assert res["curve"][-1]["auroc"] > 0.95
    assert res["curve"][-1]["train_loss"] < res["curve"][0]["train_loss"]
    assert json.loads((tmp_path / "fit" / "fit.json").read_text())["final_auroc"] > 0.95


def test_oracle_summary_scores_the_neighbourhood_rate_per_category():
    """The local oracle's AUROC: a neighbourhood rate that orders the labels scores 1, one
    that reverses them 0, per category and in the mean."""
    from w2e_ros.experiments.ceiling import _radius_key, summarize_oracle

    k1, k2 = _radius_key(0.003), _radius_key(0.01)
    trials = []
    for c in ("a", "b"):
        for i, lab in enumerate([True, True, False, False, False]):
            trials.append({"primitive": "pull", "category": c, "label": lab,
                           k1: (0.9 if lab else 0.1) + 0.01 * i,
                           k2: (0.1 if lab else 0.9) + 0.01 * i})
    s = summarize_oracle(trials, (0.003, 0.01), boot=50)["pull"]
    assert s["n"] == 10 and s["positives"] == 4
    assert s[k1][0] == pytest.approx(1.0) and s[k2][0] == pytest.approx(0.0)
    assert s[f"{k1}_pooled"][0] == pytest.approx(1.0)
    assert s["categories"]["b"][k1] == pytest.approx(1.0)
    assert s["categories"]["a"]["n"] == 5


@pytest.mark.slow
def test_w2e_ceiling_oracle_scores_simulated_trials(tmp_path):
    """The command as typed on a real collection: tiny radii keep the stored outcome, so
    the oracle ranks the stored labels far above chance."""
    from w2e_ros.experiments.collect import CollectConfig, collect

    collect(CollectConfig(out=str(tmp_path / "data"), categories=["cabinet"], split="test",
                          observations=3, interactions=24, primitives=("push",), workers=1))
    out = tmp_path / "oracle"
    proc = subprocess.run([sys.executable, "-m", "w2e_ros.cli", "ceiling", "oracle", "--data",
                           str(tmp_path / "data"), "--out", str(out), "--trials", "12",
                           "--primitives", "push", "--radii", "0.0005", "--samples", "2"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads((out / "oracle.json").read_text())["primitives"]["push"]
    assert res["positives"] > 0 and res["n"] > res["positives"]
    assert res["within_0.5mm"][0] >= 0.9
    bad = subprocess.run([sys.executable, "-m", "w2e_ros.cli", "ceiling", "oracle", "--data",
                          str(tmp_path / "data"), "--samples", "0"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0 and "--samples" in bad.stderr
