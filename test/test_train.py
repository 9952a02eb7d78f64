"""Training: the C_aff / C_sim split, the running-accuracy target, loss, seeds, resume."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic import synthetic_data

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.model.config import ModelConfig, TrainConfig
from w2e_ros.core.model.metrics import auroc
from w2e_ros.core.model.network import load_model
from w2e_ros.core.model.predict import predict_interactions
from w2e_ros.core.model.training import (
    BalancedSampler,
    RunningAccuracy,
    Trainer,
    Validator,
    load_training_data_from,
    make_batch,
    method_categories,
    train,
    training_losses,
)
from w2e_ros.core.robot.actions import encode_rotation

torch.set_num_threads(2)
SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def data():
    return synthetic_data(obs_per_cat=4, per_obs=24)


def _cfg(**kw) -> TrainConfig:
    base = dict(method="w2e", combo="cfw", primitive="push", steps=4, clouds=3,
                per_cloud=8, seed=3, log_every=2, ckpt_every=2,
                calibrate_steps=0)
    base.update(kw)
    return TrainConfig(**base)


def test_methods_split_the_training_categories():
    assert method_categories("w2e", "cfw") == (("cabinet",), ("cabinet", "faucet", "window"))
    assert method_categories("where2act", "tsw") == (("table", "switch", "window"), ())
    aff, sim = method_categories("fulldata", "cfw")
    assert len(aff) == 14 and sim == ()
    with pytest.raises(ValueError):
        method_categories("bogus", "cfw")


def test_running_accuracy_counts_every_prediction_including_the_current_one():
    acc = RunningAccuracy(4)
    np.testing.assert_allclose(acc.update(np.array([0, 1]), np.array([1, 0])), [1.0, 0.0])
    np.testing.assert_allclose(acc.update(np.array([0, 1]), np.array([0, 1])), [0.5, 0.5])
    # the same interaction twice in one batch counts twice; keys beyond the size grow it
    np.testing.assert_allclose(acc.update(np.array([0, 0, 7]), np.array([1, 1, 1])),
                               [0.75, 0.75, 1.0])
    assert acc.total[0] == 4 and acc.total[7] == 1


def test_affordance_head_gets_no_gradient_from_other_sim_categories(data):
    model = __import__("w2e_ros.core.model.network", fromlist=["W2EModel"]).W2EModel(SMALL)
    rows = np.flatnonzero(data.interaction_category != "cabinet")[:40]
    batch = make_batch(data, rows, ("cabinet",), ("cabinet", "faucet", "window"), CPU)
    assert not batch.aff_mask.any() and batch.sim_mask.all()
    loss, _ = training_losses(model, batch, RunningAccuracy(data.num_interactions))
    loss.backward()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.aff_head.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.sim_head.parameters())
    # with the similarity loss switched off, the encoder gets nothing from them either
    model.zero_grad(set_to_none=True)
    loss, _ = training_losses(model, batch, RunningAccuracy(data.num_interactions),
                              sim_weight=0.0)
    loss.backward()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.encoder.parameters())


def test_affordance_loss_only_counts_c_aff_interactions(data):
    model = __import__("w2e_ros.core.model.network", fromlist=["W2EModel"]).W2EModel(SMALL)
    rows = np.arange(data.num_interactions)[::3]
    batch = make_batch(data, rows, ("cabinet",), ("cabinet", "faucet", "window"), CPU)
    assert batch.aff_mask.any() and not batch.aff_mask.all()
    # affordance gradient on the encoder from a mixed batch == from its C_aff rows alone
    loss, _ = training_losses(model, batch, RunningAccuracy(), sim_weight=0.0)
    loss.backward()
    g_mixed = [p.grad.clone() for p in model.aff_head.parameters()]
    model.zero_grad(set_to_none=True)
    caff = rows[data.interaction_category[rows] == "cabinet"]
    only = make_batch(data, caff, ("cabinet",), (), CPU)
    loss, _ = training_losses(model, only, RunningAccuracy(), sim_weight=0.0)
    loss.backward()
    for a, b in zip(g_mixed, (p.grad for p in model.aff_head.parameters()), strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)


def test_similarity_target_is_the_running_accuracy(data):
    model = __import__("w2e_ros.core.model.network", fromlist=["W2EModel"]).W2EModel(SMALL).train()
    rows = np.arange(0, data.num_interactions, 5)
    batch = make_batch(data, rows, ("cabinet",), ("cabinet", "faucet", "window"), CPU)
    acc = RunningAccuracy(data.num_interactions)
    expect_c = np.zeros(data.num_interactions)
    for _ in range(3):
        with torch.no_grad():
            feats = model.encode(batch.clouds)
            pred = model.aff_head(feats[batch.cloud_of, batch.point_index], batch.actions) > 0
            expect_c[rows] += (pred.float() == batch.success).numpy()
        loss, stats = training_losses(model, batch, acc)
        model.zero_grad()
        loss.backward()
        with torch.no_grad():  # move the affordance head so predictions change
            for p in model.parameters():
                p.add_(torch.randn_like(p) * 0.05)
    np.testing.assert_array_equal(acc.total[rows], 3)
    np.testing.assert_array_equal(acc.correct[rows], expect_c[rows])
    assert stats["sim_target"] == pytest.approx(float(np.mean(expect_c[rows] / 3)))


def test_a_few_steps_reduce_the_loss_on_a_small_batch(data):
    trainer = Trainer(_cfg(), data, SMALL, CPU)
    batch = trainer.next_batch()
    first = trainer.train_step(batch)["loss_aff"]
    for _ in range(25):
        last = trainer.train_step(batch)["loss_aff"]
    assert last < 0.6 * first


def test_same_seed_same_weights(data):
    a, b = (Trainer(_cfg(), data, SMALL, CPU) for _ in range(2))
    for _ in range(3):
        a.train_step()
        b.train_step()
    for p, q in zip(a.model.state_dict().values(), b.model.state_dict().values(), strict=True):
        torch.testing.assert_close(p, q)


def test_resume_continues_where_it_stopped(tmp_path, data):
    straight = Trainer(_cfg(), data, SMALL, CPU)
    for _ in range(4):
        straight.train_step()
    first = Trainer(_cfg(), data, SMALL, CPU)
    for _ in range(2):
        first.train_step()
    first.save(tmp_path)
    resumed = Trainer(_cfg(seed=99), data, SMALL, CPU)
    resumed.cfg.seed = 3
    resumed.resume(tmp_path)
    for _ in range(2):
        resumed.train_step()
    assert resumed.step == 4
    np.testing.assert_array_equal(resumed.acc.total, straight.acc.total)
    for p, q in zip(straight.model.state_dict().values(), resumed.model.state_dict().values(),
                    strict=True):
        torch.testing.assert_close(p, q)


def test_train_writes_checkpoint_metrics_and_resumes(tmp_path, data):
    data.save_shard(tmp_path / "data" / "shard-00000.npz")
    out = tmp_path / "run"
    path = train(_cfg(), tmp_path / "data", out, progress=False, model_cfg=SMALL)
    lines = [json.loads(s) for s in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in lines] == [2, 4]
    assert {"loss", "loss_aff", "loss_sim", "steps_per_s", "eta_s"} <= set(lines[0])
    model, meta = load_model(path, "cpu")
    assert meta["step"] == 4 and meta["combo"] == "cfw" and model.cfg == SMALL
    train(_cfg(steps=6), tmp_path / "data", out, resume=True, progress=False, model_cfg=SMALL)
    lines = [json.loads(s) for s in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in lines] == [2, 4, 6]


@pytest.mark.slow
def test_training_on_simulated_interactions_reduces_the_loss(tmp_path):
    from w2e_ros.experiments.collect import CollectConfig, collect

    collect(CollectConfig(out=str(tmp_path / "data"), categories=["cabinet", "faucet", "window"],
                          observations=2, interactions=24, primitives=("push",), workers=1))
    from w2e_ros.core.model.training import load_training_data

    data = load_training_data(tmp_path / "data", "w2e", "cfw", "push")
    assert data.points.shape[1:] == (2048, 3) and data.success.any()
    # the default gives every cloud to the affordance head (C_aff only) ...
    default = Trainer(_cfg(clouds=3, per_cloud=16), data, device=CPU)
    assert default.next_batch().aff_mask.all()
    # ... the paper's joint training shares the batch with the other C_sim categories
    trainer = Trainer(_cfg(clouds=3, per_cloud=16, sim_weight=1.0,
                           aff_share=0.5), data, device=CPU)
    batch = trainer.next_batch()
    assert batch.aff_mask.any() and (~batch.aff_mask).any()  # C_aff and other C_sim clouds
    first = trainer.train_step(batch)
    for _ in range(15):
        last = trainer.train_step(batch)
    # the affordance loss, not the total: the similarity head's soft-target BCE bottoms out
    # at the entropy of its running-accuracy target, which grows while predictions change
    assert last["loss_aff"] < 0.7 * first["loss_aff"]
    assert last["aff_acc"] >= first["aff_acc"]


# --- flipped negatives, the C_aff share, the similarity loss ------------------------------

def test_flipped_rows_reverse_the_approach_fail_and_share_the_counter(data):
    rows = np.flatnonzero(data.success)[:6]
    rows = np.concatenate([rows, rows])  # each positive twice: as stored, then flipped
    flip = np.repeat([False, True], 6)
    batch = make_batch(data, rows, ("cabinet",), ("cabinet", "faucet", "window"), CPU,
                       key_offset=100, flip=flip)
    np.testing.assert_array_equal(batch.success.numpy(), np.repeat([1.0, 0.0], 6))
    np.testing.assert_allclose(batch.actions[:6].numpy(),
                               encode_rotation(data.up[rows[:6]], data.forward[rows[:6]]))
    np.testing.assert_allclose(batch.actions[6:].numpy(),
                               encode_rotation(-data.up[rows[:6]], data.forward[rows[:6]]))
    # a flipped copy is counted on its original's running accuracy
    np.testing.assert_array_equal(batch.interaction[:6], batch.interaction[6:])
    np.testing.assert_array_equal(batch.interaction[:6], rows[:6] + 100)
    # both copies read the same contact feature
    np.testing.assert_array_equal(batch.point_index[:6], batch.point_index[6:])
    np.testing.assert_array_equal(batch.cloud_of[:6], batch.cloud_of[6:])


def _row_categories(data, rows):
    return data.category[data.obs_index[rows]]


@pytest.mark.parametrize("aff_share", [0.5, 0.8])
def test_sampler_gives_c_aff_its_share_of_the_clouds_and_flips_a_share(data, aff_share):
    cats = ("cabinet", "faucet", "window")
    s = BalancedSampler(data, cats, clouds=4, per_cloud=8, rng=np.random.default_rng(0),
                        aff_categories=("cabinet",), aff_share=aff_share, flip_share=0.25)
    rows, flips = zip(*(s.sample() for _ in range(400)), strict=True)
    # every cloud gives per_cloud rows (stored and flipped), 2 of them flipped
    assert all(len(r) == 32 and len(f) == 32 and f.sum() == 4 * 2
               for r, f in zip(rows, flips, strict=True))
    c = _row_categories(data, np.concatenate(rows))
    assert (c == "cabinet").mean() == pytest.approx(aff_share, abs=0.04)
    # the rest is split equally between the other categories
    assert (c == "faucet").mean() == pytest.approx((1 - aff_share) / 2, abs=0.04)
    # half of each cloud's rows are positives; flipped copies replace stored negatives
    r, f = np.concatenate(rows), np.concatenate(flips)
    assert (data.success[r] & ~f).mean() == pytest.approx(0.5, abs=0.03)


def test_sampler_without_affordance_categories_draws_categories_equally(data):
    s = BalancedSampler(data, ("cabinet", "faucet", "window"), clouds=3, per_cloud=4,
                        rng=np.random.default_rng(1), aff_share=0.9)
    rows = np.concatenate([s.sample()[0] for _ in range(400)])
    c = _row_categories(data, rows)
    for cat in ("cabinet", "faucet", "window"):
        assert (c == cat).mean() == pytest.approx(1 / 3, abs=0.04)
    assert not np.concatenate([s.sample()[1] for _ in range(5)]).any()  # flip_share 0


@pytest.mark.parametrize("sim_loss", ["bce", "l1"])
def test_similarity_loss_is_bce_or_l1_to_the_running_accuracy(data, sim_loss):
    torch.manual_seed(0)
    model = __import__("w2e_ros.core.model.network", fromlist=["W2EModel"]).W2EModel(SMALL)
    rows = np.flatnonzero(data.interaction_category != "cabinet")[:30]  # C_sim only
    batch = make_batch(data, rows, ("cabinet",), ("cabinet", "faucet", "window"), CPU)
    with torch.no_grad():
        f = model.encode(batch.clouds)[batch.cloud_of, batch.point_index]
        right = ((model.aff_head(f, batch.actions) > 0).float() == batch.success).float()
        logit = model.sim_head(f, batch.actions)
    # a fresh counter: the target is this prediction's correctness
    _, stats = training_losses(model, batch, RunningAccuracy(), sim_loss=sim_loss)
    if sim_loss == "bce":
        expect = torch.nn.functional.binary_cross_entropy_with_logits(logit, right)
    else:
        expect = (torch.sigmoid(logit) - right).abs().mean()
    assert stats["loss_sim"] == pytest.approx(float(expect), rel=1e-4)
    assert stats["loss_aff"] == 0.0 and stats["loss"] == pytest.approx(stats["loss_sim"])
    with pytest.raises(ValueError, match="similarity loss"):
        training_losses(model, batch, RunningAccuracy(), sim_loss="l2")


# --- validation, the best model and the early stop ---------------------------------------

@pytest.fixture(scope="module")
def val_data():
    """Held-out (test-split) instances of the training categories and a novel category,
    plus a train-split cloud the validator must ignore."""
    held = synthetic_data(categories=("cabinet", "faucet", "window", "kettle"), obs_per_cat=2,
                          per_obs=24, seed=11, instance_start=40)
    seen = synthetic_data(categories=("cabinet",), obs_per_cat=1, per_obs=24, seed=12)
    return InteractionData.concat([held, seen])


def test_validator_scores_held_out_instances_of_the_training_categories(val_data):
    v = Validator(val_data, ("cabinet",), ("cabinet", "faucet", "window"), "push")
    assert v.data.num_observations == 8 and (v.data.instance >= 40).all()
    assert set(v.groups) == {"caff", "csim", "novel"}
    assert int(v.groups["novel"].sum()) == 2 * 24
    torch.manual_seed(0)
    model = __import__("w2e_ros.core.model.network", fromlist=["W2EModel"]).W2EModel(SMALL)
    out = v.run(model)
    aff, _ = predict_interactions(model, v.data)
    cats = v.data.interaction_category
    per_cat = [auroc(aff[cats == c], v.data.success[cats == c])
               for c in ("cabinet", "faucet", "window")]  # the novel kettle does not count
    assert out["score"] == pytest.approx(float(np.mean(per_cat)))
    m = v.groups["caff"]
    assert out["caff_auroc"] == pytest.approx(auroc(aff[m], v.data.success[m]))
    assert {"csim_valid_ap", "novel_fscore", "caff_simcorr_auroc"} <= set(out)
    with pytest.raises(ValueError, match="held-out"):
        Validator(val_data.select(categories=["kettle"]), ("cabinet",),
                  ("cabinet", "faucet", "window"), "push")


def test_train_keeps_the_best_validated_model(tmp_path, data, val_data):
    data.save_shard(tmp_path / "data" / "shard-00000.npz")
    out = tmp_path / "run"
    cfg = _cfg(steps=8, val_every=2, patience=100, log_every=100, ckpt_every=100)
    path = train(cfg, tmp_path / "data", out, val_data=val_data, progress=False,
                 model_cfg=SMALL)
    recs = [json.loads(s) for s in (out / "metrics.jsonl").read_text().splitlines()]
    val = [r for r in recs if "val_score" in r]
    assert [r["step"] for r in val] == [2, 4, 6, 8]
    scores = [r["val_score"] for r in val]
    best = val[int(np.argmax(scores))]  # the first of equal scores: later ones are no better
    model, meta = load_model(path, "cpu")
    assert meta["step"] == best["step"] and meta["best_score"] == pytest.approx(max(scores))
    assert val[-1]["best_step"] == best["step"]
    # model.pt holds the weights that scored best, state.pt the latest
    v = Validator(val_data, ("cabinet",), ("cabinet", "faucet", "window"), "push")
    assert v.run(model)["score"] == pytest.approx(max(scores), abs=1e-6)
    state = torch.load(out / "state.pt", weights_only=True)
    assert state["step"] == 8
    same = all(torch.equal(state["model"][k], w) for k, w in model.state_dict().items())
    assert same == (best["step"] == 8)
    assert (out / "curves.png").stat().st_size > 0


def test_train_stops_when_validation_levels_off(tmp_path, data, val_data):
    data.save_shard(tmp_path / "data" / "shard-00000.npz")
    out = tmp_path / "run"
    # lr 0: the score never improves after the first validation
    cfg = _cfg(steps=50, lr=0.0, val_every=2, patience=3, log_every=100, ckpt_every=100)
    path = train(cfg, tmp_path / "data", out, val_data=val_data, progress=False,
                 model_cfg=SMALL)
    recs = [json.loads(s) for s in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in recs] == [2, 4, 6, 8]  # best at 2, then 3 without progress
    assert len({r["val_score"] for r in recs}) == 1
    _, meta = load_model(path, "cpu")
    assert meta["step"] == 2
    state = torch.load(out / "state.pt", weights_only=True)
    assert state["step"] == 8
    assert state["best"].tolist() == [pytest.approx(recs[0]["val_score"]), 2.0, 3.0]


def test_patience_cannot_stop_a_curve_that_still_rises():
    from w2e_ros.core.model.training import still_rising

    rng = np.random.default_rng(0)
    # a noisy climb: no new best in the last few checks, yet the trend is up
    assert still_rising([0.70, 0.74, 0.72, 0.76, 0.75, 0.78, 0.77])
    assert not still_rising([0.80, 0.79, 0.80, 0.78, 0.80, 0.79])  # flat
    assert not still_rising([0.80, 0.78, 0.76, 0.74])  # falling
    assert not still_rising([0.7, 0.8])  # too few checks to tell
    flat = 0.8 + 0.01 * rng.standard_normal((200, 7))
    assert np.mean([still_rising(f) for f in flat]) < 0.25  # noise alone rarely reads as a rise


def test_trainer_levels_off_only_without_a_new_best_and_without_a_rise(data):
    t = Trainer(_cfg(), data, SMALL, device=CPU)
    t.bad_validations = 3
    t.val_scores = [0.70, 0.74, 0.72, 0.76, 0.75, 0.78, 0.77]
    assert not t.levelled_off(patience=3) and not t.levelled_off(patience=6)
    t.val_scores = [0.78, 0.80, 0.79, 0.80, 0.79]
    assert t.levelled_off(patience=3)
    t.bad_validations = 2
    assert not t.levelled_off(patience=3)


def test_calibration_refits_only_the_similarity_head_to_the_final_correctness(data):
    from w2e_ros.core.model.training import calibrate_similarity

    torch.manual_seed(0)
    model = __import__("w2e_ros.core.model.network", fromlist=["W2EModel"]).W2EModel(SMALL)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    stats = calibrate_similarity(model, data, ("cabinet", "faucet", "window"), steps=80,
                                 batch=64)
    after = model.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith("sim_head.") for k in changed)
    # the re-fitted head ranks the (unchanged) affordance head's right answers first
    aff, sim = predict_interactions(model, data, cache=None)
    correct = (aff > 0.5) == data.success
    assert stats["rows"] == data.num_interactions
    assert stats["train_correct_rate"] == pytest.approx(correct.mean())
    assert auroc(sim, correct) > 0.6


def test_replay_pack_samples_each_primitive_keeps_only_its_clouds_and_the_cli_writes_it(
        tmp_path):
    import subprocess
    import sys

    from w2e_ros.core.model.network import W2EModel, save_model
    from w2e_ros.core.model.training import REPLAY_PACK, replay_pack

    data = InteractionData.concat([
        synthetic_data(obs_per_cat=5, per_obs=40, primitive="push"),
        synthetic_data(obs_per_cat=5, per_obs=40, primitive="pull", seed=1)])
    pack = replay_pack(data, "w2e", "cfw", ("push", "pull"), fraction=0.05, seed=0)
    assert (pack.primitive == "push").sum() == 30 and (pack.primitive == "pull").sum() == 30
    assert pack.meta[REPLAY_PACK]["of"] == [600, 600]
    # only the clouds the sampled rows refer to, every one of them used
    assert np.array_equal(np.unique(pack.obs_index), np.arange(pack.num_observations))
    assert pack.num_observations < data.num_observations
    # the rows are real training rows: same contact point, frame and label
    key = {(tuple(np.round(p, 5)), tuple(np.round(u, 5)), bool(s)) for p, u, s in
           zip(data.contact_points, data.up, data.success, strict=True)}
    assert all((tuple(np.round(p, 5)), tuple(np.round(u, 5)), bool(s)) in key for p, u, s in
               zip(pack.contact_points, pack.up, pack.success, strict=True))
    assert len({(int(o), int(i)) for o, i in zip(pack.obs_seed[pack.obs_index],
                                                 pack.point_index, strict=True)}) <= 60

    # as typed: the same pack from the command line
    data.save_shard(tmp_path / "train" / "shard-00000.npz")
    model = save_model(tmp_path / "m.pt", W2EModel(SMALL), {"method": "w2e", "combo": "cfw"})
    out = tmp_path / "pack"
    proc = subprocess.run([sys.executable, "-m", "w2e_ros.cli", "replay-pack", "--data",
                           str(tmp_path / "train"), "--model", str(model), "--fraction", "0.05",
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "60 interactions" in proc.stdout
    loaded = InteractionData.load(out)
    assert np.array_equal(loaded.success, pack.success)
    assert loaded.meta[REPLAY_PACK]["fraction"] == 0.05
    bad = subprocess.run([sys.executable, "-m", "w2e_ros.cli", "replay-pack", "--data",
                          str(tmp_path / "train"), "--model", str(model), "--fraction", "0",
                          "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--fraction" in bad.stderr


def test_w2e_calibrate_balanced_lowers_the_similarity_where_successes_are_missed(tmp_path):
    """A head that predicts "fails" everywhere is right on every failure: calibrated on the
    data's prior it calls everything familiar; weighting successes and failures equally
    (--balanced) makes the geometry of the missed successes unfamiliar."""
    import subprocess
    import sys

    from w2e_ros.core.model.network import W2EModel, load_model, save_model

    data = synthetic_data(obs_per_cat=6, per_obs=48, primitive="pull", seed=4)
    assert 0.05 < data.success.mean() < 0.4
    data.save_shard(tmp_path / "train" / "shard-00000.npz")
    torch.manual_seed(0)
    model = W2EModel(SMALL)
    with torch.no_grad():  # the affordance head says "fails" everywhere
        model.aff_head.out.bias.fill_(-20.0)
    src = save_model(tmp_path / "m.pt", model, {"method": "w2e", "combo": "cfw",
                                                "primitive": "pull"})
    sims = {}
    for name, flag in (("natural", []), ("balanced", ["--balanced"])):
        out = tmp_path / f"{name}.pt"
        proc = subprocess.run(
            [sys.executable, "-m", "w2e_ros.cli", "calibrate", "--model", str(src), "--data",
             str(tmp_path / "train"), "--out", str(out), "--steps", "300", "--threads", "1",
             *flag], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        calibrated, meta = load_model(out, "cpu")
        assert meta["calibration"]["balanced"] == float(bool(flag))
        _, sims[name] = predict_interactions(calibrated, data, cache=None)
    pos = data.success
    # natural: familiar everywhere (the head is right on the ~80 % that fail)
    assert sims["natural"].mean() > 0.6
    # balanced: the successes' geometry is clearly less familiar than the failures'
    assert sims["balanced"][pos].mean() < sims["natural"][pos].mean() - 0.1
    assert auroc(1 - sims["balanced"], pos) > 0.6


def test_w2e_train_ablation_flags_drop_the_similarity_loss(tmp_path):
    """``--sim-weight 0`` trains the affordance head alone (the total loss is the affordance
    loss), ``--sim-detach-encoder`` keeps the similarity loss out of the encoder; both are
    recorded in the run's config so an ablation can be told from the default."""
    import subprocess
    import sys

    synthetic_data(obs_per_cat=2, per_obs=16, num_points=2048).save_shard(
        tmp_path / "data" / "shard-00000.npz")
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "w2e_ros.cli", "train", "--data", str(tmp_path / "data"),
         "--out", str(out), "--steps", "2", "--clouds", "2", "--per-cloud", "8",
         "--sim-weight", "0", "--sim-detach-encoder", "--calibrate-steps", "0",
         "--log-every", "1", "--threads", "1", "--no-progress"],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    cfg = json.loads((out / "config.json").read_text())["train"]
    assert cfg["sim_weight"] == 0.0 and cfg["sim_detach_encoder"] is True
    lines = [json.loads(s) for s in (out / "metrics.jsonl").read_text().splitlines()]
    assert all(r["loss_sim"] > 0 for r in lines)  # still measured ...
    assert all(r["loss"] == pytest.approx(r["loss_aff"]) for r in lines)  # ... not trained


