"""The few-shot loop: stops at the bar and at the budget, snapshots, learns from what it does."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from synthetic import Cloud, RuleWorld, synthetic_data

from w2e_ros.core.exploration.config import ExploreConfig, FinetuneConfig
from w2e_ros.core.exploration.explore import Executed, cloud_proposer, explore, sample_candidates
from w2e_ros.core.exploration.finetune import W2EExplorer
from w2e_ros.core.exploration.proposals import ProposalConfig
from w2e_ros.core.exploration.strategies import Scored, get_strategy
from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.robot.feasibility import Arm, approach_clear, arm_reachable
from w2e_ros.core.robot.primitives import TrialResult

torch.set_num_threads(2)
SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))


@pytest.fixture(scope="module")
def novel():
    return synthetic_data(categories=("kettle", "bucket"), obs_per_cat=3, seed=5,
                          instance_start=30)


@pytest.fixture(scope="module")
def replay():
    return synthetic_data(obs_per_cat=4, per_obs=24, seed=1)


def _explorer(replay, sim_bias: float | None = None, seed: int = 0,
              **kw) -> tuple[W2EExplorer, ExploreConfig]:
    """An explorer of a small model and the loop's config (``kw``: any of its settings)."""
    torch.manual_seed(seed)
    model = W2EModel(SMALL)
    if sim_bias is not None:  # push every similarity to ~0 or ~1
        with torch.no_grad():
            model.sim_head.out.weight.zero_()
            model.sim_head.out.bias.fill_(sim_bias)
    kw = {"points_per_object": 32, "dirs_per_point": 4, "finetune_steps": 2,
          "finetune_min_steps": 2, **kw}
    cfg = ExploreConfig.from_dict(kw)
    return W2EExplorer(model, cfg.finetuning, replay, ("cabinet",),
                       ("cabinet", "faucet", "window"), seed=seed), cfg


def test_candidates_face_the_surface_and_favour_the_mask(novel):
    cloud = Cloud(novel.points[0], novel.normals[0], novel.movable[0])
    rng = np.random.default_rng(0)
    only = sample_candidates(cloud, 20, 3, rng, mask=cloud.movable,
                             proposal=ProposalConfig(movable_fraction=1.0))
    assert len(only) == 60 and cloud.movable[only.point_index].all()
    c = sample_candidates(cloud, 400, 1, rng, mask=cloud.movable)  # default: 80 % on it
    assert cloud.movable[c.point_index].mean() > 0.8
    free = sample_candidates(cloud, 400, 1, rng)  # no mask (a real robot): the whole cloud
    assert cloud.movable[free.point_index].mean() < 0.6
    for cand in (only, c, free):
        assert (np.sum(cand.up * cloud.normals[cand.point_index], axis=1) < 0).all()
        np.testing.assert_allclose(np.sum(cand.up * cand.forward, axis=1), 0, atol=1e-5)


def test_loop_stops_at_the_bar_before_spending_anything(novel, replay):
    exp, cfg = _explorer(replay, sim_bias=8.0)
    world = RuleWorld(novel)
    res = explore(exp, world, list(range(6)), get_strategy("similarity"), cfg, "push")
    assert res.stopped == "bar" and res.steps == [] and world.executed == []
    assert res.mean_similarity[0] > 0.9
    assert set(res.snapshots) == {0, 1, 2, 5}


