"""Evaluation metrics (DESIGN §3): affordance F-score and sample success rate.

The F-score is computed once from the pooled counts of true / false positives and false
negatives over all held-out interactions (the reference code averaged per-batch values,
which weights small batches wrongly and is not an F-score of anything).
"""

from __future__ import annotations

from collections.abc import Iterable

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
