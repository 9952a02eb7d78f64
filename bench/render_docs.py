"""Render every table and key figure of README.md and docs/*.md from the result files.

The pages hold no number typed by hand where a committed result file has it: each figure
sits in a block that this script rewrites from ``bench/results/``:

* ``<!-- w2e:begin NAME -->`` ... ``<!-- w2e:end NAME -->``, where NAME is one of
  :data:`BLOCKS` (``key-figures``, ``demo-seeds``, ...) or ``KIND:ARG`` with a result folder
  as ARG (``benchmark:geometry_rule/test``, ``demo-seeds:replay``,
  ``learnability:learnability/per_category``); see :func:`render_block`;
* the benchmark tables of docs/results.md between ``<!-- benchmark...:begin -->`` markers,
  rendered from ``bench/results/benchmark.json`` by ``bench/render_readme.py``.

One sign convention everywhere: a difference is rule − baseline (``similarity − random``,
``random − none``); a negative number means the rule is below its baseline.

    .venv/bin/python bench/render_docs.py            # rewrite the blocks in place
    .venv/bin/python bench/render_docs.py --check    # exit 1 naming every stale block

``test/test_docs_rendered.py`` runs the check (CI: ``make test``). The approach-check table of
docs/ros_api.md has its own renderer (``bench/approach_check.py --readme``, checked by
``test/test_readme_results.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
sys.path.insert(0, str(Path(__file__).resolve().parent))
import render_readme  # noqa: E402  (the benchmark tables; bench/ is not a package)

BLOCK = re.compile(r"(<!-- w2e:begin ([\w:/.@-]+) -->)\n(?:.*?\n)??(<!-- w2e:end \2 -->)", re.S)
BEGIN = re.compile(r"<!-- w2e:begin ([^ ]+) -->")
END = re.compile(r"<!-- w2e:end ([^ ]+) -->")
MINUS = "−"  # U+2212 in prose; the benchmark tables keep render_readme's ASCII sign
_PAGE: list[Path] = [ROOT / "README.md"]  # the page being rendered: links are relative to it


def pages(root: Path = ROOT) -> list[Path]:
    """The user's pages: the README and docs/*.md."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def link(text: str, target: str) -> str:
    """A markdown link from the page being rendered to ``target`` (relative to the root,
    ``#anchor`` kept), so one block reads right in README.md and in docs/."""
    path, _, anchor = target.partition("#")
    rel = Path(os.path.relpath(ROOT / path, _PAGE[0].parent)).as_posix()
    return f"[{text}]({rel}{'#' + anchor if anchor else ''})"


def load(rel: str) -> dict:
    """A result file under bench/results (``rel`` relative to it)."""
    return json.loads((RESULTS / rel).read_text())


# --- number formatting -----------------------------------------------------------------

def signed(x: float, digits: int = 1) -> str:
    s = f"{x:+.{digits}f}"
    if float(s) == 0:
        s = f"{0:+.{digits}f}"  # no "-0.0"
    return s.replace("-", MINUS)


def plain(x: float, digits: int = 1) -> str:
    return f"{x:.{digits}f}".replace("-", MINUS)


def interval(r: dict, sign: bool = True, scale: float = 100, digits: int = 1) -> str:
    """``+7.7 [3.4, 12.1]`` from a benchmark row (fractions, scaled to %)."""
    fmt = signed if sign else plain
    return (f"{fmt(scale * r['mean'], digits)} [{plain(scale * r['ci_low'], digits)}, "
            f"{plain(scale * r['ci_high'], digits)}]")


def row(doc: dict, method: str, metric: str, primitive: str = "pull", budget: int | None = None,
        vs: str | None = None, combination: str = "cfw") -> dict:
    """One row of a benchmark summary; KeyError names what is missing."""
    rows = doc["rows"]
    budget = budget if budget is not None else max(r["budget"] for r in rows)
    for r in rows:
        if (r["combination"], r["method"], r["metric"], r["primitive"], r["budget"],
                r.get("vs")) == (combination, method, metric, primitive, budget, vs):
            return r
    raise KeyError(f"no row {combination}/{method}/{metric}/{primitive}/b{budget}/vs={vs}")


