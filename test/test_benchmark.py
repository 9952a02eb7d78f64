"""`w2e benchmark` end to end on the shipped checkpoint: real sim trials, tiny sizes."""

from __future__ import annotations

import json
from pathlib import Path

from w2e_ros import cli

ROOT = Path(__file__).resolve().parents[1]


def test_benchmark_cli_explores_evaluates_and_writes_tables(tmp_path):
    runs = tmp_path / "runs" / "w2e_cfw_push"
    runs.mkdir(parents=True)
    (runs / "model.pt").symlink_to(ROOT / "checkpoints" / "w2e_cfw_push.pt")
    out = tmp_path / "out"
    rc = cli.main(["benchmark", "--runs", str(tmp_path / "runs"), "--combos", "cfw",
                   "--primitives", "push", "--methods", "none", "similarity", "fulldata",
                   "--categories", "door", "--budgets", "1", "--explore-objects", "1",
                   "--test-objects", "1", "--points", "16", "--dirs", "2",
                   "--finetune-steps", "1", "--bar", "1.01", "--movable-only", "--validate",
                   "--no-heatmaps", "--threads", "1", "--out", str(out)])
    assert rc == 0
    rows = [json.loads(line) for line in (out / "rows.jsonl").read_text().splitlines()]
    # fulldata has no checkpoint here: skipped with a warning, not a crash
    assert {r["method"] for r in rows} == {"none", "similarity"}
    assert all(r["metric"] == "success" and 0.0 <= r["value"] <= 1.0 for r in rows)
    steps = json.loads((out / "explored_push_cfw_similarity_s0.json").read_text())["door"]
    assert len(steps) == 1 and steps[0]["target"].startswith("door/30")  # the one explored
    tables = (out / "tables.md").read_text()
    assert "VALIDATION" in tables and "| similarity |" in tables