def test_loop_spends_the_budget_when_similarity_stays_low(novel, replay):
    # budget 2 per object x 3 objects = 6 interactions, 2 a round: snapshots after the
    # rounds where 3 (b=1) and 6 (b=2) interactions were reached; b=5 is the final model
    exp, cfg = _explorer(replay, sim_bias=-8.0, budget=2, round_size=2,
                         snapshot_budgets=(1, 2, 5))
    world = RuleWorld(novel)
    res = explore(exp, world, [0, 1, 2], get_strategy("similarity"), cfg, "push")
    assert res.stopped == "budget" and len(res.steps) == 6 == len(world.executed)
    assert [s.step for s in res.steps] == [1, 2, 3, 4, 5, 6]
    assert [s.round for s in res.steps] == [1, 1, 2, 2, 3, 3]
    assert len(res.mean_similarity) == 4 and exp.num_explored == 6
    # snapshots differ across budgets (the model was fine-tuned in between); 5 = final
    w = "aff_head.out.bias"
    assert not torch.equal(res.snapshots[0][w], res.snapshots[1][w])
    assert not torch.equal(res.snapshots[1][w], res.snapshots[2][w])
    assert torch.equal(res.snapshots[2][w], exp.snapshot()[w])
    assert torch.equal(res.snapshots[5][w], exp.snapshot()[w])


def test_similarity_strategy_executes_the_lowest_similarity_action(novel, replay):
    exp, cfg = _explorer(replay, budget=1)
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

    explore(Spy(), world, list(range(6)), get_strategy("similarity"), cfg, "push")
    sims = [s.similarity for s in seen["scored"]]
    obj = int(np.argmin([s.min() for s in sims]))
    i = int(np.argmin(sims[obj]))
    target, action = world.executed[0]
    assert target == obj
    np.testing.assert_allclose(action.up, seen["cands"][obj].up[i], atol=1e-6)


class TaggedWorld(RuleWorld):
    """The rule world whose clouds know their target (for the fake model below)."""

    def observe(self, target):
        cloud = super().observe(target)
        cloud.target = target
        return cloud


class FakeModel:
    """An ExplorationModel without learning: each object's similarity is a number that
    rises by ``gain[object]`` per interaction on it; snapshots count the updates so far."""

    def __init__(self, sim, gain, seed: int = 0):
        self.sim, self.gain = list(sim), list(gain)
        self.rounds: list[list[int]] = []
        self.seen: list[tuple[list, list]] = []
        self.rng = np.random.default_rng(seed)

    def score(self, clouds, cands):
        out = []
        for cl, c in zip(clouds, cands, strict=True):
            aff = 0.5 + 0.45 * np.sin(1000.0 * c.up[:, 0] + 7.0 * c.point_index)
            # tiny per-candidate spread, so candidates of one object are ranked
            sim = self.sim[cl.target] + 1e-4 * np.arange(len(c)) / max(len(c), 1)
            out.append(Scored(aff.astype(np.float32), sim.astype(np.float32)))
        self.seen.append((list(cands), out))
        return out

    def update(self, executed):
        self.rounds.append([e.cloud.target for e in executed])
        for e in executed:
            self.sim[e.cloud.target] += self.gain[e.cloud.target]
        return {"loss": 0.0}

    def snapshot(self):
        return len(self.rounds)


def _fake_cfg(**kw) -> ExploreConfig:
    """The loop's bookkeeping on synthetic clouds: no approach check unless a test asks."""
    return ExploreConfig(**{"points_per_object": 8, "dirs_per_point": 2,
                            "check_approach": False, **kw})


def test_budget_is_b_interactions_per_object_in_rounds_capped_per_object(novel):
    model, world = FakeModel([0.0] * 3, [0.0] * 3), TaggedWorld(novel)
    cfg = _fake_cfg(budget=2, round_size=4, per_object_per_round=2, snapshot_budgets=(1, 2, 5))
    res = explore(model, world, [0, 1, 2], get_strategy("random"), cfg, "push",
                  rng=np.random.default_rng(0))
    assert res.stopped == "budget" and len(res.steps) == 6 == len(world.executed)
    assert [len(r) for r in model.rounds] == [4, 2]  # round_size, then what is left
    assert all(max(np.bincount(r)) <= 2 for r in model.rounds)
    assert [s.round for s in res.steps] == [1, 1, 1, 1, 2, 2]
    assert [int(s.target) for s in res.steps] == [t for r in model.rounds for t in r]
    # snapshots once b x 3 interactions are spent: b=1 after round 1 (4 >= 3), b=2 after
    # round 2, b=5 (never reached) the final model
    assert res.snapshots == {0: 0, 1: 1, 2: 2, 5: 2}