def diff(doc: dict, method: str, vs: str, metric: str, **kw) -> str:
    return interval(row(doc, method, metric, vs=vs, **kw))


def level(doc: dict, method: str, metric: str, **kw) -> str:
    return plain(100 * row(doc, method, metric, **kw)["mean"])


def seeds_of(doc: dict, method: str, primitive: str = "pull", combination: str = "cfw") -> int:
    return row(doc, method, "auroc", primitive=primitive, combination=combination)["n_seeds"]


# --- the stack's demo over seeds (bench/demo_seeds.py) ----------------------------------

def _pct_ci(ci: list[float], negate: bool = False) -> str:
    """A fraction's mean and interval as whole % (``+29 % [+7, +47]``)."""
    m, lo, hi = (-ci[0], -ci[2], -ci[1]) if negate else tuple(ci)
    return f"{signed(100 * m, 0)} % [{signed(100 * lo, 0)}, {signed(100 * hi, 0)}]"


def _demo_rows(res: dict, label: str) -> list[str]:
    out = []
    for st, r in res["strategies"].items():
        out.append(f"| {st}{label} | {r['before']}/{r['trials']} -> {r['after']}/{r['trials']} | "
                   f"{r['interactions']} | {_pct_ci(r['gain_ci_seeds'])} | {r['gained']} / "
                   f"{r['lost']} (p = {r['mcnemar_p']:.2g}) |")
    return out


def _split_flags(res: dict) -> tuple[str, list[str]]:
    """The demo's budget and its other flags, as ``bench/demo_seeds.py`` recorded them."""
    flags = [f for f in res.get("demo_flags", []) if f != "--"]
    budget = flags[flags.index("--budget") + 1] if "--budget" in flags else "5"
    rest = [f for i, f in enumerate(flags) if f != "--budget"
            and (i == 0 or flags[i - 1] != "--budget")]
    return budget, rest


def _flags(res: dict) -> str:
    return f", budget {_split_flags(res)[0]}"


def _demo_differences(res: dict, judged: str) -> list[str]:
    """rule − baseline from bench/demo_seeds.py's ``after_minus_<first>`` (stored as the
    later strategy minus the first: the sign is turned when the first is the rule)."""
    out = []
    for st, r in res["strategies"].items():
        for k, v in r.items():
            if not k.startswith("after_minus_"):
                continue
            ref = k[len("after_minus_"):]
            rule, base, neg = (ref, st, True) if st == "random" else (st, ref, False)
            out.append(f"{rule} − {base}, successes after exploring (same seeds, same {judged} "
                       f"instances): {_pct_ci(v['ci_seeds'], neg)} with seeds resampled, "
                       f"[{signed(100 * (-v['ci_pairs'][2] if neg else v['ci_pairs'][1]), 0)}, "
                       f"{signed(100 * (-v['ci_pairs'][1] if neg else v['ci_pairs'][2]), 0)}] "
                       "with (seed, instance) pairs resampled.")
    return out


