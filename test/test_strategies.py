"""Each strategy picks what it claims to pick."""

from __future__ import annotations

import numpy as np
import pytest

from w2e_ros.core.strategies import Scored, get_strategy


def _scored() -> list[Scored]:
    return [
        Scored(affordance=np.array([0.9, 0.1, 0.7]), similarity=np.array([0.8, 0.6, 0.9])),
        Scored(affordance=np.array([0.45, 0.0]), similarity=np.array([0.7, 0.2])),
        Scored(affordance=np.array([]), similarity=np.array([])),
        Scored(affordance=np.array([0.52, 0.99]), similarity=np.array([0.5, 0.95])),
    ]


def test_similarity_picks_the_lowest_similarity_over_all_objects():
    assert get_strategy("similarity").choose(_scored(), np.random.default_rng(0)) == (1, 1)


@pytest.mark.parametrize("name", ["where2act", "nosim"])
def test_uncertainty_rules_pick_the_affordance_closest_to_one_half(name):
    assert get_strategy(name).choose(_scored(), np.random.default_rng(0)) == (3, 0)


def test_confident_tries_the_likeliest_successes_first_capped_per_object():
    picks = get_strategy("confident").select(_scored(), 3, 1, np.random.default_rng(0))
    assert picks == [(3, 1), (0, 0), (1, 0)]  # 0.99, 0.9, then object 1's best (0.45)


def test_random_picks_valid_candidates_from_every_object():
    rng = np.random.default_rng(0)
    picks = [get_strategy("random").choose(_scored(), rng) for _ in range(200)]
    sizes = [3, 2, 0, 2]
    assert all(0 <= i < sizes[o] for o, i in picks)
    assert {o for o, _ in picks} == {0, 1, 3}


def test_none_does_not_explore_and_only_similarity_stops_at_the_bar():
    none = get_strategy("none")
    assert not none.explores
    with pytest.raises(RuntimeError):
        none.choose(_scored(), np.random.default_rng(0))
    assert get_strategy("similarity").stops_at_bar
    assert not get_strategy("where2act").stops_at_bar
    with pytest.raises(ValueError):
        get_strategy("curiosity")


def test_select_takes_the_lowest_keys_over_all_objects_capped_per_object():
    sim = get_strategy("similarity")
    rng = np.random.default_rng(0)
    # similarity keys: (1,1)=0.2 (3,0)=0.5 (0,1)=0.6 (1,0)=0.7 (0,0)=0.8 (0,2)=0.9 (3,1)=0.95
    assert sim.select(_scored(), 3, 2, rng) == [(1, 1), (3, 0), (0, 1)]
    assert sim.select(_scored(), 4, 1, rng) == [(1, 1), (3, 0), (0, 1)]  # one per object
    assert sim.select(_scored(), 5, 2, rng) == [(1, 1), (3, 0), (0, 1), (1, 0), (0, 0)]
    assert len(sim.select(_scored(), 100, 100, rng)) == 7  # every candidate, no more


def test_oracle_picks_what_the_model_gets_most_wrong_and_needs_labels():
    oracle = get_strategy("oracle")
    assert oracle.needs_labels and not oracle.stops_at_bar
    labels = [np.array([0, 1, 1]), np.array([1, 0]), np.array([]), np.array([0, 0])]
    # errors |affordance - label|: obj0 .9 .9 .3, obj1 .55 0, obj3 .52 .99
    assert oracle.choose(_scored(), np.random.default_rng(0), labels) == (3, 1)
    assert oracle.select(_scored(), 3, 1, np.random.default_rng(0), labels) == [
        (3, 1), (0, 0), (1, 0)]
    with pytest.raises(ValueError, match="labels"):
        oracle.choose(_scored(), np.random.default_rng(0))


def test_similarity_sampled_draws_in_proportion_to_unfamiliarity():
    """Unfamiliarity 1 - s: on one object with s = (0.2, 0.6, 1.0) the picks come out near
    0.8 : 0.4 : 0 (the paper's rule would take the first every time)."""
    scored = [Scored(affordance=np.zeros(3), similarity=np.array([0.2, 0.6, 1.0]))]
    rng = np.random.default_rng(0)
    rule = get_strategy("similarity_sampled")
    picks = np.array([rule.choose(scored, rng)[1] for _ in range(3000)])
    share = np.bincount(picks, minlength=3) / len(picks)
    assert share[0] == pytest.approx(2 / 3, abs=0.03)
    assert share[1] == pytest.approx(1 / 3, abs=0.03)
    assert share[2] < 0.002
    assert rule.stops_at_bar


def test_similarity_mixed_takes_half_least_familiar_half_random():
    """Over many objects a round is about half each object's least familiar candidate and
    half spread over the rest (the argmin alone would take only the least familiar)."""
    rng = np.random.default_rng(0)
    scored = [Scored(affordance=np.zeros(20), similarity=rng.random(20)) for _ in range(400)]
    rule = get_strategy("similarity_mixed")
    picks = rule.select(scored, 200, 1, rng)
    lowest = np.mean([c == int(np.argmin(scored[o].similarity)) for o, c in picks])
    assert 0.45 < lowest < 0.65  # half by rank (mostly the lowest) + 1/20 of the random half
    assert len({o for o, _ in picks}) == 200 and rule.stops_at_bar


def test_failure_rules_look_only_at_predicted_failures_first():
    """similarity_failure: the least familiar of the predicted failures, however unfamiliar a
    predicted success is; nosim_failure: the predicted failure nearest 0.5."""
    aff = np.array([0.9, 0.2, 0.45, 0.1, 0.6])
    sim = np.array([0.0, 0.3, 0.8, 0.5, 0.1])
    rng = np.random.default_rng(0)
    scored = [Scored(affordance=aff, similarity=sim)]
    assert [c for _, c in get_strategy("similarity_failure").select(scored, 3, 5, rng)] == [1, 3, 2]
    assert [c for _, c in get_strategy("nosim_failure").select(scored, 3, 5, rng)] == [2, 1, 3]
    # once the predicted failures are used up, the predicted successes follow
    assert get_strategy("similarity_failure").select(scored, 5, 5, rng)[3:] == [(0, 0), (0, 4)]
    assert not get_strategy("similarity_failure").stops_at_bar


def test_similarity_failure_half_takes_half_by_the_rule_and_half_at_random():
    """Half of a round: the least familiar predicted failures; the rest random, never a
    candidate twice and never past an object's limit."""
    rng = np.random.default_rng(0)
    scored = [Scored(affordance=rng.random(30), similarity=rng.random(30)) for _ in range(40)]
    rule = get_strategy("similarity_failure_half")
    picks = rule.select(scored, 40, 2, rng)
    assert len(picks) == 40 and len(set(picks)) == 40
    assert max(np.bincount([o for o, _ in picks])) <= 2
    first = get_strategy("similarity_failure").select(scored, 20, 2, rng)
    assert picks[:20] == first
    # the random half reaches predicted successes, which the rule alone never takes first
    assert any(scored[o].affordance[c] > 0.5 for o, c in picks[20:])
    assert all(scored[o].affordance[c] <= 0.5 for o, c in first)
