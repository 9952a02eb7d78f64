"""Set-based selection: which of a round's candidates, over all objects, the loop executes.

A rule is a small pure function ``rule(pool, k, rng) -> indices``: ``pool`` holds the round's
candidates of every object as flat arrays (object index, predicted affordance, similarity and,
where the rule needs them, encoder features at the contact point, geometric familiarity and
hindsight labels) with each object's limit for the round; it returns at most ``k`` distinct
candidate indices into the pool, in the order they are executed, never more than an object's
limit from one object. Rules choose a round jointly (clusters, coverage, quotas); a rule that
ranks candidates one by one is the special case :func:`key_rule` builds, with the same picks
as the per-candidate keys the loop used before (the old benchmark results stay
reproducible). The registry that names the rules is :mod:`w2e_ros.core.exploration.strategies`.

The coverage rules follow the low-budget active-learning anchors (issue 40, bench/RESEARCH.md):
TypiClust (arXiv 2202.02794), ProbCover (arXiv 2205.11320), success-seeking draws as in
Where2Act's online sampling, and label-balanced picks as in BASE (arXiv 2111.12880).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

# k-means: Lloyd iterations after a k-means++ start, fitted on at most this many candidates
# (a uniform sample keeps the pool's density) and then assigned over the whole pool
KMEANS_ITERS = 8
KMEANS_FIT_SAMPLE = 4096
# TypiClust / ProbCover work on a uniform sample of the pool of at most this size: both need
# distances between candidates, quadratic in the pool (a round holds up to ~10^5 candidates)
POOL_SAMPLE = 4096
MAX_CLUSTERS = 500  # TypiClust's own cap on labelled + budget clusters
TYPICALITY_NEIGHBOURS = 20  # typicality = 1 / mean distance to this many nearest neighbours
TYPICALITY_REFERENCE = 1024  # neighbours searched among at most this many cluster members
# ProbCover's ball radius: the distance quantile at which one ball holds on average this
# share of the pool divided by the budget (1: k balls of average size would cover it once)
PROBCOVER_BALL_SHARE = 1.0
PROBCOVER_SAMPLE = 3000
# success-seeking draws: weight affordance ** gamma with the smallest gamma in the grid whose
# expected predicted success of a draw reaches the target (30-50 % successes, issue 40)
SUCCESS_TARGET = 0.4
# measured on validation: the shipped model's pull affordances average ~0.45 over the
# proposal's candidates, so 0.4 never sharpens; the sharp variant asks for 0.7
SHARP_SUCCESS_TARGET = 0.7
SHARPNESS_GRID = (1.0, 2.0, 4.0, 8.0)
DECISION_BOUNDARY = 0.5  # predicted success above it counts as a predicted success
EPS = 1e-12


@dataclass(frozen=True)
class Pool:
    """One round's candidates over all objects, flat (C candidates, O objects)."""

    obj: np.ndarray  # (C,) int object index, non-decreasing (each object's run contiguous)
    local: np.ndarray  # (C,) int candidate index within its object
    affordance: np.ndarray  # (C,) predicted success probability
    similarity: np.ndarray  # (C,) predicted similarity to the known geometry, [0, 1]
    limits: np.ndarray  # (O,) int most picks per object this round
    features: np.ndarray | None = None  # (C, F) encoder features at the contact point
    familiarity: np.ndarray | None = None  # (C,) geometric closeness to training contacts
    labels: np.ndarray | None = None  # (C,) hindsight outcomes (oracle only)
    explored: np.ndarray | None = None  # (E, F) features of the interactions already taken
    draws: np.ndarray | None = None  # (S, C) sampled success probabilities (a posterior)

    def __len__(self) -> int:
        return len(self.obj)

    @property
    def num_objects(self) -> int:
        return len(self.limits)

    def take(self, idx: np.ndarray) -> Pool:
        """The candidates ``idx`` (limits and explored set unchanged)."""
        def sub(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[idx]
        return replace(self, obj=self.obj[idx], local=self.local[idx],
                       affordance=self.affordance[idx], similarity=self.similarity[idx],
                       features=sub(self.features), familiarity=sub(self.familiarity),
                       labels=sub(self.labels),
                       draws=None if self.draws is None else self.draws[:, idx])

    def segments(self) -> list[np.ndarray]:
        """Per object o, the pool indices of its candidates (empty for an object with none)."""
        bounds = np.searchsorted(self.obj, np.arange(self.num_objects + 1))
        return [np.arange(bounds[o], bounds[o + 1]) for o in range(self.num_objects)]


Rule = Callable[[Pool, int, np.random.Generator], np.ndarray]
KeyFn = Callable[[Pool, np.random.Generator], np.ndarray]


# --- helpers -------------------------------------------------------------------------------

def lowest(keys: list[np.ndarray], k: int, limits: np.ndarray) -> list[tuple[int, int]]:
    """The ``k`` lowest finite keys over all objects, at most ``limits[o]`` from object o,
    lowest first (ties: object order, then candidate order): a round of a key rule."""
    obj, cand, val = [], [], []
    for o, key in enumerate(keys):
        top = np.argsort(key, kind="stable")[:max(int(limits[o]), 0)]
        top = top[np.isfinite(key[top])]
        obj.append(np.full(len(top), o))
        cand.append(top)
        val.append(np.asarray(key[top], np.float64))
    if not obj:
        return []
    order = np.argsort(np.concatenate(val), kind="stable")[:k]
    o_all, c_all = np.concatenate(obj), np.concatenate(cand)
    return [(int(o_all[i]), int(c_all[i])) for i in order]


def key_rule(key: KeyFn) -> Rule:
    """A set rule from a per-candidate key (lower = explore first): the key of each object's
    candidates in object order, then the ``k`` lowest over all objects within the limits."""
    def rule(pool: Pool, k: int, rng: np.random.Generator) -> np.ndarray:
        segs = pool.segments()
        keys = [key(pool.take(s), rng) if len(s) else np.zeros(0) for s in segs]
        return np.array([segs[o][c] for o, c in lowest(keys, k, pool.limits)], np.int64)
    rule.key = key  # type: ignore[attr-defined]  # the per-candidate form (learnability)
    return rule


def half_rule(first: Rule) -> Rule:
    """Half of a round (``k // 2``) by ``first``, the rest at random among what is left,
    the limits holding over both halves: random's class mix plus what the rule finds."""
    def rule(pool: Pool, k: int, rng: np.random.Generator) -> np.ndarray:
        picked = first(pool, k // 2, rng)
        left = pool.limits.astype(np.int64).copy()
        free = np.ones(len(pool), bool)
        for i in picked:
            left[pool.obj[i]] -= 1
            free[i] = False
        segs = pool.segments()
        keys = []  # random keys for what is left; the taken ones can not come again
        for s in segs:
            key = np.full(len(s), np.inf)
            key[free[s]] = rng.random(int(free[s].sum()))
            keys.append(key)
        rest = [segs[o][c] for o, c in lowest(keys, k - len(picked), left)]
        return np.concatenate([picked, np.array(rest, np.int64)])
    return rule


def _normalised_features(pool: Pool) -> np.ndarray:
    """Unit-length features (C, F) float32: k-means and balls then compare directions, as
    TypiClust and ProbCover do with their self-supervised embeddings."""
    if pool.features is None:
        raise ValueError("this rule needs the candidates' encoder features (Scored.features)")
    x = np.asarray(pool.features, np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), EPS)


def sq_distances(x: np.ndarray, c: np.ndarray, x_sq: np.ndarray | None = None) -> np.ndarray:
    """Squared Euclidean distances (N, M) as one matrix product (faster than broadcasting);
    ``x_sq``: the rows' squared norms (N,) when the caller has them."""
    x_sq = (x * x).sum(1) if x_sq is None else x_sq
    d = x_sq[:, None] - 2.0 * x @ c.T + (c * c).sum(1)[None, :]
    return np.maximum(d, 0.0)


def _nearest(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Index of each row's nearest centre (N,): the row norms do not change the argmin."""
    return ((c * c).sum(1)[None, :] - 2.0 * x @ c.T).argmin(1)


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, iters: int = KMEANS_ITERS,
           fit_sample: int = KMEANS_FIT_SAMPLE) -> tuple[np.ndarray, np.ndarray]:
    """Seeded k-means of ``x`` (N, F) into ``k`` clusters: (centres (k', F), label (N,));
    k' = min(k, N). k-means++ start and Lloyd steps on a sample of at most ``fit_sample``
    rows, then every row assigned to its nearest centre."""
    n = len(x)
    k = max(1, min(k, n))
    fit = x if n <= fit_sample else x[rng.choice(n, fit_sample, replace=False)]
    fit_sq = (fit * fit).sum(1)
    centres = np.empty((k, x.shape[1]), x.dtype)
    centres[0] = fit[rng.integers(len(fit))]
    d2 = sq_distances(fit, centres[:1], fit_sq)[:, 0]
    trials = 2 + int(np.log(k))  # greedy k-means++ (as scikit-learn): best of a few draws
    for j in range(1, k):  # the next centre far from the chosen ones
        total = d2.sum()
        if total <= 0:
            centres[j] = fit[rng.integers(len(fit))]
            continue
        cand = rng.choice(len(fit), size=trials, p=d2 / total)
        pot = np.minimum(d2[:, None], sq_distances(fit, fit[cand], fit_sq))  # (n, trials)
        best = int(np.argmin(pot.sum(0)))
        centres[j] = fit[cand[best]]
        d2 = pot[:, best]
    for _ in range(iters):
        lab = _nearest(fit, centres)
        sums = np.zeros_like(centres)
        np.add.at(sums, lab, fit)
        counts = np.bincount(lab, minlength=k)
        full = counts > 0  # an emptied cluster keeps its centre
        centres[full] = sums[full] / counts[full, None]
    return centres, _nearest(x, centres)


def _sample(pool: Pool, size: int, rng: np.random.Generator) -> np.ndarray:
    """Pool indices of a uniform sample of at most ``size`` candidates, sorted."""
    if len(pool) <= size:
        return np.arange(len(pool))
    return np.sort(rng.choice(len(pool), size, replace=False))


class _Quota:
    """Picks so far and each object's room left: the per-object limits of a set rule."""

    def __init__(self, pool: Pool) -> None:
        self.obj = pool.obj
        self.room = np.maximum(pool.limits.astype(np.int64), 0)
        self.taken = np.zeros(len(pool), bool)
        self.picks: list[int] = []

    def eligible(self, idx: np.ndarray) -> np.ndarray:
        """The indices among ``idx`` still free whose object has room."""
        return idx[~self.taken[idx] & (self.room[self.obj[idx]] > 0)]

    def add(self, i: int) -> None:
        self.taken[i] = True
        self.room[self.obj[i]] -= 1
        self.picks.append(int(i))

    def fill(self, order: np.ndarray, k: int) -> None:
        """Add from ``order`` (pool indices, best first) until ``k`` picks or it runs out."""
        for i in order:
            if len(self.picks) >= k:
                return
            if not self.taken[i] and self.room[self.obj[i]] > 0:
                self.add(int(i))

    def result(self) -> np.ndarray:
        return np.array(self.picks, np.int64)


def _weighted_order(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A draw without replacement in proportion to ``w`` (Efraimidis-Spirakis keys), as an
    order: its first j entries are a weighted sample of j."""
    key = np.log(rng.random(len(w)) + EPS) / np.maximum(w, EPS)
    return np.argsort(-key, kind="stable")


def success_weights(affordance: np.ndarray, target: float = SUCCESS_TARGET) -> np.ndarray:
    """Draw weights ``affordance ** gamma``: the smallest gamma of the grid at which a draw's
    expected predicted success reaches ``target`` (the largest if none does), so a
    pessimistic model still spends about that share of the round on likely successes."""
    a = np.clip(np.asarray(affordance, np.float64), EPS, 1.0)
    w = a
    for gamma in SHARPNESS_GRID:
        w = a ** gamma
        if (w * a).sum() / max(w.sum(), EPS) >= target:
            break
    return w


def _draw_per_cluster(quota: _Quota, members: list[np.ndarray], weights: np.ndarray,
                      rng: np.random.Generator) -> None:
    """One candidate from each cluster in turn, drawn in proportion to ``weights`` among its
    members still eligible (clusters in the given order)."""
    for idx in members:
        ok = quota.eligible(idx)
        if len(ok):
            w = weights[ok]
            quota.add(int(ok[rng.choice(len(ok), p=w / w.sum())] if w.sum() > 0
                          else ok[rng.integers(len(ok))]))


def _largest_first(label: np.ndarray, k: int) -> list[np.ndarray]:
    """Members (indices into ``label``) of each cluster, largest cluster first."""
    counts = np.bincount(label, minlength=k)
    return [np.flatnonzero(label == c) for c in np.argsort(-counts, kind="stable")
            if counts[c]]


def typicality(x: np.ndarray, rng: np.random.Generator,
               neighbours: int = TYPICALITY_NEIGHBOURS,
               reference: int = TYPICALITY_REFERENCE) -> np.ndarray:
    """TypiClust's typicality of each row of ``x`` (n, F): 1 / mean distance to its
    ``neighbours`` nearest other rows (searched among at most ``reference`` of them)."""
    n = len(x)
    if n <= 1:
        return np.ones(n)
    ref = np.arange(n) if n <= reference else rng.choice(n, reference, replace=False)
    d = np.sqrt(sq_distances(x, x[ref]))
    self_hit = ref[None, :] == np.arange(n)[:, None]
    d[self_hit] = np.inf  # a row is not its own neighbour
    m = max(1, min(neighbours, len(ref) - 1))  # a row in the reference loses one
    near = np.partition(d, m - 1, axis=1)[:, :m]
    return 1.0 / (near.mean(1) + EPS)


# --- the rules -----------------------------------------------------------------------------

def coverage_success(pool: Pool, k: int, rng: np.random.Generator,
                     target: float = SUCCESS_TARGET) -> np.ndarray:
    """k-means of the encoder features into ``k`` clusters, then one candidate per cluster
    (largest first) drawn in proportion to predicted success, sharpened until a draw's
    expected predicted success reaches ``target`` (:func:`success_weights`): the round
    covers the dense regions of the feature space and seeks successes there."""
    if not len(pool) or k <= 0:
        return np.zeros(0, np.int64)
    x = _normalised_features(pool)
    _, label = kmeans(x, k, rng)
    w = success_weights(pool.affordance, target)
    quota = _Quota(pool)
    _draw_per_cluster(quota, _largest_first(label, int(label.max()) + 1), w, rng)
    if len(quota.picks) < k:  # clusters whose objects are full: success-weighted draws
        quota.fill(_weighted_order(w, rng), k)
    return quota.result()[:k]


def _posterior(pool: Pool) -> np.ndarray:
    if pool.draws is None or not pool.draws.shape[0]:
        raise ValueError("a Thompson-style rule needs sampled success probabilities of the "
                         "candidates (Scored.draws)")
    return pool.draws


def _thompson_pick(quota: _Quota, idx: np.ndarray, draws: np.ndarray,
                   rng: np.random.Generator) -> None:
    """Thompson sampling among ``idx``: one posterior sample, its likeliest success."""
    ok = quota.eligible(idx)
    if len(ok):
        sample = draws[rng.integers(draws.shape[0]), ok]
        quota.add(int(ok[np.argmax(sample)]))


def thompson(pool: Pool, k: int, rng: np.random.Generator, cover: bool = True) -> np.ndarray:
    """Coverage + Thompson-style success seeking (issue 40, 3a): k-means of the encoder
    features into ``k`` clusters and, per cluster (largest first), the likeliest success
    under a fresh sample of the posterior; ``cover`` False draws every pick over the whole
    pool (the per-object limits still spread it). A sample, not the mean, so where the
    model is unsure the picks vary instead of repeating its confident mistakes."""
    if not len(pool) or k <= 0:
        return np.zeros(0, np.int64)
    draws = _posterior(pool)
    quota = _Quota(pool)
    if cover:
        _, label = kmeans(_normalised_features(pool), k, rng)
        for idx in _largest_first(label, int(label.max()) + 1):
            _thompson_pick(quota, idx, draws, rng)
    everything = np.arange(len(pool))
    while len(quota.picks) < k and len(quota.eligible(everything)):
        _thompson_pick(quota, everything, draws, rng)
    return quota.result()[:k]


def typiclust(pool: Pool, k: int, rng: np.random.Generator) -> np.ndarray:
    """TypiClust: k-means of the pool (with the explored interactions' features when known)
    into explored + ``k`` clusters; from each cluster without explored members, largest
    first, the most typical candidate (then the clusters with fewest explored members)."""
    if not len(pool) or k <= 0:
        return np.zeros(0, np.int64)
    s = _sample(pool, POOL_SAMPLE, rng)
    xs = _normalised_features(pool.take(s))
    ex = np.zeros((0, xs.shape[1]), np.float32)
    if pool.explored is not None and len(pool.explored):
        ex = np.asarray(pool.explored, np.float32)
        ex = ex / np.maximum(np.linalg.norm(ex, axis=1, keepdims=True), EPS)
    n_clusters = min(len(ex) + k, MAX_CLUSTERS, len(xs) + len(ex))
    _, label = kmeans(np.concatenate([xs, ex]), n_clusters, rng)
    lab_pool, lab_ex = label[:len(xs)], label[len(xs):]
    size = np.bincount(lab_pool, minlength=n_clusters)
    covered = np.bincount(lab_ex, minlength=n_clusters)
    order = np.lexsort((-size, covered))  # fewest explored members, then largest
    quota = _Quota(pool)
    for c in order:
        if len(quota.picks) >= k or size[c] == 0:
            continue
        members = np.flatnonzero(lab_pool == c)
        typ = typicality(xs[members], rng)
        quota.fill(s[members[np.argsort(-typ, kind="stable")]], len(quota.picks) + 1)
    if len(quota.picks) < k:
        quota.fill(s[rng.permutation(len(s))], k)
    return quota.result()[:k]


def probcover(pool: Pool, k: int, rng: np.random.Generator,
              ball_share: float = PROBCOVER_BALL_SHARE) -> np.ndarray:
    """ProbCover: greedy maximum coverage of δ-balls in feature space (the candidate whose
    ball holds the most candidates not yet covered, the explored interactions' balls covered
    from the start); δ is the pairwise-distance quantile ``ball_share / k``."""
    if not len(pool) or k <= 0:
        return np.zeros(0, np.int64)
    s = _sample(pool, PROBCOVER_SAMPLE, rng)
    xs = _normalised_features(pool.take(s))
    d2 = sq_distances(xs, xs)  # (S, S)
    off = d2[~np.eye(len(xs), dtype=bool)]
    delta2 = np.quantile(off, min(1.0, ball_share / k)) if len(off) else 0.0
    ball = d2 <= delta2  # (S, S) candidate j within candidate i's ball
    covered = np.zeros(len(xs), bool)
    if pool.explored is not None and len(pool.explored):
        ex = np.asarray(pool.explored, np.float32)
        ex = ex / np.maximum(np.linalg.norm(ex, axis=1, keepdims=True), EPS)
        covered = (sq_distances(ex, xs) <= delta2).any(0)
    gain = ball[:, ~covered].sum(1).astype(np.float64)
    tie = rng.random(len(xs)) * 0.5  # ties at random, never outweighing one covered point
    quota = _Quota(pool.take(s))  # over the sample: its indices, its objects' limits
    while len(quota.picks) < k:
        ok = quota.eligible(np.arange(len(xs)))
        if not len(ok):
            break
        i = int(ok[np.argmax(gain[ok] + tie[ok])])
        quota.add(i)
        new = ball[i] & ~covered
        covered |= new
        gain -= ball[:, new].sum(1)
    return s[quota.result()]


def allocate(weight: np.ndarray, k: int, cap: np.ndarray) -> np.ndarray:
    """Integer quotas (O,) summing to min(k, cap.sum()), proportional to ``weight``, never
    above ``cap``: largest remainders, what a capped object cannot take spread over the
    others in proportion again."""
    cap = np.maximum(cap.astype(np.int64), 0)
    quota = np.zeros(len(cap), np.int64)
    left = min(int(k), int(cap.sum()))
    w = np.maximum(np.asarray(weight, np.float64), 0.0)
    while left > 0:
        room = cap - quota
        open_ = room > 0
        ww = np.where(open_, w, 0.0)
        if ww.sum() <= 0:
            ww = open_.astype(np.float64)  # no weight left: evenly over the open objects
        share = left * ww / ww.sum()
        add = np.minimum(np.floor(share).astype(np.int64), room)
        if add.sum() == 0:  # the largest remainder among the open objects takes one
            add[np.argmax(np.where(open_, share, -1.0))] = 1
        quota += add
        left -= int(add.sum())
    return quota


def similarity_coverage(pool: Pool, k: int, rng: np.random.Generator) -> np.ndarray:
    """Where2Explore's similarity within coverage: the round's budget goes to the objects in
    proportion to their unfamiliarity (1 - mean similarity, within the limits); inside an
    object, k-means of its candidates' features into its quota and one success-weighted
    draw per cluster."""
    if not len(pool) or k <= 0:
        return np.zeros(0, np.int64)
    segs = pool.segments()
    sizes = np.array([len(s) for s in segs])
    unfamiliar = np.array([1.0 - float(np.mean(pool.similarity[s])) if len(s) else 0.0
                           for s in segs])
    quota = allocate(unfamiliar, k, np.minimum(pool.limits, sizes))
    x = _normalised_features(pool)
    w = success_weights(pool.affordance)
    picks = _Quota(pool)
    for o in np.argsort(-unfamiliar, kind="stable"):
        if quota[o] <= 0:
            continue
        seg = segs[o]
        _, label = kmeans(x[seg], int(quota[o]), rng)
        _draw_per_cluster(picks, [seg[m] for m in _largest_first(label, int(quota[o]))],
                          w, rng)
    if len(picks.picks) < k:
        picks.fill(_weighted_order(w, rng), k)
    return picks.result()[:k]


def balanced(pool: Pool, k: int, rng: np.random.Generator) -> np.ndarray:
    """Label-balanced picks (BASE's idea with the model's own prediction): half the round
    drawn in proportion to affordance among the predicted successes (the top half of the
    predicted scores when too few pass the boundary), half the candidates nearest the
    decision boundary."""
    if not len(pool) or k <= 0:
        return np.zeros(0, np.int64)
    a = np.asarray(pool.affordance, np.float64)
    half = (k + 1) // 2
    positive = np.flatnonzero(a > DECISION_BOUNDARY)
    if len(positive) < half:
        positive = np.flatnonzero(a >= np.median(a))
    quota = _Quota(pool)
    quota.fill(positive[_weighted_order(a[positive], rng)], half)
    near = np.lexsort((rng.random(len(a)), np.abs(a - DECISION_BOUNDARY)))
    quota.fill(near, k)
    return quota.result()
