"""Write the benchmark tables of docs/results.md from ``bench/results/benchmark.json``.

Published numbers must come from the committed results, not be typed by hand: this
renders the headline table (mean over seeds with 95 % bootstrap intervals, and the paired
differences against ``random`` and ``none``) between the ``<!-- benchmark:begin -->`` and
``<!-- benchmark:end -->`` markers (the largest budget; the mean over the combinations when
the file has several), the same table at budget N between ``<!-- benchmark-bN:begin -->``
and ``<!-- benchmark-bN:end -->``, for one combination with a ``-<combo>`` suffix
(``<!-- benchmark-cfw:begin -->``, ``<!-- benchmark-b1-cfw:begin -->``), and the paired
differences against ``random`` per combination between ``<!-- benchmark-combos:begin -->``
and ``<!-- benchmark-combos:end -->``.
``test/test_readme_results.py`` fails when docs/results.md and the JSON disagree.

    .venv/bin/python bench/render_readme.py            # rewrite the block
    .venv/bin/python bench/render_readme.py --check    # exit 1 when it is stale
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- benchmark:begin -->", "<!-- benchmark:end -->"
NAMES = {"fscore": "F-score", "auroc": "AUROC", "ap": "AP", "success": "sample success",
         "simcorr_auroc": "similarity AUROC for correctness"}


def _cell(r: dict | None, signed: bool = False) -> str:
    if r is None or r["mean"] != r["mean"]:
        return "-"
    v = f"{100 * r['mean']:+.1f}" if signed else f"{100 * r['mean']:.1f}"
    return f"{v} [{100 * r['ci_low']:.1f}, {100 * r['ci_high']:.1f}]"


def _methods(doc: dict, sel: list[dict]) -> list[str]:
    """The methods of ``sel`` in the order the summary's config lists them (runs merged from
    several outputs arrive in any order), unlisted ones after."""
    order = {m: i for i, m in enumerate(doc.get("config", {}).get("methods", []))}
    found = list(dict.fromkeys(r["method"] for r in sel))
    return sorted(found, key=lambda m: (order.get(m, len(order)), found.index(m)))


def render(doc: dict, combination: str | None = None, budget: int | None = None) -> str:
    """The headline table: every method at the largest budget, one column per (metric,
    primitive), then the paired differences at that budget."""
    rows = doc["rows"]
    combos = sorted({r["combination"] for r in rows})
    combo = combination or ("mean" if "mean" in combos else combos[0])
    budget = budget if budget is not None else max(r["budget"] for r in rows)
    sel = [r for r in rows if r["combination"] == combo and r["budget"] == budget]
    prims = [p for p in ("push", "pull") if any(r["primitive"] == p for r in sel)]
    metrics = [m for m in ("fscore", "auroc", "ap", "success")
               if any(r["metric"] == m for r in sel)]
    cols = [(m, p) for m in metrics for p in prims]
    methods = _methods(doc, sel)
    n_seeds = {p: max((r["n_seeds"] for r in sel if r["primitive"] == p), default=0)
               for p in prims}
    seeds = (f"{next(iter(n_seeds.values()))} seeds" if len(set(n_seeds.values())) <= 1 else
             "seeds: " + ", ".join(f"{p} {n}" for p, n in n_seeds.items()))

    def get(method: str, m: str, p: str, vs: str | None = None) -> dict | None:
        return next((r for r in sel if r["method"] == method and r["metric"] == m
                     and r["primitive"] == p and r.get("vs") == vs), None)

    head = "| method | " + " | ".join(f"{NAMES[m]} {p}" for m, p in cols) + " |"
    if combo == "mean":
        members = next((r.get("combinations") for r in sel if r.get("combinations")), [])
        normal = any(r.get("ci") == "normal" for r in sel)
        what = (f"Mean over the combinations {', '.join(f'`{c}`' for c in members)}, budget "
                f"{budget} interactions per explore object, {seeds} (the fewest of any "
                "combination); % with 95 % intervals from the combinations' "
                + ("intervals combined as independent normal errors" if normal else
                   "bootstrap draws averaged") + ".")
    else:
        what = (f"Combination `{combo}`, budget {budget} interactions per explore object, "
                f"{seeds} (exploration seeds, times training seeds where there are "
                "several); % with 95 % bootstrap intervals "
                "(test observations / objects and seeds resampled).")
    lines = [what, "", head, "|---" * (len(cols) + 1) + "|"]
    for method in methods:
        lines.append(f"| {method} | " + " | ".join(_cell(get(method, m, p)) for m, p in cols)
                     + " |")
    for ref in ("random", "none"):
        for method in methods:
            if method == ref or get(method, cols[0][0], cols[0][1], ref) is None:
                continue
            if get(ref, cols[0][0], cols[0][1], method) is not None and method == "none":
                continue  # one sign convention, rule − baseline: random − none, not none − random
            lines.append(f"| {method} − {ref} (paired) | " + " | ".join(
                _cell(get(method, m, p, ref), signed=True) for m, p in cols) + " |")
    sc = [r for r in rows if r["combination"] == combo and r["metric"] == "simcorr_auroc"
          and r["budget"] == 0 and r["method"] == "none" and "vs" not in r]
    if sc:
        lines += ["", "Similarity AUROC for \"the affordance prediction is correct\" on the "
                  "novel test interactions, before exploring: " + ", ".join(
                      f"{r['primitive']} {_cell(r)}" for r in sc) + "."]
    return "\n".join(lines)


def render_combos(doc: dict, budget: int | None = None) -> str:
    """Per combination (and their mean): each method's paired difference against random at
    one budget, F-score and AUROC for push and pull, with the seeds behind each."""
    rows = doc["rows"]
    budget = budget if budget is not None else max(r["budget"] for r in rows)
    combos = sorted({r["combination"] for r in rows}, key=lambda c: (c == "mean", c))
    cols = [(m, p) for m in ("fscore", "auroc") for p in ("push", "pull")]
    lines = [f"Paired differences at budget {budget}, rule − baseline: each rule against "
             "`random`, and `random` against `none` (what exploring at random buys); % with 95 % "
             "intervals (seeds per primitive in brackets after the combination).", "",
             "| combination | difference | " + " | ".join(
                 f"{NAMES[m]} {p}" for m, p in cols) + " |", "|---" * (len(cols) + 2) + "|"]
    for combo in combos:
        at = [r for r in rows if r["combination"] == combo and r["budget"] == budget]
        sel = [r for r in at if r.get("vs") == "random"]
        n = {p: max((r["n_seeds"] for r in sel if r["primitive"] == p), default=0)
             for p in ("push", "pull")}
        label = f"`{combo}` ({n['push']} / {n['pull']})"
        gain = [r for r in at if r["method"] == "random" and r.get("vs") == "none"]
        for method in _methods(doc, sel):
            src, name = sel, f"{method} − random"
            if method == "none" and gain:  # rule − baseline: random − none
                src, name = gain, "random − none"
            cells = [_cell(next((r for r in src if (r["method"] == method or src is gain)
                                 and r["metric"] == m and r["primitive"] == p), None), True)
                     for m, p in cols]
            lines.append(f"| {label} | {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


BLOCK = re.compile(r"(<!-- benchmark(?:-b(\d+))?(?:-([a-z]+))?:begin -->)"
                   r"\n(?:.*?\n)??(<!-- benchmark[-\w]*:end -->)", re.S)  # an empty block too


def rewrite(text: str, doc: dict) -> str:
    """Every block: ``benchmark`` at the largest budget, ``benchmark-b<N>`` at budget N,
    a ``-<combo>`` suffix for one combination, ``-combos`` for the per-combination table."""
    def block(m: re.Match) -> str:
        budget = int(m.group(2)) if m.group(2) else None
        body = (render_combos(doc, budget) if m.group(3) == "combos" else
                render(doc, combination=m.group(3), budget=budget))
        return f"{m.group(1)}\n{body}\n{m.group(4)}"
    return BLOCK.sub(block, text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "benchmark.json"))
    ap.add_argument("--readme", default=str(ROOT / "docs" / "results.md"))
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/results.md is stale")
    a = ap.parse_args(argv)
    doc = json.loads(Path(a.json).read_text())
    text = Path(a.readme).read_text()
    if BEGIN not in text or END not in text:
        print(f"{a.readme}: no {BEGIN} ... {END} block", file=sys.stderr)
        return 2
    new = rewrite(text, doc)
    if a.check:
        if new != text:
            print(f"{a.readme}: benchmark block is stale: run bench/render_readme.py",
                  file=sys.stderr)
            return 1
        return 0
    Path(a.readme).write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