def test_default_round_is_half_of_the_objects(novel):
    model, world = FakeModel([0.0] * 6, [0.0] * 6), TaggedWorld(novel)
    res = explore(model, world, list(range(6)), get_strategy("random"),
                  _fake_cfg(budget=1, per_object_per_round=1), "push",
                  rng=np.random.default_rng(1))
    assert [len(r) for r in model.rounds] == [3, 3] and len(res.steps) == 6


def test_budget_is_chosen_globally_so_an_unfamiliar_object_takes_more(novel):
    # object 0 stays unfamiliar (similarity 0.1), the others familiar-ish (0.6): the
    # similarity rule spends most of the budget on object 0, up to 2 per round
    model, world = FakeModel([0.1, 0.6, 0.6], [0.0] * 3), TaggedWorld(novel)
    cfg = _fake_cfg(budget=2, round_size=3, per_object_per_round=2)
    res = explore(model, world, [0, 1, 2], get_strategy("similarity"), cfg, "push")
    targets = [int(s.target) for s in res.steps]
    assert len(targets) == 6 and targets.count(0) == 4
    assert all(r.count(0) == 2 for r in model.rounds)


def test_object_cap_spreads_a_budget_the_bar_would_give_to_one_object(novel):
    # objects 1, 2 pass the bar after one round; object 0 never does: without a cap it takes
    # the rest of the budget, with object_cap 1.5 (x budget 4 = 6) it stops at 6
    for cap, n0, stopped in ((0.0, 10, "budget"), (1.5, 6, "cap")):
        model, world = FakeModel([0.1, 0.8, 0.8], [0.0, 0.2, 0.2]), TaggedWorld(novel)
        cfg = _fake_cfg(budget=4, round_size=3, per_object_per_round=2, similarity_bar=0.9,
                        object_cap=cap)
        res = explore(model, world, [0, 1, 2], get_strategy("similarity"), cfg, "push")
        targets = [int(s.target) for s in res.steps]
        assert targets.count(0) == n0 and res.stopped == stopped, (cap, targets)
        assert all(max(np.bincount(r)) <= 2 for r in model.rounds)


def test_an_object_over_the_bar_is_dropped_while_the_others_continue(novel):
    # object 0 becomes familiar fast (+0.25 per interaction), the others slowly
    model, world = FakeModel([0.5] * 3, [0.25, 0.05, 0.05]), TaggedWorld(novel)
    cfg = _fake_cfg(budget=3, round_size=3, per_object_per_round=1, similarity_bar=0.9)
    res = explore(model, world, [0, 1, 2], get_strategy("similarity"), cfg, "push")
    assert res.stopped == "budget" and len(res.steps) == 9
    rounds_of_0 = {s.round for s in res.steps if int(s.target) == 0}
    assert rounds_of_0 == {1, 2}  # 0.5 -> 0.75 -> 1.0 > 0.9: not explored after round 2
    assert [sorted(r) for r in model.rounds] == [[0, 1, 2], [0, 1, 2], [1, 2], [1]]
    # the mean similarity before a round is over all objects, the dropped one included
    assert res.mean_similarity[2] == pytest.approx(np.mean([1.0, 0.6, 0.6]), abs=1e-3)


def test_loop_stops_at_the_bar_once_every_object_passes_it(novel):
    model, world = FakeModel([0.5] * 3, [0.25] * 3), TaggedWorld(novel)
    cfg = _fake_cfg(budget=5, round_size=3, per_object_per_round=1, similarity_bar=0.9,
                    snapshot_budgets=(1, 5))
    res = explore(model, world, [0, 1, 2], get_strategy("similarity"), cfg, "push")
    assert res.stopped == "bar" and len(res.steps) == 6 and len(model.rounds) == 2
    assert res.snapshots == {0: 0, 1: 1, 5: 2}  # budget 5 never reached: the final model


