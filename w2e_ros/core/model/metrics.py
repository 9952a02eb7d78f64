"""Evaluation metrics: affordance F-score and sample success rate.

The F-score is computed once from the pooled counts of true / false positives and false
negatives over all held-out interactions (the reference code averaged per-batch values,
which weights small batches wrongly and is not an F-score of anything).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np


def fscore(pred: np.ndarray, label: np.ndarray) -> dict[str, float]:
    """Precision, recall and their harmonic mean for boolean predictions vs labels.

    Empty denominators count as 0 (no positive predictions -> precision 0), so a model that
    never predicts success scores F = 0 rather than NaN.
    """
    pred, label = np.asarray(pred, bool), np.asarray(label, bool)
    if pred.shape != label.shape:
        raise ValueError(f"predictions {pred.shape} and labels {label.shape} differ")
    tp = int(np.sum(pred & label))
    fp = int(np.sum(pred & ~label))
    fn = int(np.sum(~pred & label))
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    acc = float(np.mean(pred == label)) if len(pred) else float("nan")
    return {"fscore": f, "precision": precision, "recall": recall, "accuracy": acc,
            "tp": tp, "fp": fp, "fn": fn, "n": len(pred)}


def affordance_fscore_from_probs(probs: np.ndarray, success: np.ndarray,
                                 threshold: float = 0.5) -> dict[str, float]:
    """F-score of ``probs > threshold`` (sigmoid of the affordance logit) vs success labels."""
    return fscore(np.asarray(probs) > threshold, success)


def success_rate(outcomes: Iterable[bool]) -> float:
    """Fraction of executed actions that succeeded (NaN when none was executed)."""
    o = np.asarray(list(outcomes), dtype=bool)
    return float(o.mean()) if len(o) else float("nan")


def mean_std(values: Iterable[float]) -> tuple[float, float]:
    """Mean and population std over runs (combinations x seeds), NaNs ignored."""
    v = np.asarray([x for x in values if x == x], dtype=float)
    if not len(v):
        return float("nan"), float("nan")
    return float(v.mean()), float(v.std())


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (ties count one half); NaN when one class is missing.

    Threshold-free, so it says whether the model ranks successes above failures even where
    a poorly calibrated 0.5 threshold makes the F-score 0.
    """
    s, y = np.asarray(scores, dtype=np.float64), np.asarray(labels, dtype=bool)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    order = np.argsort(s, kind="mergesort")
    ranks = np.empty(len(s), dtype=np.float64)
    sorted_s = s[order]
    # average ranks over ties (1-based)
    _, first, counts = np.unique(sorted_s, return_index=True, return_counts=True)
    avg = first + (counts + 1) / 2.0
    ranks[order] = np.repeat(avg, counts)
    return float((ranks[y].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def within_class_auroc(scores: np.ndarray, correct: np.ndarray,
                       predicted: np.ndarray) -> float:
    """AUROC of ``scores`` for ``correct``, counting only pairs of the same ``predicted`` class.

    The similarity's plain AUROC for "the prediction is right" mostly separates the predicted
    successes (on pull mostly wrong) from the predicted failures (mostly right): the affordance
    alone knows that. Compared within one predicted class, a score above 0.5 says something
    the prediction does not, e.g. which of the model's "no"s are successes: what exploring
    has to find. Pairs are pooled over the classes (weighted by their number of pairs).
    """
    s, ok = np.asarray(scores, np.float64), np.asarray(correct, bool)
    pred = np.asarray(predicted, bool)
    num = den = 0.0
    for m in (pred, ~pred):
        a = auroc(s[m], ok[m])
        if np.isfinite(a):
            pairs = float(ok[m].sum()) * float((~ok[m]).sum())
            num, den = num + a * pairs, den + pairs
    return num / den if den else float("nan")


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """Average precision (area under the precision-recall step curve); NaN without positives.

    Its chance level is the positive rate, which the reader must keep in mind (pull: ~5 %).
    """
    s, y = np.asarray(scores, dtype=np.float64), np.asarray(labels, dtype=bool)
    n_pos = int(y.sum())
    if n_pos == 0:
        return float("nan")
    order = np.argsort(-s, kind="mergesort")
    y = y[order]
    tp = np.cumsum(y)
    precision = tp / np.arange(1, len(y) + 1)
    return float(precision[y].sum() / n_pos)


def r_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """Precision among the R highest scores, R = the number of positives (there precision =
    recall = F-score); NaN without positives.

    The F-score at a fixed 0.5 threshold also moves when a fit only shifts how many
    predictions cross 0.5: with few positives, predicting more of them raises it even at
    chance precision. R-precision depends on the ranking alone. Ties at the cut share it.
    """
    s, y = np.asarray(scores, dtype=np.float64), np.asarray(labels, dtype=bool)
    r = int(y.sum())
    if r == 0:
        return float("nan")
    cut = np.sort(s)[::-1][r - 1]
    above, at = s > cut, s == cut
    tp = y[above].sum() + y[at].mean() * (r - above.sum())  # ties at the cut: their mean
    return float(tp / r)


def classification_metrics(probs: np.ndarray, success: np.ndarray,
                           threshold: float = 0.5) -> dict[str, float]:
    """F-score (with its counts) at ``threshold``, AUROC and average precision."""
    out = affordance_fscore_from_probs(probs, success, threshold)
    out["auroc"] = auroc(probs, success)
    out["ap"] = average_precision(probs, success)
    out["pos_rate"] = float(np.mean(success)) if len(success) else float("nan")
    return out


def bootstrap_ci(stat: Callable[[np.ndarray], float], groups: np.ndarray,
                 n_boot: int = 1000, seed: int = 0, level: float = 0.95
                 ) -> tuple[float, float, float]:
    """Statistic and its percentile bootstrap interval, resampling whole groups.

    ``groups`` (K,) labels each row with its resampling unit (a test observation, a seed):
    rows of one cloud are not independent, so the cloud, not the row, is resampled.
    ``stat`` receives the (K',) row indices of a resample.
    """
    groups = np.asarray(groups)
    uniq, inv = np.unique(groups, return_inverse=True)
    members = [np.flatnonzero(inv == g) for g in range(len(uniq))]
    rng = np.random.default_rng(seed)
    point = float(stat(np.arange(len(groups))))
    vals = np.empty(n_boot)
    for b in range(n_boot):
        pick = rng.integers(len(members), size=len(members))
        vals[b] = stat(np.concatenate([members[i] for i in pick]))
    lo, hi = np.nanpercentile(vals, [50 * (1 - level), 50 * (1 + level)])
    return point, float(lo), float(hi)
