"""Each strategy picks what it claims to pick."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from w2e_ros.core.exploration.selection import allocate, success_weights
from w2e_ros.core.exploration.strategies import (
    BEST_RULE,
    EXPERIMENTAL,
    STRATEGIES,
    Scored,
    Strategy,
    describe_rules,
    get_strategy,
    registry,
)


def entry(name: str) -> Strategy:
    """Any rule of the registry, the experiments' too."""
    return get_strategy(name, experimental=True)


def _scored() -> list[Scored]:
    return [
        Scored(affordance=np.array([0.9, 0.1, 0.7]), similarity=np.array([0.8, 0.6, 0.9])),
        Scored(affordance=np.array([0.45, 0.0]), similarity=np.array([0.7, 0.2])),
        Scored(affordance=np.array([]), similarity=np.array([])),
        Scored(affordance=np.array([0.52, 0.99]), similarity=np.array([0.5, 0.95])),
    ]


def test_similarity_picks_the_lowest_similarity_over_all_objects():
    assert entry("similarity").choose(_scored(), np.random.default_rng(0)) == (1, 1)


@pytest.mark.parametrize("name", ["where2act", "nosim"])
def test_uncertainty_rules_pick_the_affordance_closest_to_one_half(name):
    assert entry(name).choose(_scored(), np.random.default_rng(0)) == (3, 0)


def test_confident_tries_the_likeliest_successes_first_capped_per_object():
    picks = entry("confident").select(_scored(), 3, 1, np.random.default_rng(0))
    assert picks == [(3, 1), (0, 0), (1, 0)]  # 0.99, 0.9, then object 1's best (0.45)


def test_random_picks_valid_candidates_from_every_object():
    rng = np.random.default_rng(0)
    picks = [entry("random").choose(_scored(), rng) for _ in range(200)]
    sizes = [3, 2, 0, 2]
    assert all(0 <= i < sizes[o] for o, i in picks)
    assert {o for o, _ in picks} == {0, 1, 3}


def test_none_does_not_explore_and_only_similarity_stops_at_the_bar():
    none = entry("none")
    assert not none.explores
    with pytest.raises(RuntimeError):
        none.choose(_scored(), np.random.default_rng(0))
    assert entry("similarity").stops_at_bar
    assert not entry("where2act").stops_at_bar
    with pytest.raises(ValueError):
        get_strategy("curiosity", experimental=True)



# --- the user-facing rules and the experiments ------------------------------------------------

def test_the_user_picks_from_the_paper_the_baseline_where2act_and_the_best_rule():
    assert set(STRATEGIES) == {"similarity", "random", "where2act", BEST_RULE}
    assert BEST_RULE == "random"  # every other rule ties it or loses to it on validation
    assert not set(STRATEGIES) & set(EXPERIMENTAL)
    assert registry(experimental=True) == {**STRATEGIES, **EXPERIMENTAL}
    assert {"similarity_sampled", "geometry", "oracle", "typiclust", "none"} <= set(EXPERIMENTAL)


def test_every_user_facing_rule_runs_on_the_stack():
    """The planner runs them: no hindsight labels, no training bank, no encoder features."""
    for name, s in STRATEGIES.items():
        assert s.name == name and s.explores and not s.offline_only, name
        assert s.summary and ";" not in s.summary, name


def test_an_experiment_is_refused_where_only_the_user_facing_rules_go():
    with pytest.raises(ValueError, match="is an experiment") as err:
        get_strategy("geometry")
    assert "similarity, random, where2act" in str(err.value)
    assert get_strategy("geometry", experimental=True) is EXPERIMENTAL["geometry"]
    with pytest.raises(ValueError, match="unknown strategy 'simlarity'; the rules: similarity"):
        get_strategy("simlarity")


def test_the_help_text_names_every_user_facing_rule_and_the_experiments_on_request():
    text = describe_rules()
    assert [part.split(" = ")[0] for part in text.split("; ")] == list(STRATEGIES)
    assert "the best on the validation split" in text.split("; ")[list(STRATEGIES).index(BEST_RULE)]
    assert describe_rules(experimental=True).endswith(", ".join(EXPERIMENTAL))