def test_a_stop_between_interactions_keeps_what_the_round_executed(novel):
    """Cancel (the planner's explore action): no interaction starts once should_stop says so;
    the ones of the round already executed are still learned from (model.update)."""
    model, world = FakeModel([0.0] * 3, [0.0] * 3), TaggedWorld(novel)
    cfg = _fake_cfg(budget=2, round_size=3, per_object_per_round=1)
    res = explore(model, world, [0, 1, 2], get_strategy("random"), cfg, "push",
                  rng=np.random.default_rng(0), should_stop=lambda: len(world.executed) >= 4)
    assert res.stopped == "cancelled"
    assert len(world.executed) == 4 == len(res.steps)  # round 1 (3), then 1 of round 2
    assert [len(r) for r in model.rounds] == [3, 1]  # the cut round's one was learned from
    # asked before anything: nothing executed, nothing learned
    model, world = FakeModel([0.0] * 3, [0.0] * 3), TaggedWorld(novel)
    res = explore(model, world, [0, 1, 2], get_strategy("random"), cfg, "push",
                  should_stop=lambda: True)
    assert res.stopped == "cancelled" and world.executed == [] and model.rounds == []


def test_a_resumed_run_counts_the_interactions_already_spent(novel):
    """Resume (the planner's sessions): spent interactions count against the budget and the
    step numbers continue after them."""
    model, world = FakeModel([0.0] * 3, [0.0] * 3), TaggedWorld(novel)
    cfg = _fake_cfg(budget=2, round_size=2, per_object_per_round=1)
    res = explore(model, world, [0, 1, 2], get_strategy("random"), cfg, "push",
                  rng=np.random.default_rng(0), spent=5)
    assert res.stopped == "budget" and len(world.executed) == 1
    assert [s.step for s in res.steps] == [6]
    model, world = FakeModel([0.0] * 3, [0.0] * 3), TaggedWorld(novel)
    res = explore(model, world, [0, 1, 2], get_strategy("random"), cfg, "push", spent=6)
    assert res.stopped == "budget" and res.steps == [] and world.executed == []


def test_check_approach_drops_the_candidates_whose_approach_runs_into_the_cloud(novel):
    """check_approach (on in the planner): the loop draws the same candidates, drops those
    whose approach runs into the object's cloud before scoring, and executes only clear ones."""
    seen, executed = {}, {}
    for check in (False, True):
        model, world = FakeModel([0.0] * 3, [0.0] * 3), TaggedWorld(novel)
        cfg = _fake_cfg(budget=2, round_size=3, per_object_per_round=1, points_per_object=32,
                        dirs_per_point=4, check_approach=check)
        res = explore(model, world, [0, 1, 2], get_strategy("similarity"), cfg, "pull",
                      rng=np.random.default_rng(0))
        assert res.stopped == "budget" and len(res.steps) == 6
        seen[check], executed[check] = [c for c, _ in model.seen], world.executed
    dropped = 0
    for off, on in zip(seen[False], seen[True], strict=True):  # rounds
        for obj, (a, b) in enumerate(zip(off, on, strict=True)):
            pts = novel.points[obj]
            clear = approach_clear(pts, pts[a.point_index], a.up, a.forward, "pull")
            np.testing.assert_array_equal(b.point_index, a.point_index[clear])
            np.testing.assert_array_equal(b.up, a.up[clear])
            dropped += int((~clear).sum())
    assert dropped > 0
    assert all(approach_clear(novel.points[t], a.point, a.up, a.forward, "pull")[0]
               for t, a in executed[True])
    assert not all(approach_clear(novel.points[t], a.point, a.up, a.forward, "pull")[0]
                   for t, a in executed[False])