def demo_seeds(sub: str = "", extra: tuple[str, ...] = (), per_seed: bool = True) -> str:
    """The demo over exploration seeds: per rule before -> after, interactions spent, the
    mean gain per trial, rule − baseline after exploring, and (``per_seed``) every seed."""
    folder = f"demo_seeds/{sub}".rstrip("/")
    res = load(f"{folder}/demo_seeds.json")
    more = [(load(f"demo_seeds/{e}/demo_seeds.json"), e) for e in extra]
    first = next(iter(res["strategies"].values()))
    n_seeds = len(res["seeds"])
    judged = ("validation" if "--validate" in res.get("demo_flags", []) else "test")
    lines = [f"Bucket pull through the stack: {n_seeds} exploration seeds "
             f"({', '.join(map(str, res['seeds']))}), each judged on the same "
             f"{first['trials'] // n_seeds} unseen {judged} instances before and after. "
             f"Source: `bench/results/{folder}/demo_seeds.json`"
             + "".join(f", `bench/results/demo_seeds/{e}/demo_seeds.json`" for _, e in more)
             + "." + "".join(f" `w2e demo` flags of {src}: `{' '.join(rest)}`."
                             for src, rest in [(folder, _split_flags(res)[1]),
                                               *((e, _split_flags(d)[1]) for d, e in more)]
                             if rest), "",
             "| rule | successes before -> after | interactions | mean gain per trial "
             "[95 % CI, seeds resampled] | gained / lost (exact McNemar p) |",
             "|---|---|---|---|---|"]
    lines += _demo_rows(res, _flags(res))
    for doc, _ in more:
        lines += _demo_rows(doc, _flags(doc))
    lines += ["", *_demo_differences(res, judged)]
    if not per_seed:
        return "\n".join(lines).replace("\n\n\n", "\n\n")
    lines += ["", "Per seed, successes before -> after (interactions):", "",
              "| rule | " + " | ".join(f"seed {s}" for s in res["seeds"]) + " |",
              "|---" * (n_seeds + 1) + "|"]
    for doc in [res, *(d for d, _ in more)]:
        for st, r in doc["strategies"].items():
            lines.append(f"| {st}{_flags(doc)} | " + " | ".join(
                f"{p['before']} -> {p['after']} ({p['interactions']})" for p in r["per_seed"])
                + " |")
    return "\n".join(lines).replace("\n\n\n", "\n\n")


# --- learnability (w2e learnability --per-category) -------------------------------------

