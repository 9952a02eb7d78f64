"""The update guard: an update that predicts the explored set worse than the prior is not
served; an accepted one is exactly the unguarded fit; the average is the stated mix."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic import synthetic_data

from w2e_ros.core.exploration.config import FinetuneConfig
from w2e_ros.core.exploration.finetune import W2EExplorer
from w2e_ros.core.exploration.guard import fold_of_rows, judge, mix
from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.model.predict import FeatureCache

torch.set_num_threads(2)
SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))
SIM = ("cabinet", "faucet", "window")


@pytest.fixture(scope="module")
def novel():
    return synthetic_data(categories=("kettle", "bucket"), obs_per_cat=4, per_obs=16, seed=5,
                          instance_start=30)


def _explorer(model: W2EModel | None = None, **kw) -> W2EExplorer:
    torch.manual_seed(0)
    cfg = FinetuneConfig(**{"finetune_steps": 60, "finetune_min_steps": 60,
                            "finetune_lr": 3e-3, "anchor": 0.0, "prior": 0.0, **kw})
    return W2EExplorer(model or W2EModel(SMALL), cfg, None, ("cabinet",), SIM, seed=0,
                       features=FeatureCache())


def _state(ex: W2EExplorer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in ex.model.state_dict().items()}


@pytest.fixture(scope="module")
def fitted(novel):
    """A model that already knows the explored set: the prior an update can only spoil."""
    ex = _explorer(finetune_steps=400, finetune_min_steps=400)
    ex.add_data(novel)
    ex.fit()
    return ex.model


def test_judge_keeps_an_update_only_when_it_predicts_held_out_better():
    y = np.array([True, False, False, True, False])
    good, bad = np.where(y, 0.8, 0.2), np.where(y, 0.3, 0.6)
    assert judge(bad, good, y, "loss")[0] and not judge(good, bad, y, "loss")[0]
    assert judge(bad, good, y, "auroc")[0] and not judge(good, bad, y, "auroc")[0]
    assert judge(good, bad, np.zeros(5, bool), "loss")[0]  # one class: nothing to judge


def test_folds_keep_a_cloud_together_and_spread_the_successes():
    cloud = np.repeat(np.arange(10), 3)
    success = np.zeros(30, bool)
    success[[0, 3, 6, 9, 12]] = True  # clouds 0-4 hold a success each
    fold = fold_of_rows(cloud, success, 5, np.random.default_rng(0))
    for c in range(10):
        assert len(set(fold[cloud == c])) == 1
    assert sorted(fold[success]) == [0, 1, 2, 3, 4]


def test_accept_rejects_an_update_that_raises_the_held_out_loss(novel, fitted):
    """A prior that already fits the explored set and a fine-tuning that runs away (lr 10):
    the out-of-fold loss rises, the model serves the prior, its last fit is still kept."""
    prior = {k: v.detach().clone() for k, v in fitted.state_dict().items()}
    ex = _explorer(_copy(fitted), guard="accept", finetune_lr=10.0)
    ex.add_data(novel)
    stats = ex.fit()
    assert stats["guard_accepted"] == 0.0 and stats["guard_adapted"] > stats["guard_prior"]
    for k, v in _state(ex).items():
        torch.testing.assert_close(v, prior[k])
    assert any(not torch.equal(v, prior[k]) for k, v in ex.adapted.items())


def test_an_accepted_update_is_exactly_the_unguarded_one(novel):
    """A random-weight prior, a learnable explored set: the update passes the check, and the
    trial fits left no trace (same weights as with the guard off)."""
    off, on = _explorer(guard="off"), _explorer(guard="accept")
    for ex in (off, on):
        ex.add_data(novel)
    off.fit()
    stats = on.fit()
    assert stats["guard_accepted"] == 1.0 and stats["guard_adapted"] < stats["guard_prior"]
    for k, v in _state(off).items():
        torch.testing.assert_close(_state(on)[k], v, rtol=0, atol=0)


def test_average_serves_the_mix_and_fits_on_from_the_adapted_weights(novel):
    off, avg = _explorer(guard="off"), _explorer(guard="average", guard_weight=0.25)
    prior = _state(avg)
    for ex in (off, avg):
        ex.add_data(novel)
        ex.fit()
        ex.fit()  # the second fit continues from the adapted weights, not from the mix
    for k, v in mix(prior, _state(off), 0.25).items():
        torch.testing.assert_close(_state(avg)[k], v)


def _copy(model: W2EModel) -> W2EModel:
    import copy

    return copy.deepcopy(model)