def test_a_panda_arm_drops_the_candidates_it_cannot_reach(novel):
    """arm panda (planner parameter): the loop draws the same candidates, drops those whose
    waypoints the arm at its base pose cannot follow, and executes only reachable ones."""
    arm = Arm("panda", base_pose=(0.95, 0.0, -0.3, 0.0, 0.0, 1.0, 0.0))  # facing the object
    seen, executed = {}, {}
    for a in (None, arm):
        model, world = FakeModel([0.0] * 3, [0.0] * 3), TaggedWorld(novel)
        cfg = _fake_cfg(budget=1, round_size=3, per_object_per_round=1, points_per_object=16,
                        dirs_per_point=4)
        res = explore(model, world, [0, 1, 2], get_strategy("similarity"), cfg, "pull",
                      rng=np.random.default_rng(0), **({"arm": a} if a else {}))
        assert res.stopped == "budget" and len(res.steps) == 3
        seen[a is not None], executed[a is not None] = [c for c, _ in model.seen], world.executed
    dropped = 0
    for obj, (a, b) in enumerate(zip(seen[False][0], seen[True][0], strict=True)):
        pts = novel.points[obj]
        ok = arm_reachable(pts[a.point_index], a.up, a.forward, "pull", arm)
        np.testing.assert_array_equal(b.point_index, a.point_index[ok])
        dropped += int((~ok).sum())
    assert dropped > 0
    assert all(arm_reachable(x.point, x.up, x.forward, "pull", arm)[0]
               for _, x in executed[True])


def test_oracle_executes_the_pool_candidates_the_model_gets_most_wrong(novel):
    model, world = FakeModel([0.0] * 2, [0.0] * 2), TaggedWorld(novel)
    cfg = _fake_cfg(budget=2, round_size=2, per_object_per_round=1, oracle_pool=12)
    res = explore(model, world, [0, 1], get_strategy("oracle", experimental=True), cfg, "push")
    # the pools were labelled in hindsight first (2 x 12 trials), then 4 interactions
    assert len(world.executed) == 24 + 4 and len(res.steps) == 4
    assert [t for t, _ in world.executed[:24]] == [0] * 12 + [1] * 12
    picked: dict[int, set] = {0: set(), 1: set()}
    for rnd, (cands, scored) in enumerate(model.seen[:2]):
        for obj in (0, 1):
            c, s = cands[obj], scored[obj]
            assert len(c) == 12 - rnd  # the pool, without what was executed
            label = novel.movable[obj][c.point_index] & (c.up[:, 2] < -0.7)
            i = int(np.argmax(np.abs(s.affordance - label)))
            step = next(st for st in res.steps if st.round == rnd + 1 and int(st.target) == obj)
            np.testing.assert_allclose(step.up, c.up[i], atol=1e-6)
            assert step.success == bool(label[i])
            picked[obj].add(int(c.source[i]))
    assert all(len(p) == 2 for p in picked.values())  # never the same candidate twice


def test_none_strategy_spends_nothing_and_snapshots_the_initial_model(novel, replay):
    exp, cfg = _explorer(replay)
    world = RuleWorld(novel)
    res = explore(exp, world, [0, 1], get_strategy("none", experimental=True), cfg, "push")
    assert res.stopped == "none" and not world.executed
    assert all(torch.equal(res.snapshots[b]["aff_head.out.bias"],
                           res.snapshots[0]["aff_head.out.bias"]) for b in (1, 2, 5))


def test_a_proposer_built_once_draws_what_one_built_every_round_drew(novel):
    """The loop builds each cloud's proposal pools once: the same seed, the same candidates
    round after round as building them for every draw."""
    clouds = [Cloud(novel.points[i], novel.normals[i], novel.movable[i]) for i in range(3)]
    fresh, kept = np.random.default_rng(5), np.random.default_rng(5)
    proposers = [cloud_proposer(c, c.movable) for c in clouds]
    for _ in range(3):  # rounds
        for c, p in zip(clouds, proposers, strict=True):
            a = sample_candidates(c, 32, 4, fresh, c.movable)
            b = sample_candidates(c, 32, 4, kept, proposer=p)
            for f in ("point_index", "up", "forward"):
                np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


