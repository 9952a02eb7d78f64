"""``w2e demo`` as the README's first command runs it: the stack learns a category it never saw.

The default (bucket pull, seed 0, the shipped checkpoints, the stack's parameters; the best
rule, random, then the paper's similarity, both spending the whole budget) is deterministic.
The test asserts what the demo exists to show (more test buckets move after exploring with the
best rule than before), that both rules spent the same and started from the same model and
start states, and that exploring reached every explore bucket: a broken scene layout once
stacked them in one place, one was never segmented, and the demo showed 0 -> 0.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from w2e_ros.core.exploration.strategies import BEST_RULE
from w2e_ros.demo import report, wilson


@pytest.mark.slow
@pytest.mark.timeout(1200)  # past the demo's own 900 s limit, which names what it was doing
def test_w2e_demo_as_typed_learns_the_novel_category(tmp_path: Path):
    w2e = Path(sys.executable).with_name("w2e")
    out = tmp_path / "demo"
    r = subprocess.run([str(w2e), "demo", "--out", str(out), "--quiet-nodes"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert (s["category"], s["primitive"], s["rules"]) == ("bucket", "pull",
                                                          [BEST_RULE, "similarity"])
    assert len(s["test_instances"]) == 10
    spend = s["budget"] * len(s["explore_instances"])
    for rule, run in s["runs"].items():
        assert [o["instance"] for o in s["before"]] == s["test_instances"] == \
            [o["instance"] for o in run["after"]]
        message = run["explore"]["message"]
        assert "not seen" not in message, (rule, message)
        assert f"on {len(s['explore_instances'])} object(s)" in message, (rule, message)
        assert run["explore"]["interactions"] == spend, (rule, message)  # equal spend
    before = sum(o["success"] for o in s["before"])
    after = sum(o["success"] for o in s["runs"][BEST_RULE]["after"])
    assert after > before, (before, after, s["runs"][BEST_RULE]["explore"]["message"])
    assert "success on 10 unseen bucket instances" in r.stdout
    assert f"similarity - {BEST_RULE}, after:" in r.stdout
    for png in [*s["heatmaps"], s["plot"]]:
        assert Path(png).stat().st_size > 10_000


def test_w2e_demo_refuses_a_missing_parameter_file_before_starting_anything(tmp_path: Path):
    w2e = Path(sys.executable).with_name("w2e")
    out = tmp_path / "demo"
    r = subprocess.run([str(w2e), "demo", "--params-file", str(tmp_path / "none.yaml"),
                        "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip() == f"w2e demo: no parameter file {tmp_path / 'none.yaml'}"
    assert not (out / "summary.json").exists()


def test_w2e_demo_validate_refuses_when_no_explore_instance_is_left_to_judge(tmp_path: Path):
    """--validate judges on the explore-split instances that are not explored; exploring all
    ten leaves none, and the demo says so instead of judging on the explored ones."""
    w2e = Path(sys.executable).with_name("w2e")
    r = subprocess.run([str(w2e), "demo", "--validate", "--explore-instances", "10",
                        "--out", str(tmp_path / "demo")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2
    assert "validation needs explore instances of bucket beyond the 10 explored" in r.stderr


def test_the_demo_report_gives_intervals_pairs_and_the_sign_rule_minus_baseline():
    """Each rule's after with its Wilson interval and per-instance pairing, rule - baseline,
    and the recorded seeds' range: one run is read as one draw."""
    lo, hi = wilson(1, 10)
    assert 0.0 < lo < 0.1 < hi < 0.5  # 1/10: [2 %, 40 %]
    assert wilson(0, 10)[0] == 0.0 and wilson(10, 10)[1] == 1.0
    outcome = [{"success": x} for x in (1, 0, 0, 0)]
    summary = {"category": "bucket", "primitive": "pull", "rules": ["random", "similarity"],
               "before": outcome,
               "runs": {"random": {"after": [{"success": x} for x in (1, 1, 1, 0)],
                                   "explore": {"interactions": 8}},
                        "similarity": {"after": [{"success": x} for x in (0, 1, 0, 0)],
                                       "explore": {"interactions": 8}}}}
    recorded = {"strategies": {"random": {"before": 1, "after": 5, "trials": 8, "per_seed": [
        {"after": 2}, {"after": 3}]}}}
    text = report(summary, recorded)
    assert "before exploring: 1/4" in text
    assert "with random: 3/4" in text and "gained 2, lost 0" in text
    assert "with similarity: 1/4" in text and "gained 1, lost 1" in text
    assert "similarity - random, after: -2 of 4" in text
    assert "random: 1/8 -> 5/8, one seed's after from 2 to 3 of 4" in text
