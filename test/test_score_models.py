"""bench/score_models.py's paired comparison: the interval is on the difference of two models
scored on the same held-out rows, resampling whole objects (issue 26: recipes are chosen by
differences of a point or two, which two overlapping intervals cannot show)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_SPEC = importlib.util.spec_from_file_location(
    "score_models", Path(__file__).resolve().parents[1] / "bench" / "score_models.py")
score_models = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(score_models)


def _rows(prob: np.ndarray, y: np.ndarray, unit: np.ndarray) -> tuple:
    cats = np.where(np.arange(len(y)) % 2 == 0, "cabinet", "faucet")
    return prob, y, cats, unit, ["cabinet", "faucet"]


def test_the_paired_difference_is_zero_for_a_model_against_itself_and_positive_for_a_better_one():
    rng = np.random.default_rng(0)
    y = rng.random(2000) < 0.2
    unit = np.repeat(np.arange(40), 50)  # 40 held-out objects of 50 rows each
    weak = 0.6 * y + rng.random(2000)
    strong = 2.0 * y + rng.random(2000)
    same = score_models.paired_training_score(_rows(weak, y, unit), _rows(weak, y, unit), 200)
    assert same == (0.0, 0.0, 0.0)
    d, lo, hi = score_models.paired_training_score(_rows(weak, y, unit),
                                                   _rows(strong, y, unit), 200)
    assert 0 < lo < d < hi


def test_models_scored_on_different_rows_are_refused():
    y = np.array([True, False] * 10)
    unit = np.arange(20)
    with pytest.raises(ValueError, match="same held-out rows"):
        score_models.paired_training_score(_rows(np.zeros(20), y, unit),
                                           _rows(np.zeros(20), ~y, unit), 10)


def test_the_novel_difference_pools_only_the_rows_of_categories_the_models_never_trained_on():
    rng = np.random.default_rng(1)
    y = rng.random(3000) < 0.2
    unit = np.repeat(np.arange(60), 50)
    cats = np.array(["cabinet", "faucet", "kettle"])[np.arange(3000) % 3]
    a = rng.random(3000)
    b = np.where(cats == "kettle", 2.0 * y + rng.random(3000), a)  # better on kettle only

    def rows(p: np.ndarray) -> tuple:
        return p, y, cats, unit, ["cabinet", "faucet"]

    assert score_models.paired_training_score(rows(a), rows(b), 100) == (0.0, 0.0, 0.0)
    d, lo, _ = score_models.paired_training_score(rows(a), rows(b), 100, novel=True)
    assert d > 0.3 and lo > 0
