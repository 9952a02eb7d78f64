"""The numbers of README.md and docs/*.md come from the committed result files.

``bench/render_docs.py`` renders every table and key figure between ``<!-- w2e:begin NAME -->``
markers (and the benchmark blocks) from ``bench/results/``; these tests fail when a page and
its files disagree, when a block renders from a file git does not track, when a page links a
file that is not in the repository, and when the sign convention (rule − baseline) or the
one-page status slip.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
import render_docs  # noqa: E402

PAGES = render_docs.pages()
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _tracked() -> set[str]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout
    return set(out.split("\n")) - {""}


def test_the_committed_pages_match_their_result_files():
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "render_docs.py"), "--check"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr


def test_a_number_typed_over_in_a_block_is_caught(tmp_path):
    """The check is not vacuous: a page whose rendered figure was edited by hand fails."""
    page = ROOT / "docs" / "status.md"
    text = page.read_text()
    block = re.search(r"<!-- w2e:begin key-figures -->\n(.*?)<!-- w2e:end key-figures -->",
                      text, re.S)
    assert block and "10/100" in block.group(1)
    copy = tmp_path / "docs" / "status.md"
    copy.parent.mkdir()
    copy.write_text(text.replace("10/100", "11/100", 1))
    assert render_docs.main(["--check", str(copy)]) == 1
    assert render_docs.main(["--check", str(page)]) == 0


def test_a_changed_result_file_is_caught(monkeypatch):
    """A page goes stale when the JSON under it changes (here the demo's after count)."""
    real = render_docs.load

    def changed(rel: str) -> dict:
        doc = real(rel)
        if rel == "demo_seeds/demo_seeds.json":
            doc = json.loads(json.dumps(doc))
            doc["strategies"]["random"]["after"] += 1
        return doc

    text = (ROOT / "README.md").read_text()
    assert render_docs.rewrite(text, page=ROOT / "README.md") == text
    monkeypatch.setattr(render_docs, "load", changed)
    new = render_docs.rewrite(text, page=ROOT / "README.md")
    assert new != text
    assert "headline" in render_docs.stale_blocks(text, new)


def test_every_block_is_known_paired_and_renders_from_tracked_files(monkeypatch):
    tracked = _tracked()
    used: list[str] = []
    real = render_docs.load

    def recording(rel: str) -> dict:
        used.append(f"bench/results/{rel}")
        return real(rel)

    monkeypatch.setattr(render_docs, "load", recording)
    names = []
    for page in PAGES:
        text = page.read_text()
        assert not render_docs.problems(text), (page, render_docs.problems(text))
        for m in render_docs.BLOCK.finditer(text):
            names.append(m.group(2))
            render_docs.render_block(m.group(2))  # KeyError for an unknown block
    assert {"key-figures", "headline", "demo-seeds"} <= set(names)
    untracked = sorted(set(used) - tracked)
    assert not untracked, f"blocks render from files git does not track: {untracked}"


def test_an_unknown_block_is_refused(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("<!-- w2e:begin no-such-block -->\n<!-- w2e:end no-such-block -->\n")
    assert render_docs.main(["--check", str(page)]) == 1
    page.write_text("<!-- w2e:begin key-figures -->\nno end\n")
    assert render_docs.main(["--check", str(page)]) == 1


def test_differences_are_written_rule_minus_baseline():
    """One sign convention: `similarity − random`, `random − none`; never the baseline first."""
    flipped = re.compile(r"\b(none|random)(?:'s after)? [−-] (random|similarity|nosim|geometry|"
                         r"where2act)(?:'s)?\b", re.I)
    found = []
    for page in PAGES:
        for n, line in enumerate(page.read_text().splitlines(), 1):
            found += [f"{page.relative_to(ROOT)}:{n}: {m.group(0)}" for m in flipped.finditer(line)
                      if m.group(1).lower() != m.group(2).lower()
                      and not (m.group(1).lower() == "random" and m.group(2).lower() == "none")]
    assert not found, "baseline − rule written:\n" + "\n".join(found)


def test_the_status_page_is_one_page():
    lines = (ROOT / "docs" / "status.md").read_text().splitlines()
    assert len(lines) <= 80, f"docs/status.md has {len(lines)} lines (at most 80)"
    long = [n for n, line in enumerate(lines, 1) if len(line) > 200]
    assert not long, f"docs/status.md lines over 200 characters: {long}"


@pytest.mark.parametrize("page", [*PAGES, ROOT / "bench" / "RESEARCH.md",
                                  ROOT / "bench" / "REPRODUCE.md"],
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_link_and_named_result_file_is_tracked(page):
    """Links (images too) resolve to tracked files; a ``bench/results/...`` path a user page
    names in code (``bench/results/load/summary.json``) exists as well."""
    tracked = _tracked()
    dirs = {Path(*Path(p).parts[:i]).as_posix() for p in tracked
            for i in range(1, len(Path(p).parts))}
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    bad = []
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        rel = (page.parent / target.partition("#")[0]).resolve()
        try:
            rel = rel.relative_to(ROOT).as_posix()
        except ValueError:
            bad.append(f"{target}: outside the repository")
            continue
        if rel not in tracked and rel.rstrip("/") not in dirs:
            bad.append(f"{target}: {rel} is not tracked")
    if page in PAGES:
        for named in re.findall(r"`(bench/results/[^`\s*{}$]+)`", text):
            if named.rstrip("/") not in tracked and named.rstrip("/") not in dirs:
                bad.append(f"`{named}` is not tracked")
    assert not bad, f"{page.relative_to(ROOT)}:\n" + "\n".join(bad)


def test_bench_results_holds_summaries_not_every_run():
    """Raw per-trial outputs and superseded runs stay out of the tree (git history and the
    commands of bench/REPRODUCE.md keep them)."""
    files = [p for p in _tracked() if p.startswith("bench/results/")]
    assert len(files) <= 150, f"bench/results tracks {len(files)} files (at most 150)"
    raw = [p for p in files if p.endswith(".jsonl")]
    assert not raw, f"raw per-trial outputs tracked: {raw}"


def test_the_robot_install_carries_the_defaults_and_the_research_is_an_extra(monkeypatch):
    """``pip install .`` installs the default checkpoints and their replay pack, not the
    research checkpoints (``checkpoints/fulldata_*``), which no node or config names; the
    offline experiments' dependencies come with ``.[experiments]``, as the README says."""
    import runpy

    import setuptools

    captured: dict = {}
    monkeypatch.setattr(setuptools, "setup", lambda **kw: captured.update(kw))
    monkeypatch.chdir(ROOT)
    runpy.run_path(str(ROOT / "setup.py"))
    files = [f for _, group in captured["data_files"] for f in group]
    assert {"checkpoints/w2e_cfw_pull.pt", "checkpoints/w2e_cfw_push.pt"} <= set(files)
    assert any(f.startswith("checkpoints/replay_cfw/") for f in files)
    assert not [f for f in files if "fulldata" in f]
    extras = captured["extras_require"]
    assert any(r.startswith("ray") for r in extras["experiments"])
    assert set(extras["sim"]) <= set(extras["experiments"])
    robot = [ROOT / "config", ROOT / "launch", ROOT / "w2e_ros" / "nodes"]
    named = [p for d in robot for p in d.rglob("*") if p.is_file()
             and p.suffix in (".py", ".yaml", ".xml") and "fulldata_" in p.read_text()]
    assert not named, f"the robot stack names a research checkpoint: {named}"
    assert "pip install .[experiments]" in (ROOT / "README.md").read_text()
