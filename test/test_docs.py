"""The README is a manual and every page it leads to is in the repository.

The README stays short (at most 300 lines) and links the reference pages under docs/; every
relative link of the README and of docs/*.md names a file git tracks (an image too), an anchor
names a heading of its page, and no text sends the reader outside the repository (the design
notes and the paper that sat beside the checkout once were linked as ``../shared/...`` and
cited as "DESIGN §3")."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
OUTSIDE = ("DESIGN §", "DESIGN.md", "../shared", "/work/")


def _tracked() -> set[str]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.split("\n")
    return {p for p in out if p}


def _slugs(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings (outside code blocks)."""
    slugs: set[str] = set()
    seen: dict[str, int] = {}
    fenced = False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        m = None if fenced else re.match(r"#+\s+(.*)", line)
        if m:
            slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            slugs.add(slug if n == 0 else f"{slug}-{n}")
    return slugs


def _links(page: Path) -> list[str]:
    """The page's markdown links and images outside code blocks."""
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return LINK.findall(text)


def test_readme_is_a_manual_of_at_most_300_lines():
    n = len(README.read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines; move reference material to docs/"


def test_readme_links_every_page_under_docs():
    links = set(_links(README))
    missing = [p.relative_to(ROOT).as_posix() for p in PAGES[1:]
               if p.relative_to(ROOT).as_posix() not in links]
    assert not missing, f"README.md links no {missing}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_names_a_tracked_file_inside_the_repository(page):
    tracked = _tracked()
    tracked_dirs = {Path(p).parent.as_posix() for p in tracked}
    bad = []
    for target in _links(page):
        if re.match(r"[a-z]+:", target):  # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        try:
            rel = dest.relative_to(ROOT).as_posix()
        except ValueError:
            bad.append(f"{target}: outside the repository")
            continue
        if rel not in tracked and rel.rstrip("/") not in tracked_dirs:
            bad.append(f"{target}: {rel} is not tracked by git")
        elif anchor and rel.endswith(".md") and anchor not in _slugs(ROOT / rel):
            bad.append(f"{target}: no heading #{anchor} in {rel}")
    assert not bad, f"{page.relative_to(ROOT)}:\n" + "\n".join(bad)


@pytest.mark.parametrize("page", [*PAGES, ROOT / "bench" / "RESEARCH.md",
                                  ROOT / "bench" / "REPRODUCE.md"],
                         ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_text_points_outside_the_repository(page):
    text = page.read_text()
    found = [s for s in OUTSIDE if s in text] + re.findall(r"§\s*\d+", text)
    assert not found, f"{page.relative_to(ROOT)} mentions {found}: name a file of the repository"


def test_readme_lists_every_w2e_verb():
    """The verbs table follows the CLI: a verb added to ``w2e`` is documented."""
    import argparse

    from w2e_ros.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    section = README.read_text().split("## The `w2e` command", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"`w2e ([a-z-]+)`", section))
    assert listed == set(sub.choices), (
        f"README's verbs {sorted(listed)}; `w2e --help` has {sorted(sub.choices)}")


def test_no_code_comment_cites_the_design_notes_outside_the_repository():
    """Docstrings and comments say the fact or name the module, not a section of notes a
    user of the repository does not have."""
    tracked = subprocess.run(["git", "ls-files", "*.py", "*.yaml", "Makefile"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout.split()
    cited = [p for p in tracked if p != "test/test_docs.py"
             and any(s in (ROOT / p).read_text() for s in ("DESIGN §", "DESIGN.md", "../shared"))]
    assert not cited, cited
