"""Exploration strategies: which sampled actions the few-shot loop executes next.

A strategy ranks every candidate action of every object it may touch (lower key = explore
first) and the loop takes a round's worth of the best ones over all objects, at most a few
per object. ``similarity`` is Where2Explore's rule (lowest similarity = least familiar
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
contacts' (a model-free familiarity, :mod:`w2e_ros.core.familiarity`, that follows where the
model is right across novel categories where the similarity head does not) and
``geometry_sampled`` draws in proportion to that unfamiliarity (offline only: they need the
training contacts; measured on cfw pull: both tie random);
``oracle`` uses hindsight labels from the simulator and picks the actions the current model
gets most wrong (the most any selection rule can win); ``none`` does not explore.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from operator import itemgetter

import numpy as np


@dataclass
class Scored:
    """Predictions for the candidate actions on one object."""

    affordance: np.ndarray  # (C,) probability that the action moves a part
    similarity: np.ndarray  # (C,) predicted similarity to the known geometry, in [0, 1]
    familiarity: np.ndarray | None = None  # (C,) geometric closeness to the training contacts


@dataclass(frozen=True)
class Strategy:
    """A selection rule. ``explores`` False: the loop spends no interaction.
    ``stops_at_bar``: an object stops being explored when its mean similarity passes the
    bar (only meaningful for models whose similarity head was trained).
    ``needs_labels``: the loop must give hindsight outcomes of the candidates (oracle).
    ``half_of``: half of each round by that rule, the rest at random.
    ``needs_familiarity``: the loop must fill ``Scored.familiarity`` (a training bank)."""

    name: str
    explores: bool = True
    stops_at_bar: bool = False
    needs_labels: bool = False
    half_of: str | None = None
    needs_familiarity: bool = False

    def keys(self, s: Scored, rng: np.random.Generator,
             labels: np.ndarray | None = None) -> np.ndarray:
        """Lower = explore first."""
        if self.name == "random":
            return rng.random(len(s.affordance))
        if self.name == "similarity":
            return s.similarity
        if self.name == "similarity_sampled":
            # drawn in proportion to unfamiliarity (1 - similarity), without replacement
            # (Efraimidis-Spirakis keys): the paper's rule always takes the extreme, which on
            # a pull is the model's most confident false positive, again and again
            w = np.clip(1.0 - s.similarity, 1e-6, None)
            return -np.log(rng.random(len(w)) + 1e-12) / w
        if self.name == "similarity_mixed":
            # a coin per candidate: heads keys by its similarity rank within the object,
            # tails by a uniform draw; both keys are uniform over [0, 1), so across objects
            # about half of a round is each object's least familiar, half random
            n = len(s.similarity)
            rank = (np.argsort(np.argsort(s.similarity, kind="stable"), kind="stable")
                    + rng.random(n)) / max(n, 1)
            return np.where(rng.random(n) < 0.5, rank, rng.random(n))
        if self.name == "similarity_failure":
            # the least familiar of the actions the model predicts to fail: the teaching
            # signal is a success the model did not expect, and the similarity's own low
            # scores fall mostly on predicted successes (its class prior), which it skips
            return s.similarity + 2.0 * (s.affordance > 0.5)
        if self.name == "nosim_failure":  # its control: the predicted failures nearest 0.5
            return -s.affordance + 2.0 * (s.affordance > 0.5)
        if self.needs_familiarity:
            if s.familiarity is None:
                raise ValueError(f"strategy {self.name!r} needs the geometric familiarity of "
                                 "the candidates (a bank of training contacts)")
            if self.name == "geometry":
                return s.familiarity
            # geometry_sampled: in proportion to the distance from the bank (Efraimidis-Spirakis)
            w = np.clip(-s.familiarity, 1e-6, None)
            return -np.log(rng.random(len(w)) + 1e-12) / w
        if self.name == "confident":
            return -s.affordance
        if self.name == "oracle":
            if labels is None:
                raise ValueError("the oracle needs hindsight labels of the candidates")
            return -np.abs(s.affordance - np.asarray(labels, np.float32))
        return np.abs(s.affordance - 0.5)  # where2act / nosim: the least certain action

    def select(self, scored: list[Scored], k: int, per_object: int | Sequence[int],
               rng: np.random.Generator,
               labels: list[np.ndarray] | None = None) -> list[tuple[int, int]]:
        """The ``k`` lowest-key (object, candidate) pairs over all objects, at most
        ``per_object`` (one number, or one per object) from one object, best first."""
        if not self.explores:
            raise RuntimeError(f"strategy {self.name!r} does not explore")
        limits = [per_object] * len(scored) if isinstance(per_object, int) else per_object
        if self.half_of:
            return self._half_and_half(scored, k, limits, rng)
        keys = [self.keys(s, rng, None if labels is None else labels[o]) if len(s.affordance)
                else np.zeros(0) for o, s in enumerate(scored)]
        return _lowest(keys, k, limits)

    def _half_and_half(self, scored: list[Scored], k: int, limits: Sequence[int],
                       rng: np.random.Generator) -> list[tuple[int, int]]:
        """Half of the round by ``half_of``, the rest at random among what is left (the
        per-object limits hold over both halves): random's class mix, which keeps the fitted
        head's calibration, plus what the rule finds."""
        first = get_strategy(self.half_of).select(scored, k // 2, limits, rng)
        left = list(limits)
        free = [np.ones(len(s.affordance), bool) for s in scored]
        for o, c in first:
            left[o] -= 1
            free[o][c] = False
        keys = []  # random keys for what is left; the taken ones can not come again
        for f in free:
            key = np.full(len(f), np.inf)
            key[f] = rng.random(int(f.sum()))
            keys.append(key)
        return first + _lowest(keys, k - len(first), left)

    def choose(self, scored: list[Scored], rng: np.random.Generator,
               labels: list[np.ndarray] | None = None) -> tuple[int, int]:
        """(object index, candidate index) of the single best action."""
        return self.select(scored, 1, 1, rng, labels)[0]


def _lowest(keys: list[np.ndarray], k: int, limits: Sequence[int]) -> list[tuple[int, int]]:
    """The ``k`` lowest finite keys over all objects, at most ``limits[o]`` from object o,
    lowest first: a round of one rule, chosen globally."""
    pool: list[tuple[float, int, int]] = []
    for o, key in enumerate(keys):
        for c in np.argsort(key, kind="stable")[:max(int(limits[o]), 0)]:
            if np.isfinite(key[c]):
                pool.append((float(key[c]), o, int(c)))
    pool.sort(key=itemgetter(0))
    return [(o, c) for _, o, c in pool[:k]]


STRATEGIES: dict[str, Strategy] = {
    "similarity": Strategy("similarity", stops_at_bar=True),
    "similarity_sampled": Strategy("similarity_sampled", stops_at_bar=True),
    "similarity_mixed": Strategy("similarity_mixed", stops_at_bar=True),
    "similarity_failure": Strategy("similarity_failure"),
    "nosim_failure": Strategy("nosim_failure"),
    "similarity_failure_half": Strategy("similarity_failure_half",
                                        half_of="similarity_failure"),
    "where2act": Strategy("where2act"),
    "nosim": Strategy("nosim"),
    "confident": Strategy("confident"),
    "random": Strategy("random"),
    "geometry": Strategy("geometry", needs_familiarity=True),
    "geometry_sampled": Strategy("geometry_sampled", needs_familiarity=True),
    "oracle": Strategy("oracle", needs_labels=True),
    "none": Strategy("none", explores=False),
}


def get_strategy(name: str) -> Strategy:
    if name not in STRATEGIES:
        raise ValueError(f"unknown strategy {name!r}; known: {', '.join(STRATEGIES)}")
    return STRATEGIES[name]
