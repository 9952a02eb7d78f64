"""The few-shot loop: stops at the bar and at the budget, snapshots, learns from what it does."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic import Cloud, RuleWorld, synthetic_data

from sim_bridge.types import TrialResult
from w2e_ros.core.config import ExploreConfig, ModelConfig
from w2e_ros.core.explore import Executed, W2EExplorer, explore, sample_candidates
from w2e_ros.core.model import W2EModel
from w2e_ros.core.strategies import get_strategy

torch.set_num_threads(2)
SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))


@pytest.fixture(scope="module")
def novel():
    return synthetic_data(categories=("kettle", "bucket"), obs_per_cat=3, seed=5,
                          instance_start=30)


@pytest.fixture(scope="module")
def replay():
    return synthetic_data(obs_per_cat=4, per_obs=24, seed=1)


def _explorer(replay, sim_bias: float | None = None, seed: int = 0, **kw) -> W2EExplorer:
    torch.manual_seed(seed)
    model = W2EModel(SMALL)
    if sim_bias is not None:  # push every similarity to ~0 or ~1
        with torch.no_grad():
            model.sim_head.out.weight.zero_()
            model.sim_head.out.bias.fill_(sim_bias)
    kw = {"points_per_object": 32, "dirs_per_point": 4, "finetune_steps": 2, **kw}
    cfg = ExploreConfig(**kw)
    return W2EExplorer(model, cfg, replay, ("cabinet",), ("cabinet", "faucet", "window"),
                       seed=seed)


def test_candidates_face_the_surface_and_stay_on_the_mask(novel):
    cloud = Cloud(novel.points[0], novel.normals[0], novel.movable[0])
    c = sample_candidates(cloud, 20, 3, np.random.default_rng(0), mask=cloud.movable)
    assert len(c) == 60 and cloud.movable[c.point_index].all()
    assert (np.sum(c.up * cloud.normals[c.point_index], axis=1) < 0).all()
    np.testing.assert_allclose(np.sum(c.up * c.forward, axis=1), 0, atol=1e-5)


def test_loop_stops_at_the_bar_before_spending_anything(novel, replay):
    exp = _explorer(replay, sim_bias=8.0)
    world = RuleWorld(novel)
    res = explore(exp, world, list(range(6)), get_strategy("similarity"), exp.cfg, "push")
    assert res.stopped == "bar" and res.steps == [] and world.executed == []
    assert res.mean_similarity[0] > 0.9
    assert set(res.snapshots) == {0, 1, 2, 5}


def test_loop_spends_the_budget_when_similarity_stays_low(novel, replay):
    exp = _explorer(replay, sim_bias=-8.0, budget=3, snapshot_budgets=(1, 2, 5))
    world = RuleWorld(novel)
    res = explore(exp, world, list(range(6)), get_strategy("similarity"), exp.cfg, "push")
    assert res.stopped == "budget" and len(res.steps) == 3 == len(world.executed)
    assert [s.step for s in res.steps] == [1, 2, 3]
    assert len(res.mean_similarity) == 4
    # snapshots differ across budgets (the model was fine-tuned in between); 5 = final
    w = "aff_head.out.bias"
    assert not torch.equal(res.snapshots[0][w], res.snapshots[1][w])
    assert not torch.equal(res.snapshots[1][w], res.snapshots[2][w])
    assert torch.equal(res.snapshots[5][w], exp.snapshot()[w])


def test_similarity_strategy_executes_the_lowest_similarity_action(novel, replay):
    exp = _explorer(replay, budget=1)
    world = RuleWorld(novel)
    seen = {}

    class Spy:
        def score(self, clouds, cands):
            out = exp.score(clouds, cands)
            seen.setdefault("scored", out)  # the first scoring chooses the first action
            seen.setdefault("cands", cands)
            return out

        def update(self, *a):
            return exp.update(*a)

        def snapshot(self):
            return exp.snapshot()

    explore(Spy(), world, list(range(6)), get_strategy("similarity"), exp.cfg, "push")
    sims = [s.similarity for s in seen["scored"]]
    obj = int(np.argmin([s.min() for s in sims]))
    i = int(np.argmin(sims[obj]))
    target, action = world.executed[0]
    assert target == obj
    np.testing.assert_allclose(action.up, seen["cands"][obj].up[i], atol=1e-6)


def test_budget_counts_interactions_per_category_one_update_per_round(novel, replay):
    exp = _explorer(replay, sim_bias=-8.0, budget=2, snapshot_budgets=(1, 2))
    world = RuleWorld(novel)
    updates = []

    class Counting:
        def score(self, clouds, cands):
            return exp.score(clouds, cands)

        def update(self, executed):
            updates.append(len(executed))
            return exp.update(executed)

        def snapshot(self):
            return exp.snapshot()

    group = {i: str(novel.category[i]) for i in range(6)}
    res = explore(Counting(), world, list(range(6)), get_strategy("similarity"), exp.cfg,
                  "push", group_of=group.__getitem__)
    assert updates == [2, 2]  # two categories: one interaction each, one update per round
    assert [(s.round, s.group) for s in res.steps] == [
        (1, "kettle"), (1, "bucket"), (2, "kettle"), (2, "bucket")]
    assert all(str(novel.category[t]) == s.group
               for (t, _), s in zip(world.executed, res.steps, strict=True))


def test_none_strategy_spends_nothing_and_snapshots_the_initial_model(novel, replay):
    exp = _explorer(replay)
    world = RuleWorld(novel)
    res = explore(exp, world, [0, 1], get_strategy("none"), exp.cfg, "push")
    assert res.stopped == "none" and not world.executed
    assert all(torch.equal(res.snapshots[b]["aff_head.out.bias"],
                           res.snapshots[0]["aff_head.out.bias"]) for b in (1, 2, 5))


def test_fine_tuning_fits_the_explored_interactions(novel):
    # no replay: the explored interaction alone must be learned (replay only anchors)
    exp = _explorer(None, finetune_steps=30, finetune_lr=1e-3)
    cloud = Cloud(novel.points[0], novel.normals[0], novel.movable[0])
    cands = sample_candidates(cloud, 16, 2, np.random.default_rng(1), mask=cloud.movable)
    i = int(np.argmin(cands.up[:, 2]))  # straight into the handle: a success
    before = exp.score([cloud], [cands])[0].affordance[i]
    exp.update([Executed(cloud, cands, i, TrialResult(True, True, np.array([0.05]), 0, "door"))])
    after = exp.score([cloud], [cands])[0].affordance[i]
    assert after > max(before, 0.6)


@pytest.mark.slow
def test_loop_explores_simulated_objects_and_learns_from_the_outcomes():
    from w2e_ros.core.evaluate import SuccessProbe, evaluation_targets
    from w2e_ros.core.explore import explore_targets
    from w2e_ros.core.sim_world import SimWorld

    world = SimWorld()
    torch.manual_seed(0)
    model = W2EModel()
    cfg = ExploreConfig(budget=2, points_per_object=16, dirs_per_point=2, finetune_steps=1,
                        snapshot_budgets=(1, 2))
    exp = W2EExplorer(model, cfg, None, ("cabinet",), ("cabinet", "faucet", "window"))
    targets = explore_targets(["kettle"], per_category=2)
    assert [t.instance for t in targets] == [30, 31]
    res = explore(exp, world, targets, get_strategy("similarity"), cfg, "pull")
    assert len(res.steps) == 2 and res.stopped == "budget"
    assert all(s.target.startswith("kettle/") for s in res.steps)
    assert exp.explored and all(e.cloud.shape == (2048, 3) for e in exp.explored)
    probe = SuccessProbe(world, evaluation_targets(["kettle"], 2), "pull", points_per_object=8,
                         dirs_per_point=2)
    r = probe.run(exp.model_at(res.snapshots[2]))
    assert set(r) == {"kettle", "all", "mean"} and 0.0 <= r["all"] <= 1.0


def test_explored_batch_weighs_successes_and_failures_equally(novel):
    exp = _explorer(None, finetune_steps=0)
    cloud = Cloud(novel.points[0], novel.normals[0], novel.movable[0])
    cands = sample_candidates(cloud, 8, 1, np.random.default_rng(2))
    outcomes = [True, False, False, False]
    exp.update([Executed(cloud, cands, k, TrialResult(True, ok, np.array([0.0]), 0, "door"))
                for k, ok in enumerate(outcomes)])
    batch = exp._explored_batch(np.arange(4))
    w, y = batch.weight.numpy(), batch.success.numpy()
    assert w[y == 1].sum() == pytest.approx(w[y == 0].sum())
    assert w.mean() == pytest.approx(1.0)


@pytest.mark.slow
@pytest.mark.parametrize("budget_per, per_round", [("category", 2), ("object", 4)])
def test_budget_per_object_gives_every_explore_instance_its_own_interactions(budget_per,
                                                                             per_round):
    from w2e_ros.core.explore import fewshot
    from w2e_ros.core.sim_world import SimWorld

    torch.manual_seed(0)
    model = W2EModel(SMALL)
    cfg = ExploreConfig(budget=2, points_per_object=8, dirs_per_point=2, finetune_steps=2,
                        finetune_clouds=3, snapshot_budgets=(1, 2), sim_bar=1.01,
                        budget_per=budget_per)
    meta = {"aff_categories": ["cabinet"], "sim_categories": ["cabinet", "faucet", "window"]}
    runs = fewshot(model, meta, SimWorld(SMALL.num_points), ["kettle", "door"],
                   get_strategy("random"), cfg, "push", per_category=2)
    res, explorer = runs["all"]
    assert len(res.steps) == 2 * per_round and len(explorer.explored) == 2 * per_round
    for rnd in (1, 2):
        targets = [s.target for s in res.steps if s.round == rnd]
        assert len(targets) == per_round
        if budget_per == "object":  # each of the 4 instances once per round
            assert sorted(t.rsplit("/", 1)[0] for t in targets) == [
                "door/30", "door/31", "kettle/30", "kettle/31"]
    with pytest.raises(ValueError, match="budget_per"):
        fewshot(model, meta, SimWorld(SMALL.num_points), ["kettle"], get_strategy("random"),
                ExploreConfig(budget_per="instance"), "push", per_category=1)
