"""Which interactions make a training batch: a fixed share of the clouds from ``C_aff`` (so
the affordance head is not starved by the other ``C_sim`` categories), the rest equally per
category; per cloud half positives, a quarter negatives and a quarter flipped-approach copies
(``up`` reversed, labelled failure: the reference's extra negatives, sharing the original's
accuracy counter)."""

from __future__ import annotations

import numpy as np

from w2e_ros.core.dataset.interactions import InteractionData


class BalancedSampler:
    """Batches of ``clouds`` observations x ``per_cloud`` interactions (+ flipped copies).

    ``aff_share`` of the clouds come from ``aff_categories`` (when given and present), the
    rest from the other categories drawn equally; half the clouds come from observations
    that have a positive interaction, and each cloud gives half positives, half negatives
    where it can. ``flip_share`` x ``per_cloud`` of a cloud's negatives are flipped copies
    of its interactions instead of stored failures (the reference's extra negatives).
    """

    def __init__(self, data: InteractionData, categories: tuple[str, ...], clouds: int,
                 per_cloud: int, rng: np.random.Generator,
                 aff_categories: tuple[str, ...] = (), aff_share: float = 0.0,
                 flip_share: float = 0.0) -> None:
        self.data, self.clouds, self.per_cloud, self.rng = data, clouds, per_cloud, rng
        self.flip_share = flip_share
        order = np.argsort(data.obs_index, kind="stable")
        bounds = np.searchsorted(data.obs_index[order], np.arange(data.num_observations + 1))
        self.all: list[np.ndarray] = []
        self.pos: list[np.ndarray] = []
        self.neg: list[np.ndarray] = []
        for o in range(data.num_observations):
            rows = order[bounds[o]:bounds[o + 1]]
            self.all.append(rows)
            self.pos.append(rows[data.success[rows]])
            self.neg.append(rows[~data.success[rows]])
        self.by_cat: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for c in categories:
            obs = np.flatnonzero(data.category == c)
            obs = obs[[len(self.all[o]) > 0 for o in obs]]
            if len(obs) == 0:
                continue
            with_pos = obs[[len(self.pos[o]) > 0 for o in obs]]
            self.by_cat[c] = (obs, with_pos)
        if not self.by_cat:
            raise ValueError(f"no interactions of categories {', '.join(categories)} in the "
                             "training data: collect them with `w2e collect`")
        self.categories = tuple(self.by_cat)
        aff = [c for c in self.categories if c in aff_categories]
        rest = [c for c in self.categories if c not in aff_categories]
        # probability of drawing each category for a cloud
        if aff and rest and aff_share > 0:
            p = [aff_share / len(aff) if c in aff else (1 - aff_share) / len(rest)
                 for c in self.categories]
        else:
            p = [1.0 / len(self.categories)] * len(self.categories)
        self.cat_prob = np.asarray(p) / np.sum(p)

    def sample(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, flip): the interactions of one batch and which of them enter flipped."""
        rng, half = self.rng, self.per_cloud // 2
        cats = rng.choice(len(self.categories), size=self.clouds, p=self.cat_prob)
        rows, flips = [], []
        for i, ci in enumerate(cats):
            obs, with_pos = self.by_cat[self.categories[ci]]
            pool = with_pos if (i % 2 == 0 and len(with_pos)) else obs
            o = int(pool[rng.integers(len(pool))])
            pos, neg = self.pos[o], self.neg[o]
            n_flip = int(round(self.flip_share * self.per_cloud))
            n_pos = half if len(pos) else 0
            n_neg = self.per_cloud - n_pos - n_flip
            if not len(neg):
                n_neg, n_pos = 0, self.per_cloud - n_flip
            for pool_rows, n, flipped in ((pos, n_pos, False), (neg, n_neg, False),
                                          (self.all[o], n_flip, True)):
                if n > 0 and len(pool_rows):
                    rows.append(rng.choice(pool_rows, size=n, replace=len(pool_rows) < n))
                    flips.append(np.full(n, flipped))
        return np.concatenate(rows), np.concatenate(flips)