def test_fine_tuning_fits_the_explored_interactions(novel):
    # no replay: the explored interaction alone must be learned (replay only anchors); no
    # prior either: with one interaction the default prior (5 / N) holds the model near its
    # trained weights on purpose (test_finetune checks that)
    exp, _ = _explorer(None, finetune_steps=30, finetune_lr=1e-3, prior=0.0)
    cloud = Cloud(novel.points[0], novel.normals[0], novel.movable[0])
    cands = sample_candidates(cloud, 16, 2, np.random.default_rng(1), mask=cloud.movable)
    i = int(np.argmin(cands.up[:, 2]))  # straight into the handle: a success
    before = exp.score([cloud], [cands])[0].affordance[i]
    exp.update([Executed(cloud, cands, i, TrialResult(True, True, np.array([0.05]), 0, "door"))])
    after = exp.score([cloud], [cands])[0].affordance[i]
    assert after > max(before, 0.6)


@pytest.mark.slow
def test_loop_explores_simulated_objects_and_learns_from_the_outcomes():
    from w2e_ros.core.exploration.evaluate import SuccessProbe, evaluation_targets
    from w2e_ros.core.exploration.explore import explore_targets
    from w2e_ros.experiments.sim_world import SimWorld

    world = SimWorld()
    torch.manual_seed(0)
    model = W2EModel()
    cfg = ExploreConfig.from_dict(dict(budget=1, points_per_object=16, dirs_per_point=2,
                                       finetune_steps=1, finetune_min_steps=1,
                                       snapshot_budgets=(1, 2)))
    exp = W2EExplorer(model, cfg.finetuning, None, ("cabinet",), ("cabinet", "faucet", "window"))
    targets = explore_targets(["kettle"], per_category=2)
    assert [t.instance for t in targets] == [30, 31]
    res = explore(exp, world, targets, get_strategy("similarity"), cfg, "pull")
    assert len(res.steps) == 2 and res.stopped == "budget"
    assert all(s.target.startswith("kettle/") for s in res.steps)
    assert exp.num_explored == 2 and all(c.shape == (2048, 3) for c in exp.clouds)
    probe = SuccessProbe(world, evaluation_targets(["kettle"], 2), "pull", points_per_object=8,
                         dirs_per_point=2)
    r = probe.run(exp.model_at(res.snapshots[2]))
    assert set(r) == {"kettle", "all", "mean"} and 0.0 <= r["all"] <= 1.0


@pytest.mark.slow
def test_fewshot_spends_the_budget_per_object_over_all_novel_categories():
    from w2e_ros.core.exploration.explore import fewshot
    from w2e_ros.experiments.sim_world import SimWorld

    torch.manual_seed(0)
    model = W2EModel(SMALL)
    cfg = ExploreConfig.from_dict(dict(budget=1, points_per_object=8, dirs_per_point=2,
                                       finetune_steps=2, finetune_min_steps=2,
                                       snapshot_budgets=(1,), similarity_bar=1.01,
                                       round_size=2, check_approach=False))
    meta = {"aff_categories": ["cabinet"], "sim_categories": ["cabinet", "faucet", "window"]}
    world = SimWorld(SMALL.num_points)
    runs = fewshot(model, meta, world, ["kettle", "door"], get_strategy("random"), cfg, "push",
                   per_category=2)
    res, explorer = runs["all"]
    # budget 1 x 4 explore instances, in rounds of 2
    assert len(res.steps) == 4 and explorer.num_explored == 4
    assert [s.round for s in res.steps] == [1, 1, 2, 2]
    assert {s.target.rsplit("/", 1)[0] for s in res.steps} <= {
        "door/30", "door/31", "kettle/30", "kettle/31"}
    with pytest.raises(ValueError, match="mode"):
        fewshot(model, meta, world, ["kettle"], get_strategy("random"), cfg, "push",
                mode="per-instance", per_category=1)
    # frozen: the affordance head adapts, the similarity head keeps its calibrated weights;
    # finetune (the reference): both move
    for update, sim_moves in (("frozen", False), ("finetune", True)):
        c = replace(cfg, finetuning=replace(cfg.finetuning, similarity_update=update,
                                            finetune_steps=20, finetune_min_steps=20))
        _, ex = fewshot(model, meta, world, ["kettle"], get_strategy("random"), c, "push",
                        per_category=2)["all"]
        moved = {name: not torch.equal(p, model.state_dict()[name])
                 for name, p in ex.model.state_dict().items() if "head" in name}
        assert any(v for k, v in moved.items() if k.startswith("aff_head")), update
        assert any(v for k, v in moved.items() if k.startswith("sim_head")) == sim_moves, update
    with pytest.raises(ValueError, match="similarity update"):
        fewshot(model, meta, world, ["kettle"], get_strategy("random"),
                ExploreConfig(finetuning=FinetuneConfig(similarity_update="sometimes")), "push",
                per_category=1)


