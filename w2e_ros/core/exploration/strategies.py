"""Exploration strategies: the registry of selection rules the few-shot loop, the benchmark
and the planner choose by name.

Two parts. :data:`STRATEGIES` holds the rules a user picks (the planner's ``strategy``
parameter, ``w2e demo --strategy``): ``similarity`` (Where2Explore's, the paper's),
``random`` (the baseline), ``where2act`` (Where2Act's uncertainty rule) and
:data:`BEST_RULE`, the one that explored best on the validation split. :data:`EXPERIMENTAL`
holds the others, which ``w2e benchmark --methods``, ``w2e fewshot`` and the bench scripts
still run (``get_strategy(name, experimental=True)``); the planner refuses them. The
parameter description and the ``--help`` texts are made from the entries
(:func:`describe_rules`), so a rule added or promoted here is listed everywhere.

Each entry names a set rule of :mod:`w2e_ros.core.exploration.selection` (a round's picks over
all objects, chosen jointly) and says what it needs (hindsight labels, the geometric
familiarity, the encoder features) and whether it stops at the similarity bar; the loop knows
only the entry. Rules that rank candidates one by one are key rules (lower key = explore
first; :func:`w2e_ros.core.exploration.selection.key_rule`).

Key rules: ``similarity`` is Where2Explore's rule (lowest similarity = least familiar
geometry), ``similarity_sampled`` draws in proportion to unfamiliarity instead,
``similarity_mixed`` takes half its picks as the least familiar of each object and half at
random (meant to add successes without losing the spread; measured: an object's own least
familiar candidate is rarely a success, and the rule ties random);
``similarity_failure`` takes the least familiar of the actions the model predicts to fail
(where a success it did not expect would teach it), spending the whole budget (no bar), and
``nosim_failure`` is its control without the similarity (the predicted failures nearest 0.5);
``similarity_failure_half`` takes half of each round that way and half at random (measured
on cfw pull: all three tie random or lose to it);
``where2act`` / ``nosim`` explore where the affordance is least certain (closest to 0.5),
with the Where2Act baseline model or with ours; ``confident`` tries the actions the model
rates most likely to succeed (a baseline: it finds successes, but the ones the model already
expected, and measured below random on pull); ``random`` ranks at random;
``geometry`` explores the actions whose contact neighbourhood looks least like the training
contacts' (a model-free familiarity, :mod:`w2e_ros.core.exploration.familiarity`, that
follows where the model is right across novel categories where the similarity head does not) and
``geometry_sampled`` draws in proportion to that unfamiliarity (offline only: they need the
training contacts; measured on cfw pull: both tie random);
``oracle`` uses hindsight labels from the simulator and picks the actions the current model
gets most wrong (the most any selection rule can win); ``none`` does not explore.

Set rules on the encoder features (issue 40, the low-budget anchors): ``coverage_success``
(k-means into the round's budget, a success-weighted draw per cluster;
``coverage_success_sharp`` sharpens the draw towards the likeliest successes), ``typiclust`` and
``probcover``, ``similarity_coverage`` (the similarity allocates the round over objects,
coverage picks inside one) and ``balanced`` (half predicted successes, half near the
boundary; needs no features), ``thompson`` (k-means clusters, in each the likeliest success
under a fresh MC-dropout sample of the affordance head: Thompson sampling with coverage;
``thompson_light`` at a lower dropout rate, ``thompson_flat`` without the clusters). The
stack's inference node returns no features or draws yet, so these rules are offline only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from w2e_ros.core.exploration import selection as sel
from w2e_ros.core.exploration.selection import Pool, Rule


@dataclass
class Scored:
    """Predictions for the candidate actions on one object."""

    affordance: np.ndarray  # (C,) probability that the action moves a part
    similarity: np.ndarray  # (C,) predicted similarity to the known geometry, in [0, 1]
    familiarity: np.ndarray | None = None  # (C,) geometric closeness to the training contacts
    features: np.ndarray | None = None  # (C, F) float32 encoder features at the contact point
    draws: np.ndarray | None = None  # (S, C) sampled success probabilities (MC dropout)


# --- the per-candidate keys (lower = explore first); each sees one object's candidates ------

def _random(p: Pool, rng: np.random.Generator) -> np.ndarray:
    return rng.random(len(p))


def _similarity(p: Pool, rng: np.random.Generator) -> np.ndarray:
    return p.similarity


def _similarity_sampled(p: Pool, rng: np.random.Generator) -> np.ndarray:
    # drawn in proportion to unfamiliarity (1 - similarity), without replacement
    # (Efraimidis-Spirakis keys): the paper's rule always takes the extreme, which on a pull
    # is the model's most confident false positive, again and again
    w = np.clip(1.0 - p.similarity, 1e-6, None)
    return -np.log(rng.random(len(w)) + 1e-12) / w


def _similarity_mixed(p: Pool, rng: np.random.Generator) -> np.ndarray:
    # a coin per candidate: heads keys by its similarity rank within the object, tails by a
    # uniform draw; both keys are uniform over [0, 1), so across objects about half of a
    # round is each object's least familiar, half random
    n = len(p)
    rank = (np.argsort(np.argsort(p.similarity, kind="stable"), kind="stable")
            + rng.random(n)) / max(n, 1)
    return np.where(rng.random(n) < 0.5, rank, rng.random(n))


def _similarity_failure(p: Pool, rng: np.random.Generator) -> np.ndarray:
    # the least familiar of the actions the model predicts to fail: the teaching signal is a
    # success the model did not expect, and the similarity's own low scores fall mostly on
    # predicted successes (its class prior), which it skips
    return p.similarity + 2.0 * (p.affordance > 0.5)


def _nosim_failure(p: Pool, rng: np.random.Generator) -> np.ndarray:
    return -p.affordance + 2.0 * (p.affordance > 0.5)  # the predicted failures nearest 0.5


def _familiarity(p: Pool) -> np.ndarray:
    if p.familiarity is None:
        raise ValueError("this strategy needs the geometric familiarity of the candidates "
                         "(a bank of training contacts)")
    return p.familiarity


def _geometry(p: Pool, rng: np.random.Generator) -> np.ndarray:
    return _familiarity(p)


def _geometry_sampled(p: Pool, rng: np.random.Generator) -> np.ndarray:
    # in proportion to the distance from the bank (Efraimidis-Spirakis)
    w = np.clip(-_familiarity(p), 1e-6, None)
    return -np.log(rng.random(len(w)) + 1e-12) / w


def _confident(p: Pool, rng: np.random.Generator) -> np.ndarray:
    return -p.affordance


def _oracle(p: Pool, rng: np.random.Generator) -> np.ndarray:
    if p.labels is None:
        raise ValueError("the oracle needs hindsight labels of the candidates")
    return -np.abs(p.affordance - np.asarray(p.labels, np.float32))


def _uncertain(p: Pool, rng: np.random.Generator) -> np.ndarray:
    return np.abs(p.affordance - 0.5)  # where2act / nosim: the least certain action


def _no_rule(pool: Pool, k: int, rng: np.random.Generator) -> np.ndarray:
    raise RuntimeError("this strategy does not explore")


# --- the registry ----------------------------------------------------------------------------

@dataclass(frozen=True)
class Strategy:
    """A registry entry: a selection rule and what the loop must give it.
    ``explores`` False: the loop spends no interaction.
    ``stops_at_bar``: an object stops being explored when its mean similarity passes the
    bar (only meaningful for models whose similarity head was trained).
    ``needs_labels``: the loop must give hindsight outcomes of the candidates (oracle).
    ``needs_familiarity``: the loop must fill ``Scored.familiarity`` (a training bank).
    ``needs_features``: the model must fill ``Scored.features`` (the encoder's).
    ``draws`` / ``dropout``: the model must fill ``Scored.draws`` with that many MC-dropout
    samples of the success probability (Thompson-style rules).
    ``summary``: what the rule does, in a few words without a semicolon (the user-facing
    rules' help texts)."""

    name: str
    rule: Rule = _no_rule
    explores: bool = True
    stops_at_bar: bool = False
    needs_labels: bool = False
    needs_familiarity: bool = False
    needs_features: bool = False
    draws: int = 0  # > 0: the model must fill ``Scored.draws`` with this many samples
    dropout: float = 0.0  # the MC-dropout rate of those samples
    summary: str = ""

    @property
    def offline_only(self) -> bool:
        """What the stack cannot give: labels, a training bank, the encoder's features or
        posterior draws."""
        return (self.needs_labels or self.needs_familiarity or self.needs_features
                or self.draws > 0)

    def keys(self, s: Scored, rng: np.random.Generator,
             labels: np.ndarray | None = None) -> np.ndarray:
        """A key rule's keys for one object's candidates (lower = explore first)."""
        key = getattr(self.rule, "key", None)
        if key is None:
            raise ValueError(f"strategy {self.name!r} chooses sets, it has no per-candidate key")
        return key(_pool([s], 0, None if labels is None else [labels]), rng)

    def select(self, scored: list[Scored], k: int, per_object: int | Sequence[int],
               rng: np.random.Generator, labels: list[np.ndarray] | None = None,
               explored: np.ndarray | None = None) -> list[tuple[int, int]]:
        """At most ``k`` distinct (object, candidate) picks over all objects, at most
        ``per_object`` (one number, or one per object) from one object, in execution order.
        ``explored``: (E, F) features of the interactions already taken (coverage rules)."""
        if not self.explores:
            raise RuntimeError(f"strategy {self.name!r} does not explore")
        pool = _pool(scored, per_object, labels, explored)
        picks = self.rule(pool, k, rng)
        return [(int(pool.obj[i]), int(pool.local[i])) for i in picks]

    def choose(self, scored: list[Scored], rng: np.random.Generator,
               labels: list[np.ndarray] | None = None) -> tuple[int, int]:
        """(object index, candidate index) of the single best action."""
        return self.select(scored, 1, 1, rng, labels)[0]


def _pool(scored: Sequence[Scored], per_object: int | Sequence[int],
          labels: Sequence[np.ndarray] | None = None,
          explored: np.ndarray | None = None) -> Pool:
    """The round's candidates of ``scored`` as one flat :class:`Pool`; an optional array
    (familiarity, features) is kept only when every object with candidates has it."""
    sizes = [len(s.affordance) for s in scored]
    limits = (np.full(len(scored), per_object, np.int64) if isinstance(per_object, int)
              else np.asarray(per_object, np.int64))

    def flat(arrays: list[np.ndarray | None], dtype: type, axis: int = 0) -> np.ndarray | None:
        if any(a is None for a, n in zip(arrays, sizes, strict=True) if n):
            return None
        parts = [np.asarray(a, dtype) for a, n in zip(arrays, sizes, strict=True) if n]
        return np.concatenate(parts, axis=axis) if parts else None

    return Pool(
        obj=np.repeat(np.arange(len(scored)), sizes),
        local=np.concatenate([np.arange(n) for n in sizes]) if sizes else np.zeros(0, int),
        affordance=np.concatenate([np.asarray(s.affordance) for s in scored])
        if scored else np.zeros(0),
        similarity=np.concatenate([np.asarray(s.similarity) for s in scored])
        if scored else np.zeros(0),
        limits=limits,
        features=flat([s.features for s in scored], np.float32),
        familiarity=flat([s.familiarity for s in scored], np.float64),
        draws=flat([s.draws for s in scored], np.float64, axis=1),  # (S, C)
        labels=None if labels is None else flat(list(labels), np.float32),
        explored=explored)


_KEYED = sel.key_rule
THOMPSON_DRAWS = 16  # posterior samples per candidate and round
# the masks' rate: 0.5 gives a Bernoulli mask its widest spread, 0.2 (``thompson_light``) a
# posterior held closer to the mean; the head was trained without dropout, so neither is a
# calibrated posterior and the benchmark chooses between them (bench/RESEARCH.md)
THOMPSON_DROPOUT = 0.5
THOMPSON_LIGHT_DROPOUT = 0.2
_ALL: dict[str, Strategy] = {
    "similarity": Strategy("similarity", _KEYED(_similarity), stops_at_bar=True,
                           summary="the paper's rule (Where2Explore): the least familiar "
                           "geometry first, until an object's mean similarity passes the bar"),
    "similarity_sampled": Strategy("similarity_sampled", _KEYED(_similarity_sampled),
                                   stops_at_bar=True),
    "similarity_mixed": Strategy("similarity_mixed", _KEYED(_similarity_mixed),
                                 stops_at_bar=True),
    "similarity_failure": Strategy("similarity_failure", _KEYED(_similarity_failure)),
    "nosim_failure": Strategy("nosim_failure", _KEYED(_nosim_failure)),
    "similarity_failure_half": Strategy("similarity_failure_half",
                                        sel.half_rule(_KEYED(_similarity_failure))),
    "where2act": Strategy("where2act", _KEYED(_uncertain),
                          summary="Where2Act's rule: the least certain predicted success "
                          "(closest to 0.5) first"),
    "nosim": Strategy("nosim", _KEYED(_uncertain)),
    "confident": Strategy("confident", _KEYED(_confident)),
    "random": Strategy("random", _KEYED(_random),
                       summary="the baseline: candidates in random order"),
    "geometry": Strategy("geometry", _KEYED(_geometry), needs_familiarity=True),
    "geometry_sampled": Strategy("geometry_sampled", _KEYED(_geometry_sampled),
                                 needs_familiarity=True),
    "oracle": Strategy("oracle", _KEYED(_oracle), needs_labels=True),
    "coverage_success": Strategy("coverage_success", sel.coverage_success,
                                 needs_features=True),
    "coverage_success_sharp": Strategy(
        "coverage_success_sharp",
        partial(sel.coverage_success, target=sel.SHARP_SUCCESS_TARGET), needs_features=True),
    "typiclust": Strategy("typiclust", sel.typiclust, needs_features=True),
    "probcover": Strategy("probcover", sel.probcover, needs_features=True),
    "similarity_coverage": Strategy("similarity_coverage", sel.similarity_coverage,
                                    needs_features=True),
    "balanced": Strategy("balanced", sel.balanced),
    "thompson": Strategy("thompson", sel.thompson, needs_features=True,
                         draws=THOMPSON_DRAWS, dropout=THOMPSON_DROPOUT),
    "thompson_light": Strategy("thompson_light", sel.thompson, needs_features=True,
                               draws=THOMPSON_DRAWS, dropout=THOMPSON_LIGHT_DROPOUT),
    "thompson_flat": Strategy("thompson_flat", partial(sel.thompson, cover=False),
                              needs_features=True, draws=THOMPSON_DRAWS,
                              dropout=THOMPSON_DROPOUT),
    "none": Strategy("none", explores=False),
}

BEST_RULE = "random"
"""The rule that explored best on the validation split, the one a user is told to take: so far
every other rule ties random or loses to it (the measurements above, bench/RESEARCH.md). A rule
takes its place only by measuring better there; an experimental one is then moved into the
user-facing set."""

USER_FACING = ("similarity", "random", "where2act", BEST_RULE)
"""The rules a user picks from: the paper's, the baseline, Where2Act's and the best measured."""

STRATEGIES: dict[str, Strategy] = {n: _ALL[n] for n in dict.fromkeys(USER_FACING)}
"""The user-facing rules (the planner, ``w2e demo``), each runnable by the stack."""

EXPERIMENTAL: dict[str, Strategy] = {n: s for n, s in _ALL.items() if n not in STRATEGIES}
"""Every other rule: for the benchmark, ``w2e fewshot`` and the bench scripts only."""


def registry(experimental: bool = False) -> dict[str, Strategy]:
    """Name -> entry: the user-facing rules, or every rule (``experimental``) in one order."""
    return dict(_ALL) if experimental else dict(STRATEGIES)


def describe_rules(experimental: bool = False) -> str:
    """The rules a user may pick, each with what it does, for a parameter description or a
    ``--help`` text (``experimental``: the experiments' names follow)."""
    text = "; ".join(f"{n} = {s.summary}" + (", the best on the validation split so far"
                                               if n == BEST_RULE else "")
                     for n, s in STRATEGIES.items())
    if experimental:
        text += "; experiments (offline): " + ", ".join(EXPERIMENTAL)
    return text


def get_strategy(name: str, experimental: bool = False) -> Strategy:
    """The registry entry called ``name``: a user-facing rule, or with ``experimental`` any
    rule. A typo or an experiment where only the user-facing rules go fails here, naming the
    allowed ones."""
    if name in STRATEGIES:
        return STRATEGIES[name]
    if name in EXPERIMENTAL and experimental:
        return EXPERIMENTAL[name]
    allowed = ", ".join(registry(experimental))
    if name in EXPERIMENTAL:
        raise ValueError(f"strategy {name!r} is an experiment (w2e benchmark --methods, w2e "
                         f"fewshot), not a rule for the robot; the rules: {allowed}")
    raise ValueError(f"unknown strategy {name!r}; the rules: {allowed}")