def test_w2e_calibrate_gives_a_where2act_model_a_similarity_on_its_training_categories(
        tmp_path):
    """The 'wide' variant: a where2act model (affordance on all three training categories)
    gets a similarity head fitted to where its affordance head is right on them, and says so
    in its meta (the explorer then trains the similarity too); a fulldata model, which has
    no held-out categories to be familiar or not with, is refused with a clear error."""
    import subprocess
    import sys

    from w2e_ros.core.model.network import W2EModel, load_model, save_model

    data = synthetic_data(obs_per_cat=4, per_obs=32, seed=5)
    data.save_shard(tmp_path / "train" / "shard-00000.npz")
    torch.manual_seed(0)
    cmd = [sys.executable, "-m", "w2e_ros.cli", "calibrate", "--data", str(tmp_path / "train"),
           "--steps", "200", "--threads", "1"]
    for method in ("where2act", "fulldata"):
        src = save_model(tmp_path / f"{method}.pt", W2EModel(SMALL),
                         {"method": method, "combo": "cfw", "primitive": "push"})
        out = tmp_path / f"{method}_w.pt"
        proc = subprocess.run([*cmd, "--model", str(src), "--out", str(out)],
                              capture_output=True, text=True, timeout=300)
        if method == "fulldata":
            assert proc.returncode != 0 and "no similarity categories" in proc.stderr
            continue
        assert proc.returncode == 0, proc.stderr
        model, meta = load_model(out, "cpu")
        assert meta["method"] == "where2act"
        assert meta["sim_categories"] == meta["aff_categories"] == ["cabinet", "faucet", "window"]
        aff, sim = predict_interactions(model, data, cache=None)
        assert auroc(sim, (aff > 0.5) == data.success) > 0.6  # it ranks its own correctness


