"""Exploration strategies: which sampled action the few-shot loop executes next.

Each strategy sees the scored candidates of every object the loop may touch and returns
(object, candidate). ``similarity`` is Where2Explore's rule (lowest similarity = least
familiar geometry); ``where2act`` / ``nosim`` explore where the affordance is least certain
(closest to 0.5), with the Where2Act baseline model or with ours; ``random`` picks uniformly;
``none`` does not explore (the no-explore lower bound).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Scored:
    """Predictions for the candidate actions on one object."""

    affordance: np.ndarray  # (C,) probability that the action moves a part
    similarity: np.ndarray  # (C,) predicted similarity to the known geometry, in [0, 1]


@dataclass(frozen=True)
class Strategy:
    """A selection rule. ``explores`` False: the loop spends no interaction.
    ``stops_at_bar``: the loop stops when the mean similarity passes the bar (only meaningful
    for models whose similarity head was trained)."""

    name: str
    explores: bool = True
    stops_at_bar: bool = False

    def choose(self, scored: list[Scored], rng: np.random.Generator) -> tuple[int, int]:
        """(object index, candidate index) of the action to execute next."""
        if not self.explores:
            raise RuntimeError(f"strategy {self.name!r} does not explore")
        if self.name == "random":
            sizes = np.array([len(s.affordance) for s in scored])
            obj = int(rng.choice(np.flatnonzero(sizes)))
            return obj, int(rng.integers(sizes[obj]))
        keys = [self.key(s) for s in scored]
        best = [int(np.argmin(k)) if len(k) else -1 for k in keys]
        vals = np.array([k[b] if b >= 0 else np.inf for k, b in zip(keys, best, strict=True)])
        obj = int(np.argmin(vals))
        return obj, best[obj]

    def key(self, s: Scored) -> np.ndarray:
        """Lower = explore first."""
        if self.name == "similarity":
            return s.similarity
        return np.abs(s.affordance - 0.5)  # where2act / nosim: the least certain action


STRATEGIES: dict[str, Strategy] = {
    "similarity": Strategy("similarity", stops_at_bar=True),
    "where2act": Strategy("where2act"),
    "nosim": Strategy("nosim"),
    "random": Strategy("random"),
    "none": Strategy("none", explores=False),
}


def get_strategy(name: str) -> Strategy:
    if name not in STRATEGIES:
        raise ValueError(f"unknown strategy {name!r}; known: {', '.join(STRATEGIES)}")
    return STRATEGIES[name]
