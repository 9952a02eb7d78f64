"""What the README and docs/ show, git tracks: the benchmark numbers of docs/results.md are
rendered from the committed bench/results/benchmark.json, the approach-check table of
docs/ros_api.md from its committed JSON, and every image the README links exists in the
repository (test_docs.py checks every link of docs/ too)."""

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


def _tracked() -> set[str]:
    return set(subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True,
                              text=True).stdout.split())


def test_every_linked_image_and_table_is_tracked_by_git():
    text = (ROOT / "README.md").read_text()
    links = [link.partition("#")[0] for link in  # a section anchor names the same file
             re.findall(r"\]\(((?:bench|checkpoints|config|docs)/[^)\s]+)\)", text)]
    assert links, "the README links no results"
    tracked = _tracked()
    missing = [p for p in links if p not in tracked]
    assert not missing, f"README links files git does not track: {missing}"


def test_the_research_log_and_reproduction_links_resolve_to_tracked_files():
    """bench/RESEARCH.md and bench/REPRODUCE.md link relative to bench/: every such link
    names a file git tracks (a link copied from the README unchanged would not)."""
    tracked = _tracked()
    for doc in ("bench/RESEARCH.md", "bench/REPRODUCE.md"):
        text = (ROOT / doc).read_text()
        links = [t for t in re.findall(r"\]\(([^)\s#]+)\)", text) if "://" not in t]
        resolved = [(ROOT / "bench" / t).resolve().relative_to(ROOT).as_posix() for t in links]
        missing = [p for p in resolved if p not in tracked]
        assert not missing, f"{doc} links files git does not track: {missing}"
    assert re.findall(r"\]\(([^)\s#]+)\)", (ROOT / "bench/RESEARCH.md").read_text())


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


def test_combination_and_per_combination_blocks():
    """`-cfw` renders that combination, the plain block the mean over the combinations
    (saying how its intervals were made), `-combos` one row per combination and method."""
    sys.path.insert(0, str(ROOT / "bench"))
    from render_readme import rewrite

    def row(combo, method, prim, metric, mean, vs=None, **kw):
        return {"combination": combo, "primitive": prim, "method": method, "budget": 5,
                "metric": metric, "n_seeds": 3 if combo != "cfw" else 10, "mean": mean,
                "ci_low": mean - 0.01, "ci_high": mean + 0.01, **({"vs": vs} if vs else {}),
                **kw}

    rows = []
    for combo, gain in (("cfw", 0.02), ("tsw", 0.04), ("mean", 0.03)):
        extra = {"combinations": ["cfw", "tsw"], "ci": "normal"} if combo == "mean" else {}
        for prim in ("push", "pull"):
            for metric in ("fscore", "auroc"):
                rows += [row(combo, "random", prim, metric, 0.5, **extra),
                         row(combo, "similarity", prim, metric, 0.5 + gain, **extra),
                         row(combo, "similarity", prim, metric, gain, vs="random", **extra)]
    doc = {"rows": rows}
    text = ("<!-- benchmark:begin -->\nx\n<!-- benchmark:end -->\n"
            "<!-- benchmark-cfw:begin -->\nx\n<!-- benchmark-cfw:end -->\n"
            "<!-- benchmark-combos:begin -->\nx\n<!-- benchmark-combos:end -->\n")
    mean_block, cfw_block, combos_block = rewrite(text, doc).split(":end -->")[:3]
    assert "Mean over the combinations `cfw`, `tsw`" in mean_block
    assert "independent normal errors" in mean_block and "53.0 [52.0, 54.0]" in mean_block
    assert "Combination `cfw`" in cfw_block and "52.0 [51.0, 53.0]" in cfw_block
    assert "53.0 [52.0, 54.0]" not in cfw_block
    lines = [ln for ln in combos_block.splitlines() if ln.startswith("| `")]
    assert [ln.split(" | ")[0] for ln in lines] == ["| `cfw` (10 / 10)", "| `tsw` (3 / 3)",
                                                    "| `mean` (3 / 3)"]
    assert "+4.0 [3.0, 5.0]" in lines[1]


def test_methods_follow_the_summary_config_order():
    """Runs merged from several outputs arrive in any order; the tables list the methods as
    the summary's ``--methods`` did."""
    sys.path.insert(0, str(ROOT / "bench"))
    from render_readme import render

    rows = [{"combination": "cfw", "primitive": "pull", "method": m, "budget": 5,
             "metric": "auroc", "n_seeds": 3, "mean": 0.6, "ci_low": 0.5, "ci_high": 0.7}
            for m in ("fulldata", "random", "odd", "none")]
    doc = {"rows": rows, "config": {"methods": ["none", "random", "fulldata"]}}
    names = [ln.split(" | ")[0][2:] for ln in render(doc).splitlines()
             if ln.startswith("| ") and not ln.startswith("| method")]
    assert names == ["none", "random", "fulldata", "odd"]


def test_an_empty_block_is_filled_and_leaves_the_next_block_alone():
    """A block written as begin/end with nothing between (a new section) is rendered in
    place; it must not swallow the text up to the next block's end."""
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        from render_readme import rewrite
    finally:
        sys.path.remove(str(ROOT / "bench"))
    rows = [{"combination": "cfw", "primitive": "pull", "method": m, "budget": 5,
             "metric": "auroc", "n_seeds": 3, "mean": v, "ci_low": v - 0.1, "ci_high": v + 0.1}
            for m, v in (("none", 0.6), ("random", 0.7))]
    text = ("<!-- benchmark:begin -->\n<!-- benchmark:end -->\nkept between\n"
            "<!-- benchmark-combos:begin -->\nold\n<!-- benchmark-combos:end -->\n")
    new = rewrite(text, {"config": {"methods": ["none", "random"]}, "rows": rows})
    assert "kept between" in new and "old" not in new
    assert new.count("<!-- benchmark:end -->") == 1 and "| random | 70.0 [60.0, 80.0] |" in new