def test_w2e_calibrate_combo_retargets_a_model_to_a_combination_with_the_same_c_aff(tmp_path):
    """cfw and csr share C_aff (cabinet): the affordance head is the same, only the
    similarity's categories change; a combination with another C_aff is refused as typed."""
    import subprocess
    import sys

    from w2e_ros.core.model.network import W2EModel, load_model, save_model

    data = InteractionData.concat([
        synthetic_data(categories=("cabinet", "faucet", "window"), obs_per_cat=3, per_obs=24,
                       primitive="pull", seed=1),
        synthetic_data(categories=("switch", "refrigerator"), obs_per_cat=3, per_obs=24,
                       primitive="pull", seed=2)])
    data.save_shard(tmp_path / "train" / "shard-00000.npz")
    torch.manual_seed(0)
    src = save_model(tmp_path / "m.pt", W2EModel(SMALL), {"method": "w2e", "combo": "cfw",
                                                          "primitive": "pull"})
    before, _ = load_model(src, "cpu")

    def calibrate(combo: str, out: Path) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "w2e_ros.cli", "calibrate", "--model", str(src), "--data",
             str(tmp_path / "train"), "--out", str(out), "--steps", "50", "--threads", "1",
             "--combo", combo], capture_output=True, text=True, timeout=300)

    proc = calibrate("csr", tmp_path / "csr.pt")
    assert proc.returncode == 0, proc.stderr
    model, meta = load_model(tmp_path / "csr.pt", "cpu")
    assert meta["combo"] == "csr" and meta["retargeted_from"] == "cfw"
    assert meta["aff_categories"] == ["cabinet"]
    assert meta["sim_categories"] == ["cabinet", "switch", "refrigerator"]
    # fitted on the csr categories' rows only, and the affordance head is untouched
    assert meta["calibration"]["rows"] == data.select(
        categories=("cabinet", "switch", "refrigerator")).num_interactions
    sd, ref = model.state_dict(), before.state_dict()
    assert all(torch.equal(sd[k], ref[k]) for k in sd if not k.startswith("sim_head."))
    assert any(not torch.equal(sd[k], ref[k]) for k in sd if k.startswith("sim_head."))

    bad = calibrate("tfr", tmp_path / "tfr.pt")
    assert bad.returncode == 2 and "C_aff table" in bad.stderr
    assert not (tmp_path / "tfr.pt").exists()