def test_cli_explore_defaults_are_the_core_defaults():
    """``w2e fewshot`` / ``benchmark`` / ``learnability`` with no tuning flags run the core's
    ExploreConfig, so a default changed there reaches every front end."""
    from dataclasses import asdict

    from w2e_ros import cli
    from w2e_ros.core.exploration.config import ExploreConfig

    parser = cli.build_parser()
    for argv in (["fewshot", "--model", "m.pt", "--out", "o"], ["benchmark"],
                 ["learnability", "--model", "m.pt", "--pool-data", "p", "--test-data", "t"]):
        got = asdict(cli._explore_config(parser.parse_args(argv)))
        assert got == asdict(ExploreConfig()), argv[0]


def test_cli_round_flags_reach_the_loop():
    """``--round-size`` and ``--per-object-per-round`` set the loop's rounds (one round of the
    whole budget, from the base model, is a protocol the research log measured)."""
    from w2e_ros import cli

    a = cli.build_parser().parse_args(["benchmark", "--round-size", "275",
                                       "--per-object-per-round", "5"])
    cfg = cli._explore_config(a)
    assert (cfg.round_size, cfg.per_object_per_round) == (275, 5)


def test_posterior_draws_scatter_around_the_affordance_and_leave_the_fit_alone(novel, replay):
    """MC dropout at rate 0 reproduces the scored affordance; at 0.5 the draws differ and
    their mean stays near it. Drawing them does not move the fit: from the same interaction
    an explorer that drew and one that did not end on the same weights."""
    cloud = Cloud(novel.points[0], novel.normals[0], novel.movable[0])
    cands = sample_candidates(cloud, 16, 2, np.random.default_rng(1), mask=cloud.movable)
    done = Executed(cloud, cands, 0, TrialResult(True, True, np.array([0.05]), 0, "door"))
    weights = []
    for draw in (True, False):
        exp, _ = _explorer(replay)
        scored = exp.score([cloud], [cands])
        if draw:
            exp.draw_affordance(scored, [cands], 4, 0.0)
            np.testing.assert_allclose(scored[0].draws,
                                       np.repeat(scored[0].affordance[None], 4, 0), atol=1e-5)
            exp.draw_affordance(scored, [cands], 64, 0.5)
            d = scored[0].draws
            assert d.shape == (64, len(cands)) and d.std(0).mean() > 0.01
            assert np.abs(d.mean(0) - scored[0].affordance).mean() < 0.1
        exp.update([done])
        weights.append(exp.snapshot())
    for k, v in weights[0].items():
        assert torch.equal(v, weights[1][k]), k


def test_the_thompson_rule_explores_and_learns_through_the_loop(novel, replay):
    exp, cfg = _explorer(replay, budget=2, round_size=2)
    world = RuleWorld(novel)
    res = explore(exp, world, list(range(4)), get_strategy("thompson", experimental=True),
                  cfg, "push")
    assert len(res.steps) == 8 and res.stopped == "budget" and exp.num_explored == 8
    assert len(world.executed) == 8 and {t for t, _ in world.executed} <= set(range(4))