def test_select_takes_the_lowest_keys_over_all_objects_capped_per_object():
    sim = entry("similarity")
    rng = np.random.default_rng(0)
    # similarity keys: (1,1)=0.2 (3,0)=0.5 (0,1)=0.6 (1,0)=0.7 (0,0)=0.8 (0,2)=0.9 (3,1)=0.95
    assert sim.select(_scored(), 3, 2, rng) == [(1, 1), (3, 0), (0, 1)]
    assert sim.select(_scored(), 4, 1, rng) == [(1, 1), (3, 0), (0, 1)]  # one per object
    assert sim.select(_scored(), 5, 2, rng) == [(1, 1), (3, 0), (0, 1), (1, 0), (0, 0)]
    assert len(sim.select(_scored(), 100, 100, rng)) == 7  # every candidate, no more


def test_oracle_picks_what_the_model_gets_most_wrong_and_needs_labels():
    oracle = entry("oracle")
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
    rule = entry("similarity_sampled")
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
    rule = entry("similarity_mixed")
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
    assert [c for _, c in entry("similarity_failure").select(scored, 3, 5, rng)] == [1, 3, 2]
    assert [c for _, c in entry("nosim_failure").select(scored, 3, 5, rng)] == [2, 1, 3]
    # once the predicted failures are used up, the predicted successes follow
    assert entry("similarity_failure").select(scored, 5, 5, rng)[3:] == [(0, 0), (0, 4)]
    assert not entry("similarity_failure").stops_at_bar


def test_similarity_failure_half_takes_half_by_the_rule_and_half_at_random():
    """Half of a round: the least familiar predicted failures; the rest random, never a
    candidate twice and never past an object's limit."""
    rng = np.random.default_rng(0)
    scored = [Scored(affordance=rng.random(30), similarity=rng.random(30)) for _ in range(40)]
    rule = entry("similarity_failure_half")
    picks = rule.select(scored, 40, 2, rng)
    assert len(picks) == 40 and len(set(picks)) == 40
    assert max(np.bincount([o for o, _ in picks])) <= 2
    first = entry("similarity_failure").select(scored, 20, 2, rng)
    assert picks[:20] == first
    # the random half reaches predicted successes, which the rule alone never takes first
    assert any(scored[o].affordance[c] > 0.5 for o, c in picks[20:])
    assert all(scored[o].affordance[c] <= 0.5 for o, c in first)


# --- the set-based interface: the key rules keep their picks -------------------------------

GOLDEN = Path(__file__).parent / "golden" / "strategy_picks.json"
GOLDEN_SIZES = (5, 0, 12, 7, 1, 9)  # an object without candidates among them


def _golden_inputs(seed: int) -> tuple[list[Scored], list[np.ndarray]]:
    """The inputs the golden picks were recorded on (with the per-candidate code of
    2026-12-06, before the set interface)."""
    rng = np.random.default_rng(1000 + seed)
    scored, labels = [], []
    for n in GOLDEN_SIZES:
        scored.append(Scored(affordance=rng.random(n).astype(np.float32),
                             similarity=rng.random(n).astype(np.float32),
                             familiarity=-rng.random(n).astype(np.float32)))
        labels.append((rng.random(n) < 0.4).astype(np.float32))
    return scored, labels


def test_every_old_rule_gives_the_picks_it_gave_before_the_set_interface():
    """Picks recorded with the per-candidate keys and ``_lowest`` (commit 58992a1): every
    old rule, two seeds, four (budget, limit) cases, two rounds on one generator (so the
    generator is consumed as before too)."""
    golden = json.loads(GOLDEN.read_text())
    names = {key.split("|")[0] for key in golden}
    assert names == {n for n, s in registry(experimental=True).items()
                     if s.explores and not s.needs_features and n != "balanced"}
    for key, want in golden.items():
        name, seed, k, lim = key.split("|")
        scored, labels = _golden_inputs(int(seed))
        rule = entry(name)
        rng = np.random.default_rng(int(seed))
        got = [rule.select(scored, int(k), json.loads(lim), rng,
                           labels if rule.needs_labels else None) for _ in range(2)]
        assert [[list(p) for p in r] for r in got] == want, key