def test_yaw_augmentation_turns_clouds_and_their_actions_together(data):
    """Each cloud and the actions on it turn by the same angle about the vertical: heights,
    distances and every action's angle to the cloud's geometry are kept, labels untouched."""
    from w2e_ros.core.model.training import rotate_yaw

    t = Trainer(_cfg(), data, SMALL, device=CPU)
    b = t.next_batch()
    angles = np.array([0.3, -1.2, 2.5])[:len(b.clouds)]
    r = rotate_yaw(b, angles)
    torch.testing.assert_close(r.clouds[..., 2], b.clouds[..., 2])  # heights kept
    torch.testing.assert_close(r.clouds.norm(dim=-1), b.clouds.norm(dim=-1))
    torch.testing.assert_close(r.actions[:, 2], b.actions[:, 2])
    torch.testing.assert_close(r.actions[:, 5], b.actions[:, 5])
    # the contact point and the approach turn together: their dot product is kept
    p0 = b.clouds[b.cloud_of, b.point_index]
    p1 = r.clouds[r.cloud_of, r.point_index]
    torch.testing.assert_close((p1 * r.actions[:, :3]).sum(-1), (p0 * b.actions[:, :3]).sum(-1))
    c = np.cos(angles[0])
    k = int((b.cloud_of == 0).nonzero()[0])
    torch.testing.assert_close((r.actions[k, :2] * b.actions[k, :2]).sum(),
                               b.actions[k, :2].norm() ** 2 * torch.tensor(c, dtype=torch.float32))
    assert torch.equal(r.success, b.success) and torch.equal(r.point_index, b.point_index)
    # off by default; on, the trainer draws its angles from its seeded generator
    on = Trainer(_cfg(augment_yaw=True), data, SMALL, device=CPU)
    again = Trainer(_cfg(augment_yaw=True), data, SMALL, device=CPU)
    torch.testing.assert_close(on.next_batch().clouds, again.next_batch().clouds)
    assert not torch.allclose(Trainer(_cfg(augment_yaw=True), data, SMALL, device=CPU)
                              .next_batch().clouds, b.clouds)


