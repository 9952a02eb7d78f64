"""Metrics against hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from w2e_ros.core.model.metrics import (
    affordance_fscore_from_probs,
    auroc,
    average_precision,
    bootstrap_ci,
    classification_metrics,
    fscore,
    mean_std,
    success_rate,
    within_class_auroc,
)


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


def _pairwise_auroc(s: np.ndarray, y: np.ndarray) -> float:
    """P(score of a positive > score of a negative), ties one half: the definition."""
    pos, neg = s[y], s[~y]
    diff = pos[:, None] - neg[None, :]
    return float(((diff > 0) + 0.5 * (diff == 0)).mean())


def test_auroc_hand_computed_with_and_without_ties():
    # positives 0.9, 0.7, 0.6 vs negatives 0.8, 0.5, 0.4: 3 + 2 + 2 of 9 pairs ranked right
    s = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    y = np.array([1, 0, 1, 1, 0, 0], bool)
    assert auroc(s, y) == pytest.approx(7 / 9)
    # a tie between a positive and a negative counts one half: (0.5 + 1 + 2) / 4
    assert auroc(np.array([0.5, 0.5, 0.2, 0.8]), np.array([1, 0, 0, 1], bool)) == \
        pytest.approx(0.875)
    # perfect, reversed, all tied
    assert auroc(np.array([0.1, 0.2, 0.9]), np.array([0, 0, 1], bool)) == 1.0
    assert auroc(np.array([0.9, 0.2, 0.1]), np.array([0, 0, 1], bool)) == 0.0
    assert auroc(np.full(6, 0.3), y) == pytest.approx(0.5)


def test_auroc_equals_the_pairwise_definition_and_ignores_calibration():
    rng = np.random.default_rng(0)
    s = rng.integers(0, 8, size=300) / 8.0  # many ties
    y = rng.random(300) < 0.3 + 0.4 * s
    assert auroc(s, y) == pytest.approx(_pairwise_auroc(s, y))
    # threshold-free: any increasing transform of the scores gives the same value
    assert auroc(1e-3 * s ** 3 - 5, y) == pytest.approx(auroc(s, y))


def test_auroc_and_average_precision_edge_cases():
    assert math.isnan(auroc(np.array([0.2, 0.8]), np.array([1, 1], bool)))
    assert math.isnan(auroc(np.array([0.2, 0.8]), np.array([0, 0], bool)))
    assert math.isnan(auroc(np.array([]), np.array([], bool)))
    assert math.isnan(average_precision(np.array([0.2, 0.8]), np.array([0, 0], bool)))
    assert average_precision(np.array([0.2, 0.8]), np.array([1, 1], bool)) == 1.0


def test_average_precision_hand_computed():
    # ranked: + - + + - -  -> precision at each positive 1/1, 2/3, 3/4
    s = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    y = np.array([1, 0, 1, 1, 0, 0], bool)
    assert average_precision(s, y) == pytest.approx((1 + 2 / 3 + 3 / 4) / 3)
    # the order of the rows does not matter, only the ranking
    perm = np.random.default_rng(1).permutation(6)
    assert average_precision(s[perm], y[perm]) == pytest.approx(29 / 36)
    # all positives ranked first: 1; all last: the mean of k / (n_neg + k)
    assert average_precision(np.array([0.9, 0.8, 0.1, 0.0]), np.array([1, 1, 0, 0], bool)) == 1.0
    assert average_precision(np.array([0.9, 0.8, 0.1, 0.0]), np.array([0, 0, 1, 1], bool)) == \
        pytest.approx((1 / 3 + 2 / 4) / 2)


def test_within_class_auroc_sees_only_what_the_prediction_does_not():
    # predicted successes are mostly wrong, predicted failures mostly right: a score that is
    # just the predicted class ranks correctness well overall, and at chance within a class
    rng = np.random.default_rng(0)
    pred = rng.random(4000) < 0.3
    correct = np.where(pred, rng.random(4000) < 0.1, rng.random(4000) < 0.95)
    class_only = np.where(pred, 0.2, 0.8) + rng.random(4000) * 1e-3
    assert auroc(class_only, correct) > 0.8
    assert abs(within_class_auroc(class_only, correct, pred) - 0.5) < 0.05
    # a score that knows which predictions are right scores 1 within each class too
    assert within_class_auroc(correct.astype(float), correct, pred) == 1.0
    # hand computed: class A one pair (right above wrong), class B two pairs, one inverted
    s = np.array([0.9, 0.1, 0.2, 0.8, 0.7])
    ok = np.array([True, False, True, False, False])
    cls = np.array([True, True, False, False, False])
    assert math.isclose(within_class_auroc(s, ok, cls), (1 * 1 + 0 * 2) / 3)
    assert math.isnan(within_class_auroc(s, np.ones(5, bool), cls))


def test_classification_metrics_combines_fscore_auroc_and_ap():
    s = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4])
    y = np.array([1, 0, 1, 1, 0, 0], bool)
    m = classification_metrics(s, y)
    # at 0.5 (strictly above): predicted 1 = 0.9, 0.8, 0.7, 0.6 -> tp 3, fp 1, fn 0
    assert (m["tp"], m["fp"], m["fn"]) == (3, 1, 0)
    assert m["fscore"] == pytest.approx(2 * 0.75 * 1 / 1.75)
    assert m["auroc"] == pytest.approx(7 / 9) and m["ap"] == pytest.approx(29 / 36)
    assert m["pos_rate"] == pytest.approx(0.5)
    assert classification_metrics(s, y, threshold=0.95)["fscore"] == 0.0


def test_bootstrap_interval_covers_the_statistic_and_is_reproducible():
    rng = np.random.default_rng(0)
    values = rng.normal(1.0, 1.0, size=400)
    groups = np.arange(400) // 4  # 100 groups of 4 rows
    mean = lambda idx: float(values[idx].mean())  # noqa: E731
    point, lo, hi = bootstrap_ci(mean, groups, n_boot=300, seed=3)
    assert point == pytest.approx(values.mean())
    assert lo < point < hi and hi - lo < 0.5
    assert bootstrap_ci(mean, groups, n_boot=300, seed=3) == (point, lo, hi)
    # a wider level gives a wider interval
    _, lo99, hi99 = bootstrap_ci(mean, groups, n_boot=300, seed=3, level=0.99)
    assert lo99 <= lo and hi99 >= hi


def test_bootstrap_resamples_whole_groups_not_rows():
    # two groups of 100 identical rows (0s and 1s): a group resample can only give a mean of
    # 0, 1/2 or 1 (a row resample would give 0.5 +- 0.07), so the 95 % interval is [0, 1]
    values = np.repeat([0.0, 1.0], 100)
    groups = np.repeat(["a", "b"], 100)
    seen: list[np.ndarray] = []

    def mean(idx: np.ndarray) -> float:
        seen.append(idx)
        return float(values[idx].mean())

    point, lo, hi = bootstrap_ci(mean, groups, n_boot=200, seed=0)
    assert point == 0.5 and (lo, hi) == (0.0, 1.0)
    assert np.array_equal(seen[0], np.arange(200))  # the point estimate uses every row
    for idx in seen[1:]:
        counts = np.bincount(idx, minlength=200)
        # every row of a group is drawn as often as the group: whole groups only
        assert len(set(counts[:100])) == 1 and len(set(counts[100:])) == 1
        assert counts.sum() == 200


# --- evaluation of a model (w2e_ros.core.exploration.evaluate) ----------------------------------

def test_predictions_match_the_model_on_each_interaction():
    import torch
    from synthetic import RuleWorld, synthetic_data

    from w2e_ros.core.exploration.evaluate import (
        SuccessProbe,
        fscore_by_category,
        predict_interactions,
    )
    from w2e_ros.core.model.config import ModelConfig
    from w2e_ros.core.model.network import W2EModel

    torch.manual_seed(0)
    model = W2EModel(ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))).eval()
    data = synthetic_data(categories=("kettle", "bucket"), obs_per_cat=3, per_obs=10)
    aff, sim = predict_interactions(model, data, chunk=4)  # chunks cut across categories
    from w2e_ros.core.robot.actions import encode_rotation

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
    outcomes = probe.outcomes(model)  # (success, valid) per target, from the same cache
    assert len(outcomes) == 3 and all(valid for _, valid in outcomes)
    assert r1["all"] == pytest.approx(np.mean([ok for ok, _ in outcomes]))
    assert len(world.executed) == 3
    # candidates favour the movable parts (the world's ground-truth mask)
    mask_share = np.mean([data.movable[t][c.point_index].mean()
                          for t, c in zip([0, 1, 2], probe.candidates, strict=True)])
    assert mask_share > 0.7


def test_the_probe_with_the_approach_check_executes_the_best_clear_action():
    """As the stack's manipulate: the highest-affordance candidate whose approach does not run
    into the cloud, not the argmax (an object with no clear candidate is a failure, untouched)."""
    import torch
    from synthetic import RuleWorld, synthetic_data

    from w2e_ros.core.exploration.evaluate import SuccessProbe
    from w2e_ros.core.model.config import ModelConfig
    from w2e_ros.core.model.network import W2EModel
    from w2e_ros.core.robot.actions import encode_rotation
    from w2e_ros.core.robot.feasibility import approach_clear

    torch.manual_seed(0)
    model = W2EModel(ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))).eval()
    data = synthetic_data(categories=("kettle",), obs_per_cat=6, per_obs=4)
    world = RuleWorld(data)
    probe = SuccessProbe(world, list(range(6)), "push", points_per_object=32, dirs_per_point=4,
                         sampler="maps", check_approach=True)
    probe.outcomes(model)
    executed = dict(world.executed)
    blocked_best = 0
    for t, (cloud, cand) in enumerate(zip(probe.clouds, probe.candidates, strict=True)):
        with torch.no_grad():
            f = model.encode(torch.from_numpy(cloud.points[None]))[0][cand.point_index]
            logit = model.aff_head(f, torch.from_numpy(encode_rotation(cand.up, cand.forward)))
        order = torch.argsort(logit, descending=True, stable=True).numpy()[:256]
        clear = approach_clear(cloud.points, cloud.points[cand.point_index[order]],
                               cand.up[order], cand.forward[order], "push")
        blocked_best += int(not clear[0])
        if not clear.any():
            assert t not in executed
            continue
        want = cand.action(cloud, int(order[np.argmax(clear)]), "push")
        np.testing.assert_allclose(executed[t].point, want.point)
        np.testing.assert_allclose(executed[t].up, want.up)
    assert blocked_best > 0  # the check changed the choice somewhere


def test_validation_instances_are_neither_explored_nor_test():
    from w2e_ros.core.dataset.categories import load_categories
    from w2e_ros.core.exploration.evaluate import evaluation_targets

    cats = load_categories()
    evaluation_instances = cats.evaluation_instances
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


def test_r_precision_depends_on_the_ranking_not_on_the_threshold():
    from w2e_ros.core.model.metrics import fscore, r_precision

    y = np.array([1, 0, 1, 0, 0, 0, 0, 0], bool)
    s = np.array([0.45, 0.8, 0.3, 0.2, 0.1, 0.1, 0.1, 0.1])
    assert r_precision(s, y) == 0.5  # the top 2 hold one of the 2 positives
    lifted = s + 0.1  # a fit that only pushes one more prediction above 0.5
    assert fscore(lifted > 0.5, y)["fscore"] > fscore(s > 0.5, y)["fscore"]
    assert r_precision(lifted, y) == r_precision(s, y)
    assert r_precision(np.where(y, 0.6, 0.4), y) == 1.0
    assert r_precision(np.full(8, 0.5), y) == 0.25  # all tied: the positive rate
    assert math.isnan(r_precision(s, np.zeros(8, bool)))
