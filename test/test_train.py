"""Training: the C_aff / C_sim split, the running-accuracy target, loss, seeds, resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from synthetic import synthetic_data

from w2e_ros.core.config import ModelConfig, TrainConfig
from w2e_ros.core.model import load_model
from w2e_ros.core.train import (
    RunningAccuracy,
    Trainer,
    make_batch,
    method_categories,
    train,
    training_losses,
)

torch.set_num_threads(2)
SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def data():
    return synthetic_data(obs_per_cat=4, per_obs=24)


def _cfg(**kw) -> TrainConfig:
    base = dict(method="w2e", combo="cfw", primitive="push", steps=4, clouds_per_batch=3,
                interactions_per_cloud=8, seed=3, log_every=2, ckpt_every=2)
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
    model = __import__("w2e_ros.core.model", fromlist=["W2EModel"]).W2EModel(SMALL)
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
    model = __import__("w2e_ros.core.model", fromlist=["W2EModel"]).W2EModel(SMALL)
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
    model = __import__("w2e_ros.core.model", fromlist=["W2EModel"]).W2EModel(SMALL).train()
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
    from w2e_ros.core.collect import CollectConfig, collect

    collect(CollectConfig(out=str(tmp_path / "data"), categories=["cabinet", "faucet", "window"],
                          observations=2, interactions=24, primitives=("push",), workers=1))
    from w2e_ros.core.train import load_training_data

    data = load_training_data(tmp_path / "data", "w2e", "cfw", "push")
    assert data.points.shape[1:] == (2048, 3) and data.success.any()
    trainer = Trainer(_cfg(clouds_per_batch=3, interactions_per_cloud=16), data, device=CPU)
    batch = trainer.next_batch()
    assert batch.aff_mask.any() and (~batch.aff_mask).any()  # C_aff and other C_sim clouds
    first = trainer.train_step(batch)
    for _ in range(15):
        last = trainer.train_step(batch)
    assert last["loss_aff"] < 0.7 * first["loss_aff"]
    assert last["loss"] < first["loss"]