def test_cosine_schedule_decays_to_its_floor_and_a_resumed_run_follows_it(tmp_path, data):
    t = Trainer(_cfg(steps=100, lr=1e-3, lr_schedule="cosine"), data, SMALL, device=CPU)
    assert t.learning_rate() == pytest.approx(1e-3)
    t.step = 50
    assert t.learning_rate() == pytest.approx(1e-3 * (0.05 + 0.95 * 0.5))
    t.step = 100
    assert t.learning_rate() == pytest.approx(5e-5)
    t.step = 0
    t.train_step()
    assert t.opt.param_groups[0]["lr"] == pytest.approx(1e-3)
    assert Trainer(_cfg(), data, SMALL, device=CPU).learning_rate() == _cfg().lr  # constant
    # the rate is a function of the step: a run resumed at step 2 uses step 2's rate
    data.save_shard(tmp_path / "data" / "shard-00000.npz")
    cfg = _cfg(steps=4, lr_schedule="cosine", ckpt_every=2)
    train(replace(cfg, steps=2), tmp_path / "data", tmp_path / "run", progress=False,
          model_cfg=SMALL)
    resumed = Trainer(cfg, data, SMALL, device=CPU)
    resumed.resume(tmp_path / "run")
    assert resumed.step == 2
    assert resumed.learning_rate() == pytest.approx(1e-3 * (0.05 + 0.95 * 0.5))


def test_training_data_keeps_train_and_extra_instances_and_never_explore_or_test_ones():
    starts = {"train": 0, "explore": 30, "test": 40, "extra": 300}
    data = InteractionData.concat([synthetic_data(obs_per_cat=2, instance_start=s, seed=i)
                                   for i, s in enumerate(starts.values())])
    kept = load_training_data_from(data, "where2act", "cfw", "push")
    assert sorted(set(kept.instance.tolist())) == [0, 1, 300, 301]
    # the validator judges what training never saw: explore / test, not extra
    held = Validator(data, ("cabinet", "faucet", "window"), (), "push").data
    assert sorted(set(held.instance.tolist())) == [30, 31, 40, 41]
