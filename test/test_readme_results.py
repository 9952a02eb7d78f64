"""What the README shows, git tracks: its benchmark numbers are rendered from the committed
bench/results/benchmark.json, and every image it links exists in the repository."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_benchmark_block_matches_the_committed_json():
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "render_readme.py"), "--check"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_every_linked_image_and_table_is_tracked_by_git():
    text = (ROOT / "README.md").read_text()
    links = re.findall(r"\]\(((?:bench|checkpoints|config|docs)/[^)\s]+)\)", text)
    assert links, "the README links no results"
    tracked = set(subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True,
                                 text=True).stdout.split())
    missing = [p for p in links if p not in tracked]
    assert not missing, f"README links files git does not track: {missing}"


def test_readme_approach_check_block_matches_the_committed_json():
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "approach_check.py"), "--readme",
                        "--check"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_a_budget_block_renders_that_budget():
    """`<!-- benchmark-b1:begin -->` blocks show budget 1, the plain block the largest."""
    import json

    sys.path.insert(0, str(ROOT / "bench"))
    from render_readme import rewrite

    doc = json.loads((ROOT / "bench" / "results" / "benchmark.json").read_text())
    text = ("a\n<!-- benchmark:begin -->\nold\n<!-- benchmark:end -->\nb\n"
            "<!-- benchmark-b1:begin -->\nold\n<!-- benchmark-b1:end -->\nc\n")
    out = rewrite(text, doc)
    largest = max(r["budget"] for r in doc["rows"])
    first, second = out.split("<!-- benchmark-b1:begin -->")
    assert f"budget {largest} interactions" in first and "old" not in out
    assert "budget 1 interactions" in second and second.endswith("<!-- benchmark-b1:end -->\nc\n")
