"""Metrics against hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from w2e_ros.core.metrics import affordance_fscore_from_probs, fscore, mean_std, success_rate


def test_fscore_hand_computed():
    # 10 interactions: tp=3, fp=1, fn=2, tn=4 -> P=3/4, R=3/5, F=2PR/(P+R)=2/3
    label = np.array([1, 1, 1, 1, 1, 0, 0, 0, 0, 0], bool)
    pred = np.array([1, 1, 1, 0, 0, 1, 0, 0, 0, 0], bool)
    r = fscore(pred, label)
    assert (r["tp"], r["fp"], r["fn"], r["n"]) == (3, 1, 2, 10)
    assert r["precision"] == pytest.approx(0.75) and r["recall"] == pytest.approx(0.6)
    assert r["fscore"] == pytest.approx(2 / 3)
    assert r["accuracy"] == pytest.approx(0.7)


def test_fscore_pools_counts_instead_of_averaging_batches():
    # batch A: tp=1 fp=0 fn=0 (F=1); batch B: tp=1 fp=3 fn=3 (F=0.25); the mean of the two
    # is 0.625, but over all 8 interactions P=2/5, R=2/5, F=0.4
    la = np.array([1], bool)
    pa = np.array([1], bool)
    lb = np.array([1, 1, 1, 1, 0, 0, 0], bool)
    pb = np.array([1, 0, 0, 0, 1, 1, 1], bool)
    r = fscore(np.concatenate([pa, pb]), np.concatenate([la, lb]))
    assert r["fscore"] == pytest.approx(0.4)


def test_fscore_edge_cases_and_threshold():
    assert fscore(np.zeros(4, bool), np.ones(4, bool))["fscore"] == 0.0
    assert fscore(np.zeros(4, bool), np.zeros(4, bool))["fscore"] == 0.0
    r = affordance_fscore_from_probs(np.array([0.5, 0.51, 0.9]), np.array([1, 1, 0], bool))
    assert (r["tp"], r["fp"], r["fn"]) == (1, 1, 1)  # 0.5 is not > 0.5
    with pytest.raises(ValueError):
        fscore(np.zeros(3, bool), np.zeros(4, bool))


def test_success_rate_and_mean_std():
    assert success_rate([True, False, True, True]) == 0.75
    assert math.isnan(success_rate([]))
    m, s = mean_std([0.2, 0.4, float("nan")])
    assert m == pytest.approx(0.3) and s == pytest.approx(0.1)


# --- evaluation of a model (w2e_ros.core.evaluate) ---------------------------------------

def test_predictions_match_the_model_on_each_interaction():
    import torch
    from synthetic import RuleWorld, synthetic_data

    from w2e_ros.core.config import ModelConfig
    from w2e_ros.core.evaluate import SuccessProbe, fscore_by_category, predict_interactions
    from w2e_ros.core.model import W2EModel

    torch.manual_seed(0)
    model = W2EModel(ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))).eval()
    data = synthetic_data(categories=("kettle", "bucket"), obs_per_cat=3, per_obs=10)
    aff, sim = predict_interactions(model, data, chunk=4)  # chunks cut across categories
    from w2e_ros.core.actions import encode_rotation

    with torch.no_grad():
        logit, s = model(torch.from_numpy(data.points), torch.from_numpy(data.obs_index).long(),
                         torch.from_numpy(data.point_index).long(),
                         torch.from_numpy(encode_rotation(data.up, data.forward)))
    np.testing.assert_allclose(aff, torch.sigmoid(logit).numpy(), atol=1e-5)
    np.testing.assert_allclose(sim, s.numpy(), atol=1e-5)
    per_cat = fscore_by_category(model, data)
    assert set(per_cat) == {"kettle", "bucket", "all", "mean"}
    assert per_cat["all"]["n"] == data.num_interactions

    world = RuleWorld(data)
    probe = SuccessProbe(world, [0, 1, 2], "push", points_per_object=8, dirs_per_point=2)
    r1 = probe.run(model)
    r2 = probe.run(model)  # cached outcomes: nothing executed twice
    assert r1 == r2 and len(world.executed) == 3
    assert 0.0 <= r1["all"] <= 1.0


def test_validation_instances_are_neither_explored_nor_test():
    from w2e_ros.core.categories import load_categories
    from w2e_ros.core.evaluate import evaluation_instances, evaluation_targets

    cats = load_categories()
    test = set(cats.instances("kettle", "test"))
    explored = set(cats.instances("kettle", "explore")[:5])
    held_out = evaluation_instances("kettle", validate=True, explored=5)
    assert held_out and not (set(held_out) & (test | explored))
    assert set(evaluation_instances("kettle")) == test
    assert {t.instance for t in evaluation_targets(["kettle"], 3, validate=True, explored=5)} \
        <= set(held_out)
    with pytest.raises(ValueError, match="explore fewer"):
        evaluation_instances("kettle", validate=True, explored=len(cats.instances("kettle",
                                                                               "explore")))