def learnability(folder: str) -> str:
    """Per category: AUROC / F-score (%) after fine-tuning on N of its own interactions,
    mean over seeds; categories sorted by their AUROC gain at the largest N."""
    doc = load(f"{folder}/per_category.json")
    curves = doc["curves"]
    ns = sorted({int(n) for c in curves.values() for n in c})
    top = str(ns[-1])

    def gain(cat: str) -> float:
        c = curves[cat]
        return c.get(top, c[max(c, key=int)])["auroc"][0] - c["0"]["auroc"][0]

    lines = [f"{doc['primitive'].capitalize()}, interactions chosen `{doc['selection']}`; "
             "AUROC / F-score in %, mean over seeds; sorted by the AUROC gain at "
             f"N = {top}. Source: `bench/results/{folder}/per_category.json`.", "",
             "| category | " + " | ".join(f"N = {n}" for n in ns) + " |",
             "|---" * (len(ns) + 1) + "|"]
    for cat in sorted(curves, key=gain, reverse=True):
        cells = []
        for n in ns:
            m = curves[cat].get(str(n))
            cells.append("-" if m is None else
                         f"{plain(100 * m['auroc'][0])} / {plain(100 * m['fscore'][0])}")
        lines.append(f"| {cat.replace('_', ' ')} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --- the benchmark (w2e benchmark) -------------------------------------------------------

def benchmark(arg: str) -> str:
    """``benchmark:<folder>[@<combination>][@b<budget>]``: the table of the folder's
    benchmark.json (``.`` is bench/results itself), as render_readme draws it."""
    folder, *opts = arg.split("@")
    combo = next((o for o in opts if not re.fullmatch(r"b\d+", o)), None)
    budget = next((int(o[1:]) for o in opts if re.fullmatch(r"b\d+", o)), None)
    rel = "benchmark.json" if folder in ("", ".") else f"{folder}/benchmark.json"
    body = render_readme.render(load(rel), combination=combo, budget=budget)
    return body + f"\n\nSource: `bench/results/{rel}`."


# --- the key figures (README and docs/status.md) ----------------------------------------

def key_figures() -> str:
    """The handful of numbers a user needs, each with its interval and its source."""
    demo = load("demo_seeds/demo_seeds.json")["strategies"]
    bench = load("benchmark.json")
    geo = load("geometry_rule/test/benchmark.json")
    sim, rnd = demo["similarity"], demo["random"]
    d = rnd["after_minus_similarity"]["ci_seeds"]
    n_demo = len(load("demo_seeds/demo_seeds.json")["seeds"])
    n_pull, n_push = seeds_of(bench, "random"), seeds_of(bench, "random", "push")
    mean = {"combination": "mean"}
    lines = [
        f"- **In the stack, one novel category** (bucket pull, {n_demo} exploration seeds x "
        f"{sim['trials'] // n_demo} unseen test buckets; "
        f"{link('demo', 'docs/demo.md#the-demo-over-seeds')}): exploring at random takes the "
        "robot from "
        f"{rnd['before']}/{rnd['trials']} to {rnd['after']}/{rnd['trials']} successes "
        f"({rnd['interactions']} interactions), the paper's similarity rule from "
        f"{sim['before']}/{sim['trials']} to {sim['after']}/{sim['trials']} "
        f"({sim['interactions']}); similarity − random after exploring {_pct_ci(d, True)}.",
        "- **Offline, the 11 novel categories at once** (the paper's Table 1 setting; `cfw`, "
        f"pull, budget 5 = 550 interactions, {n_pull} training x exploration seed pairs; "
        f"{link('table', 'docs/results.md#the-benchmark-cfw-budgets-5-and-1')}): random − none "
        f"AUROC {diff(bench, 'random', 'none', 'auroc')} ({level(bench, 'none', 'auroc')} -> "
        f"{level(bench, 'random', 'auroc')}), sample success on the unseen test objects "
        f"{level(bench, 'none', 'success')} % -> {level(bench, 'random', 'success')} % "
        f"({diff(bench, 'random', 'none', 'success')}); similarity − random AUROC "
        f"{diff(bench, 'similarity', 'random', 'auroc')}, F-score "
        f"{diff(bench, 'similarity', 'random', 'fscore')}; nosim − random AUROC "
        f"{diff(bench, 'nosim', 'random', 'auroc')}, where2act − random "
        f"{diff(bench, 'where2act', 'random', 'auroc')}.",
        f"- **Push** (`cfw`, budget 5, {n_push} seeds): random − none AUROC "
        f"{diff(bench, 'random', 'none', 'auroc', primitive='push')}, similarity − random "
        f"F-score {diff(bench, 'similarity', 'random', 'fscore', primitive='push')}.",
        "- **Over the four training combinations** (mean of `cfw`, `csr`, `tfr`, `tsw`, budget "
        f"5; {link('table', 'docs/results.md#the-claim-over-the-four-training-combinations')}): "
        f"random − none pull AUROC {diff(bench, 'random', 'none', 'auroc', **mean)}; "
        f"similarity − random pull AUROC {diff(bench, 'similarity', 'random', 'auroc', **mean)}, "
        f"F-score {diff(bench, 'similarity', 'random', 'fscore', **mean)}, push F-score "
        f"{diff(bench, 'similarity', 'random', 'fscore', primitive='push', **mean)}.",
        f"- **A model-free familiarity** (`geometry`, `cfw` pull, budget 5, "
        f"{seeds_of(geo, 'geometry')} seeds): geometry − random AUROC "
        f"{diff(geo, 'geometry', 'random', 'auroc')}, F-score "
        f"{diff(geo, 'geometry', 'random', 'fscore')}.",
        "- **The ceiling**: the Full-data model (trained on the novel categories' instances "
        f"too) reaches AUROC {interval(row(bench, 'fulldata', 'auroc'), sign=False)} pull and "
        f"{interval(row(bench, 'fulldata', 'auroc', primitive='push'), sign=False)} push "
        "(`cfw`, test objects); fulldata − random pull "
        f"{diff(bench, 'fulldata', 'random', 'auroc')}.",
    ]
    lines += ["", "Intervals: 95 % bootstrap (the stack: seeds resampled). Sources: "
              "`bench/results/demo_seeds/demo_seeds.json`, `bench/results/benchmark.json`, "
              "`bench/results/geometry_rule/test/benchmark.json`."]
    return "\n".join(lines)


def headline() -> str:
    """The README's first screen: what exploring buys and which rule to use, in two lines."""
    res = load("demo_seeds/demo_seeds.json")
    st = res["strategies"]
    sim, rnd = st["similarity"], st["random"]
    n = len(res["seeds"])
    bench = load("benchmark.json")
    return (f"**What exploring buys.** On a category the model never trained on (bucket pull, "
            f"through the stack, {n} exploration seeds x {sim['trials'] // n} unseen test "
            f"buckets), the robot succeeded {rnd['before']} times in {rnd['trials']} before "
            f"exploring and {rnd['after']} after exploring with random picks "
            f"({rnd['interactions']} interactions in all), {sim['after']} after exploring with "
            f"the paper's similarity rule ({sim['interactions']}).\n\n"
            "**Which rule to use: `random`.** No rule measured here picks better than random "
            "does: similarity − random after exploring in the stack "
            f"{_pct_ci(rnd['after_minus_similarity']['ci_seeds'], True)}; offline over the "
            f"11 novel categories (pull, budget 5) AUROC "
            f"{diff(bench, 'similarity', 'random', 'auroc')}.")


def demo_default() -> str:
    """What ``make demo`` printed on its default (bench/results/demo/summary.json)."""
    from w2e_ros.demo import report

    res = load("demo/summary.json")
    return ("```\n" + report(res) + "\n```\n\n"
            f"`make demo`, {res['date']}: {res['seconds_total']:.0f} s after the install (2 cores "
            "shared with a CI run). Source: `bench/results/demo/summary.json`.")


def pooled_success() -> str:
    """The two measurements of pooled sample success that the pages once mixed up."""
    full = load("benchmark.json")
    part = load("pooled_prior/benchmark.json")
    n_full, n_part = seeds_of(full, "random"), seeds_of(part, "random")
    return ("Sample success on the unseen test objects, `cfw` pull, budget 5, none -> random: "
            f"**{level(full, 'none', 'success')} % -> {level(full, 'random', 'success')} %** "
            f"(random − none {diff(full, 'random', 'none', 'success')}) over all {n_full} "
            "training x exploration seed pairs (`bench/results/benchmark.json`, the figure these "
            f"pages quote); {level(part, 'none', 'success')} % -> "
            f"{level(part, 'random', 'success')} % ({diff(part, 'random', 'none', 'success')}) "
            f"on the shipped model's {n_part} exploration seeds alone, a subset of the same runs "
            "(`bench/results/pooled_prior/benchmark.json`).")


# --- reliability (bench/fault_injection.py, bench/load.py, test_respawn_reconnects) ------

def respawn() -> str:
    rows = ["| code | rounds | kills | next call executed a trial | kill -> answer median / max "
            "| file |", "|---|---|---|---|---|---|"]
    for name, label in (("respawn.json", "2026-12-07, before the watch's 2 s grace (e39e8e9)"),
                        ("respawn_before_fix.json", "before the fix (bec8a8c)")):
        r = load(f"reliability/{name}")
        k = r["kill_to_answer_s"]
        rows.append(f"| {label} | {r['rounds']} | {r['kills']} | {r['next_call_executed_a_trial']} "
                    f"| {k['median']:.1f} s / {k['max']:.1f} s | `{name}` |")
    return "\n".join(rows)


FAULT_KINDS = {  # bench/fault_injection.py's kinds, as the table says them
    "kill": "SIGKILL of a node", "term": "SIGTERM of a node",
    "stop_camera": "camera stops publishing", "hang_trial": "a trial never answered",
    "stop_bridge": "SIGSTOP of the bridge", "disk_full": "the log's disk full",
}


def faults() -> str:
    r = load("fault_injection/summary.json")
    replay = r["replay"].values()
    exact = sum(x["max_weight_difference"] == 0.0 for x in replay)
    rows = [
        "| faults | sessions | calls (ended by a fault) | interactions logged | lost | duplicated "
        "| survived | node restarts | adapted model = log replayed |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {r['faults']} | {r['sessions']} | {r['calls']} ({r['calls_failed']}) | "
        f"{r['interactions_logged']} | {r['interactions_lost']} | {r['interactions_duplicated']} "
        f"| {r['faults_noticed_within_bound']} of {r['faults']} | {r['node_restarts']} | "
        f"{exact} of {len(replay)} sessions, bit for bit |",
        "",
        "| fault | injected | survived | call ended naming it | call unaffected | "
        "noticed median / max | bound |", "|---|---|---|---|---|---|---|"]
    for kind, k in r["per_kind"].items():
        held = kind not in ("kill", "term")  # a kill may be resumed from: nothing to name
        rows.append(
            f"| {FAULT_KINDS[kind]} | {k['faults']} | {k['ok']} | "
            f"{k['named'] if held else '-'} | {k['no_effect'] if held else '-'} | "
            f"{k['noticed_s_median']:.1f} s / "
            # over the bound by less than 0.05 s must not read as the bound
            f"{k['noticed_s_max']:.{2 if k['noticed_s_max'] > k['bound_s'] else 1}f} s | "
            f"{k['bound_s']:.0f} s |")
    return "\n".join([*rows, "", "Source: `bench/results/fault_injection/summary.json`."])


def load_test(name: str = "summary") -> str:
    """``reliability-load`` (bench/results/load/summary.json) or ``load:NAME`` (load/NAME.json)."""
    r = load(f"load/{name}.json")
    nodes = list(r["rss_mb_first_last"])
    ex, cl = r["explore"], r["clouds"]
    alive = sum(r["nodes_alive_at_end"].values())
    busy = (f"answered busy in {1000 * r['second_client']['seconds']:.0f} ms"
            if r["second_answered_busy"] else "not answered busy")
    return "\n".join([
        "| second client | explore | Kinect-size clouds | nodes up at the end |",
        "|---|---|---|---|",
        f"| {busy} | {ex['used']} of {r['interactions_asked']} interactions in "
        f"{ex['seconds']:.0f} s | {cl['received']:,} of {cl['sent']:,} arrived | {alive} of "
        f"{len(r['nodes_alive_at_end'])} |", "",
        "| resident memory | " + " | ".join(nodes) + " |", "|---" * (len(nodes) + 1) + "|",
        "| first -> last sample (MB) | " + " | ".join(
            f"{a} -> {b}" for a, b in r["rss_mb_first_last"].values()) + " |",
        "| slope, second half (MB/min) | " + " | ".join(
            f"{r['rss_slope_mb_per_min'][n]:.1f}" for n in nodes) + " |",
        "", f"Source: `bench/results/load/{name}.json` ({r['minutes']:.0f} min"
        + (f", the inference node's `feature_cache_clouds` {r['feature_cache_clouds']}"
           if r.get("feature_cache_clouds") is not None else "") + ")."])


def ci_repeat() -> str:
    """`.ci/repeat --record`'s runs: per kind, runs and failures over every recorded session."""
    entries = load("reliability/ci_repeat.json")
    rows = ["| runs of | runs | with a failure | tests per run | mean wall time | commits | "
            "dates |", "|---|---|---|---|---|---|---|"]
    for kind, label in (("full", "the full suite on a clean clone (`.ci/run`)"),
                        ("ros", "the ROS-heavy files")):
        runs = [(e, r) for e in entries for r in e["runs"] if r["kind"] == kind]
        if not runs:
            continue
        bad = sum(1 for _, r in runs if r["exit"] != 0 or r["failed"])
        tests = sorted({r["tests"] for _, r in runs})
        commits = sorted({e["commit"] for e, _ in runs})
        dates = sorted({e["started"][:10] for e, _ in runs})
        span = str(tests[0]) if len(tests) == 1 else f"{tests[0]}-{tests[-1]}"
        rows.append(f"| {label} | {len(runs)} | {bad} | {span} "
                    f"| {sum(r['seconds'] for _, r in runs) / len(runs) / 60:.1f} min "
                    f"| {', '.join(commits)} | {', '.join(dates)} |")
    failed: dict[str, int] = {}
    for e in entries:
        for r in e["runs"]:
            for t in r["failed"]:
                failed[t] = failed.get(t, 0) + 1
    tail = (["", "Failed: " + "; ".join(f"`{t}` ({k})" for t, k in failed.items()) + "."]
            if failed else ["", "No test failed in any recorded run."])
    return "\n".join([*rows, *tail, "", "Source: `bench/results/reliability/ci_repeat.json`."])


# --- the real arm and outcomes from clouds (docs/real_robot.md) ----------------------------

def arm_reach() -> str:
    r = load("arm_reach/results.json")["summary"]
    rows = ["| primitive | objects | top-64 candidates reachable | best candidate reachable | "
            "objects with none of the best 256 reachable |", "|---|---|---|---|---|"]
    for prim in ("push", "pull"):
        x = r[prim]
        rows.append(f"| {prim} | {x['objects']} | {100 * x['top_reachable_share']:.1f} % | "
                    f"{100 * x['top1_reachable']:.1f} % | {x['none_reachable_in_candidates']} |")
    return "\n".join(rows)


def arm_sim() -> str:
    r = load("arm_sim/results.json")["summary"]
    rows = ["| primitive | objects | actions | flying valid / success | Panda valid / success | "
            "Panda − flying, per object [95 % CI] | agreement |", "|---|---|---|---|---|---|---|"]
    for prim in ("push", "pull"):
        x = r[prim]["all"]
        lo, hi = x["difference_ci95"]
        rows.append(f"| {prim} | {x['objects']} | {x['actions']} | "
                    f"{100 * x['flying_valid']:.1f} % / {100 * x['flying_success']:.1f} % | "
                    f"{100 * x['panda_valid']:.1f} % / "
                    f"{100 * x['panda_success']:.1f} % | {signed(100 * x['difference'])} "
                    f"[{signed(100 * lo)}, {signed(100 * hi)}] | {100 * x['agreement']:.1f} % |")
    return "\n".join(rows)


def outcome_agreement() -> str:
    a = load("outcome/outcome_agreement.json")["groups"]["all"]
    return (f"Judged from the object's cloud before and after, outcomes agree with the joints on "
            f"{100 * a['agreement']:.1f} % of {a['n']} valid simulated trials (precision "
            f"{100 * a['precision']:.1f} %, recall {100 * a['recall']:.1f} %; "
            "`bench/results/outcome/outcome_agreement.json`).")


# --- the registry -------------------------------------------------------------------------

BLOCKS: dict[str, Callable[[], str]] = {
    "key-figures": key_figures,
    "headline": headline,
    "pooled-success": pooled_success,
    "demo-default": demo_default,
    "demo-seeds": lambda: demo_seeds("", ("budget2",)),
    "demo-summary": lambda: demo_seeds("", ("budget2",), per_seed=False),
    "reliability-respawn": respawn,
    "reliability-faults": faults,
    "reliability-load": load_test,
    "reliability-ci": ci_repeat,
    "arm-reach": arm_reach,
    "arm-sim": arm_sim,
    "outcome-agreement": outcome_agreement,
}
KINDS: dict[str, Callable[[str], str]] = {
    "benchmark": benchmark,
    "demo-seeds": demo_seeds,
    "demo-summary": lambda sub: demo_seeds(sub, per_seed=False),
    "learnability": learnability,
    "load": load_test,
}


def render_block(name: str) -> str:
    """The body of block NAME: a fixed block of :data:`BLOCKS` or ``KIND:ARG``."""
    if name in BLOCKS:
        return BLOCKS[name]()
    kind, _, arg = name.partition(":")
    if kind in KINDS and arg:
        return KINDS[kind](arg)
    raise KeyError(f"unknown block {name!r}: one of {sorted(BLOCKS)} or "
                   f"{', '.join(k + ':ARG' for k in KINDS)}")


def wrap(body: str, width: int = 100) -> str:
    """Prose lines of a rendered body wrapped at ``width`` (bullets hang by two spaces);
    table rows stay whole."""
    out = []
    for line in body.splitlines():
        if line.startswith("|") or len(line) <= width:
            out.append(line)
        else:
            hang = "  " if line.startswith("- ") else ""
            kept = line.replace(" − ", "\x01").replace(" -> ", "\x02")  # no break beside them
            out.append(textwrap.fill(kept, width, subsequent_indent=hang,
                                     break_long_words=False, break_on_hyphens=False)
                       .replace("\x01", " − ").replace("\x02", " -> "))
    return "\n".join(out)


def problems(text: str) -> list[str]:
    """Markers that do not pair up (a begin without its end, an end without its begin)."""
    begins, ends = BEGIN.findall(text), END.findall(text)
    return ([f"w2e:begin {n} without its end" for n in begins if n not in ends]
            + [f"w2e:end {n} without its begin" for n in ends if n not in begins])


def rewrite(text: str, render: Callable[[str], str] = render_block,
            page: Path | None = None) -> str:
    """``text`` (of ``page``, default the README: links are relative to it) with every w2e
    block and benchmark block rendered anew."""
    _PAGE[0] = (page or ROOT / "README.md").resolve()

    def one(m: re.Match) -> str:
        return f"{m.group(1)}\n{wrap(render(m.group(2)).rstrip())}\n{m.group(3)}"
    text = BLOCK.sub(one, text)
    if "<!-- benchmark" in text:
        text = render_readme.rewrite(text, load("benchmark.json"))
    return text


def stale_blocks(old: str, new: str) -> list[str]:
    """The names of the blocks whose rendered body differs."""
    def bodies(t: str) -> dict[str, str]:
        found = {m.group(2): m.group(0) for m in BLOCK.finditer(t)}
        found.update({m.group(1): m.group(0) for m in render_readme.BLOCK.finditer(t)})
        return found
    a, b = bodies(old), bodies(new)
    return sorted(k for k in b if a.get(k) != b[k]) or (["(outside the blocks)"]
                                                         if old != new else [])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 when a page differs from its rendering")
    ap.add_argument("pages", nargs="*", type=Path, help="default: README.md and docs/*.md")
    a = ap.parse_args(argv)
    bad = 0
    for page in a.pages or pages():
        text = page.read_text()
        for p in problems(text):
            print(f"{page}: {p}", file=sys.stderr)
            bad += 1
        try:
            new = rewrite(text, page=page)
        except (KeyError, FileNotFoundError) as e:
            print(f"{page}: {e}", file=sys.stderr)
            bad += 1
            continue
        if new == text:
            continue
        if a.check:
            for name in stale_blocks(text, new):
                print(f"{page}: block {name} is stale: run .venv/bin/python bench/render_docs.py",
                      file=sys.stderr)
            bad += 1
        else:
            page.write_text(new)
            print(f"rendered {page.relative_to(ROOT) if page.is_absolute() else page}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