# --- the set rules ---------------------------------------------------------------------------

SET_RULES = ["coverage_success", "coverage_success_sharp", "typiclust", "probcover",
             "similarity_coverage", "balanced", "thompson", "thompson_flat"]
DRAWS = 8
N_CLUSTERS, PER_CLUSTER, FEAT_DIM = 8, 60, 16


def _clustered(seed: int = 0, n_objects: int = 24) -> tuple[list[Scored], np.ndarray]:
    """Candidates in N_CLUSTERS well-separated feature blobs, spread over ``n_objects``
    objects; returns the scored objects and each candidate's blob (flat, in pool order)."""
    rng = np.random.default_rng(seed)
    centres = np.eye(FEAT_DIM)[:N_CLUSTERS] * 10.0
    blob = rng.permutation(np.repeat(np.arange(N_CLUSTERS), PER_CLUSTER))
    feats = (centres[blob] + rng.normal(0, 0.3, (len(blob), FEAT_DIM))).astype(np.float32)
    obj = np.sort(rng.integers(0, n_objects, len(blob)))
    scored = [Scored(affordance=rng.random(int((obj == o).sum())),
                     similarity=rng.random(int((obj == o).sum())),
                     features=feats[obj == o]) for o in range(n_objects)]
    _posterior_around(scored, 0.2, rng)
    return scored, np.concatenate([blob[obj == o] for o in range(n_objects)])


def _posterior_around(scored: list[Scored], spread: float, rng: np.random.Generator) -> None:
    """Posterior draws scattered ``spread`` around each candidate's affordance."""
    for s in scored:
        noise = rng.normal(0, spread, (DRAWS, len(s.affordance)))
        s.draws = np.clip(s.affordance[None] + noise, 0, 1)


def _flat(scored: list[Scored], picks: list[tuple[int, int]]) -> list[int]:
    starts = np.cumsum([0] + [len(s.affordance) for s in scored])
    return [int(starts[o] + c) for o, c in picks]


@pytest.mark.parametrize("name", SET_RULES)
@pytest.mark.parametrize("k,limit", [(8, 1), (20, 2), (5, 3)])
def test_set_rules_return_k_distinct_candidates_within_the_limits(name, k, limit):
    scored, _ = _clustered()
    picks = entry(name).select(scored, k, limit, np.random.default_rng(3))
    assert len(picks) == k and len(set(picks)) == k
    assert max(np.bincount([o for o, _ in picks])) <= limit
    assert all(0 <= c < len(scored[o].affordance) for o, c in picks)


@pytest.mark.parametrize("name", SET_RULES)
def test_set_rules_respect_per_object_limits_given_per_object(name):
    scored, _ = _clustered()
    limits = [0 if o % 3 == 0 else 1 for o in range(len(scored))]  # a third of them closed
    picks = entry(name).select(scored, 12, limits, np.random.default_rng(1))
    assert len(picks) == 12
    counts = np.bincount([o for o, _ in picks], minlength=len(scored))
    assert np.all(counts <= limits)


@pytest.mark.parametrize("name", SET_RULES)
def test_set_rules_are_deterministic_per_seed(name):
    scored, _ = _clustered()
    rule = entry(name)
    a = rule.select(scored, 10, 2, np.random.default_rng(5))
    assert a == rule.select(scored, 10, 2, np.random.default_rng(5))
    others = [rule.select(scored, 10, 2, np.random.default_rng(s)) for s in range(6, 10)]
    if name != "typiclust":  # typiclust's most typical points barely depend on the seed
        assert any(o != a for o in others)


@pytest.mark.parametrize("name", ["coverage_success", "coverage_success_sharp", "typiclust",
                                  "probcover", "thompson"])
