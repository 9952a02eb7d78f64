"""bench/bisect_stack.py: the settings it applies are HEAD's config with the reverted values, and
the bisection follows the change that carries the shift (the stack's runs replaced by outcomes
that depend only on the parameter file each run was given)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
import bisect_stack  # noqa: E402

CHANGES = ["inference_node.finetune_steps=500", "inference_node.fit_target=0.0",
           "inference_node.anchor=0.1"]
SEEDS = [0, 1, 2, 3, 4, 5]


def test_a_parameter_file_is_the_config_with_the_changes(tmp_path):
    ch = [bisect_stack.parse_change(c) for c in CHANGES]
    cfg = yaml.safe_load(bisect_stack.params_file(ch, tmp_path, "t").read_text())
    head = yaml.safe_load(bisect_stack.CONFIG.read_text())
    inf = cfg["inference_node"]["ros__parameters"]
    assert (inf["finetune_steps"], inf["fit_target"], inf["anchor"]) == (500, 0.0, 0.1)
    for key in ("finetune_steps", "fit_target", "anchor"):
        del inf[key], head["inference_node"]["ros__parameters"][key]
    assert cfg == head  # nothing else touched


def test_a_typo_in_a_change_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="finetune_stpes"):
        bisect_stack.params_file([bisect_stack.parse_change("inference_node.finetune_stpes=1")],
                                 tmp_path, "t")
    with pytest.raises(argparse.ArgumentTypeError):
        bisect_stack.parse_change("finetune_steps=500")


def _fake_runs(monkeypatch, effect: dict[str, int]):
    """Each reverted change in ``effect`` adds that many successes (of 5) after exploring."""
    def run_demo(d: Path, strategy: str, seed: int, extra: list[str]) -> dict:
        cfg = yaml.safe_load(Path(extra[extra.index("--params-file") + 1]).read_text())
        inf = cfg["inference_node"]["ros__parameters"]
        n = 1 + sum(k for name, k in effect.items() if inf[name] != {
            "finetune_steps": 2000, "fit_target": 0.97, "anchor": 0.0}[name])
        n = min(5, n + (seed % 2 if strategy == "similarity" else 0))
        outcome = [{"success": i < n} for i in range(5)]
        return {"before": [{"success": i < 1} for i in range(5)], "after": outcome,
                "explore": {"interactions": 25}}
    monkeypatch.setattr(bisect_stack, "run_demo", run_demo)


def _args(tmp_path) -> argparse.Namespace:
    return argparse.Namespace(change=[bisect_stack.parse_change(c) for c in CHANGES],
                              seeds=SEEDS, strategies=["similarity", "random"],
                              runs=str(tmp_path), demo_flags=bisect_stack.VALIDATION)


@pytest.mark.parametrize("culprit", ["finetune_steps", "fit_target", "anchor"])
def test_the_bisection_finds_the_change_that_carries_the_shift(tmp_path, monkeypatch, culprit):
    _fake_runs(monkeypatch, {culprit: 3})
    res = bisect_stack.bisect(_args(tmp_path))
    assert res["culprit"].startswith(f"inference_node.{culprit}=")
    assert res["total_shift"]["mean"] == pytest.approx(0.6)
    assert 2 <= len(res["steps"]) <= 3  # the two ends, then one probe per halving
    bisect_stack.write_table(res, tmp_path)
    assert "the shift follows" in (tmp_path / "bisect.md").read_text()


def test_no_shift_on_validation_means_nothing_to_bisect(tmp_path, monkeypatch):
    _fake_runs(monkeypatch, {})
    res = bisect_stack.bisect(_args(tmp_path))
    assert "culprit" not in res and res["verdict"].startswith("no shift on validation")
    assert set(res["arms"]) == {"new", "set-finetune_steps+fit_target+anchor"}