def test_coverage_rules_spread_a_round_over_the_feature_clusters(name):
    """k = clusters: one pick in every blob (random hits all 8 blobs with 8 picks in only
    8!/8^8 = 0.24 % of rounds)."""
    scored, blob = _clustered()
    for seed in range(5):
        picks = entry(name).select(scored, N_CLUSTERS, 2, np.random.default_rng(seed))
        assert len(set(blob[_flat(scored, picks)])) == N_CLUSTERS, seed


def test_typiclust_covers_the_clusters_the_explored_set_left_out():
    """One interaction explored in each of six blobs: explored + budget = 8 clusters, the
    blobs, and the round of two goes to the two blobs left."""
    scored, blob = _clustered()
    feats = np.concatenate([s.features for s in scored])
    explored = np.stack([feats[blob == b][0] for b in range(6)])
    for seed in range(3):
        picks = entry("typiclust").select(scored, 2, 2, np.random.default_rng(seed),
                                                 explored=explored)
        assert set(blob[_flat(scored, picks)]) == {6, 7}, seed


def test_typiclust_takes_a_dense_point_not_an_outlier():
    """One tight blob with a far outlier: the most typical pick is inside the blob."""
    rng = np.random.default_rng(0)
    feats = np.concatenate([rng.normal(0, 0.05, (50, 4)) + [1, 0, 0, 0],
                            [[0.6, 0.8, 0, 0]]]).astype(np.float32)
    scored = [Scored(np.full(51, 0.5), np.full(51, 0.5), features=feats)]
    (o, c), = entry("typiclust").select(scored, 1, 1, np.random.default_rng(0))
    assert c != 50


@pytest.mark.parametrize("name", ["coverage_success", "coverage_success_sharp",
                                  "similarity_coverage", "balanced", "thompson",
                                  "thompson_flat"])
def test_success_seeking_rules_pick_more_likely_successes_than_random(name):
    """Affordance skewed low (most candidates look like failures, as on pulls): over rounds
    the rule's picks are predicted successes (> 0.5) far more often than random's."""
    rng = np.random.default_rng(0)
    scored, _ = _clustered()
    for s in scored:
        s.affordance = rng.beta(0.5, 4.0, len(s.affordance))
    _posterior_around(scored, 0.2, rng)
    rule, rand = entry(name), entry("random")

    def high(r) -> float:
        picks = [p for seed in range(20)
                 for p in r.select(scored, 8, 2, np.random.default_rng(seed))]
        return float(np.mean([scored[o].affordance[c] > 0.5 for o, c in picks]))

    assert high(rule) > high(rand) + 0.2


def test_similarity_coverage_gives_the_unfamiliar_objects_the_round():
    """Half the objects familiar (similarity 0.95), half not (0.2): nearly all picks land on
    the unfamiliar ones; within one, its picks fall in different blobs."""
    scored, blob = _clustered()
    for o, s in enumerate(scored):
        s.similarity = np.full(len(s.affordance), 0.95 if o % 2 else 0.2)
    picks = entry("similarity_coverage").select(scored, 12, 2, np.random.default_rng(0))
    assert sum(o % 2 == 0 for o, _ in picks) >= 11
    flat = np.array(_flat(scored, picks))
    for o in {o for o, _ in picks}:
        mine = [f for (p, _), f in zip(picks, flat, strict=True) if p == o]
        if len(mine) == 2:
            assert blob[mine[0]] != blob[mine[1]] or len(set(blob[
                _flat(scored, [(o, c) for c in range(len(scored[o].affordance))])])) == 1


def test_allocate_is_proportional_within_caps():
    q = allocate(np.array([3.0, 1.0, 0.0, 4.0]), 6, np.array([2, 5, 5, 2]))
    assert q.sum() == 6 and np.all(q <= [2, 5, 5, 2]) and q[0] == 2 and q[3] == 2
    assert list(allocate(np.ones(3), 10, np.array([1, 1, 1]))) == [1, 1, 1]


def test_balanced_takes_half_predicted_successes_half_near_the_boundary():
    aff = np.array([0.95, 0.9, 0.85, 0.8, 0.52, 0.48, 0.1, 0.05, 0.02, 0.01])
    scored = [Scored(aff, np.zeros(10))]
    picks = [c for _, c in entry("balanced").select(scored, 4, 4,
                                                            np.random.default_rng(0))]
    assert all(aff[c] > 0.5 for c in picks[:2])
    assert set(picks[2:]) <= {4, 5, 3, 2} and len(set(picks)) == 4


def test_feature_rules_say_they_need_features_and_are_offline_only():
    scored = [Scored(np.array([0.2, 0.7]), np.array([0.5, 0.5]))]
    for name in ["coverage_success", "coverage_success_sharp", "typiclust", "probcover",
                 "similarity_coverage"]:
        rule = entry(name)
        assert rule.needs_features and rule.offline_only
        with pytest.raises(ValueError, match="features"):
            rule.select(scored, 1, 1, np.random.default_rng(0))
    assert not entry("balanced").offline_only
    assert not entry("similarity").offline_only and entry("oracle").offline_only
    with pytest.raises(ValueError, match="sets"):
        entry("typiclust").keys(scored[0], np.random.default_rng(0))


def test_thompson_takes_the_mean_where_the_posterior_is_sure_and_varies_where_it_is_not():
    """Draws all equal to the affordance: the flat rule is the per-object argmax, the same
    for every seed; draws wide apart: the picks change with the seed, and a candidate whose
    draws are all high beats one that is high only on average."""
    scored, _ = _clustered()
    rule = entry("thompson_flat")
    for s in scored:
        s.draws = np.repeat(s.affordance[None], DRAWS, axis=0)
    sure = [rule.select(scored, 6, 1, np.random.default_rng(seed)) for seed in range(4)]
    best = sorted(((-float(s.affordance.max()), o, int(s.affordance.argmax()))
                   for o, s in enumerate(scored)))[:6]
    assert all(picks == sure[0] for picks in sure)
    assert sorted(sure[0]) == sorted((o, c) for _, o, c in best)
    _posterior_around(scored, 2.0, np.random.default_rng(1))
    unsure = {tuple(rule.select(scored, 6, 1, np.random.default_rng(seed)))
              for seed in range(4)}
    assert len(unsure) > 1
    one = [Scored(np.array([0.5, 0.5]), np.array([0.5, 0.5]), features=np.eye(2, dtype=np.float32),
                  draws=np.array([[0.6, 1.0], [0.6, 0.0], [0.6, 0.0], [0.6, 0.0]]))]
    got = [rule.select(one, 1, 1, np.random.default_rng(seed))[0][1] for seed in range(40)]
    assert 0.6 < np.mean(np.array(got) == 0) < 0.9  # the sure one wins 3 draws in 4


def test_thompson_rules_need_posterior_draws_and_are_offline_only():
    scored = [Scored(np.array([0.2, 0.7]), np.array([0.5, 0.5]),
                     features=np.eye(2, dtype=np.float32))]
    for name in ["thompson", "thompson_light", "thompson_flat"]:
        rule = entry(name)
        assert rule.draws > 0 and 0 < rule.dropout < 1 and rule.offline_only
        with pytest.raises(ValueError, match="sampled success"):
            rule.select(scored, 1, 1, np.random.default_rng(0))


def test_the_sharp_draw_reaches_its_target_where_the_plain_one_stays_flat():
    """Affordances averaging ~0.45 (the shipped model's on pulls): weighting by affordance
    already gives a draw 0.4 expected success, so only the 0.7 target sharpens it."""
    a = np.random.default_rng(0).beta(2.0, 2.5, 5000)

    def expected(target: float) -> float:
        w = success_weights(a, target)
        return float((w * a).sum() / w.sum())

    assert expected(0.4) < 0.6 <= 0.7 <= expected(0.7)
