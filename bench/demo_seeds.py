"""``w2e demo`` over exploration seeds and strategies: the demo's before/after, with its noise.

One demo run is 10 test instances under one exploration; which pulls the planner samples
(``--seed``) decides much of the outcome, so a single run says little. This runs the demo as a
user types it, once per (strategy, seed), keeps each run's ``summary.json`` (a run whose
summary is there is not run again), and writes per seed before -> after, the pooled counts
with an exact McNemar test on the (seed, instance) pairs, and each strategy's gain against
the first one paired by seed ("before" depends on the seed only, not on the strategy), with
95 % bootstrap intervals resampling seeds (and, tighter but treating instances as
independent, resampling (seed, instance) pairs).

    .venv/bin/python bench/demo_seeds.py --seeds 0 1 2 3 4 --strategies similarity random \
        --runs /tmp/demo_seeds --out bench/results/demo_seeds
    # the same with the inference node replaying the shipped 1 % of the training data
    .venv/bin/python bench/demo_seeds.py ... --tag replay -- --replay-data shipped
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from w2e_ros.core.model.metrics import bootstrap_ci


def run_demo(out: Path, strategy: str, seed: int, extra: list[str]) -> dict:
    """One ``w2e demo`` (skipped when its summary with per-instance outcomes exists)."""
    summary = out / "summary.json"
    if summary.exists() and "after" in (found := json.loads(summary.read_text())):
        return found
    out.mkdir(parents=True, exist_ok=True)
    cmd = [str(Path(sys.executable).with_name("w2e")), "demo", "--strategy", strategy,
           "--seed", str(seed), "--out", str(out), "--quiet-nodes",
           # the recorded runs' bar (the paper's); the demo's own default, 1.0, spends it all
           "--similarity-bar", "0.9", *extra]
    with (out / "demo.log").open("w") as f:
        rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT).returncode
    if not summary.exists():
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {rc}); see {out / 'demo.log'}")
    return json.loads(summary.read_text())


def mcnemar_p(gained: int, lost: int) -> float:
    """Exact two-sided McNemar p-value (binomial on the discordant pairs)."""
    n = gained + lost
    if n == 0:
        return 1.0
    k = min(gained, lost)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def summarise(runs: dict[str, dict[int, dict]], seeds: list[int]) -> dict:
    """Per-strategy counts and tests, and each strategy's gain against the first."""
    out: dict = {"seeds": seeds, "strategies": {}}
    ref = next(iter(runs))
    for st, by_seed in runs.items():
        b = np.array([[o["success"] for o in by_seed[s]["before"]] for s in seeds], bool)
        a = np.array([[o["success"] for o in by_seed[s]["after"]] for s in seeds], bool)
        gained, lost = int((~b & a).sum()), int((b & ~a).sum())
        n_inst = b.shape[1]
        seed_of = np.repeat(np.arange(len(seeds)), n_inst)
        gain = (a.astype(float) - b).reshape(-1)
        row = {
            "before": int(b.sum()), "after": int(a.sum()), "trials": int(b.size),
            "gained": gained, "lost": lost, "mcnemar_p": mcnemar_p(gained, lost),
            "interactions": int(sum(by_seed[s]["explore"]["interactions"] for s in seeds)),
            "per_seed": [{"seed": s, "before": int(b[k].sum()), "after": int(a[k].sum()),
                          "interactions": int(by_seed[s]["explore"]["interactions"]),
                          "explore_message": by_seed[s]["explore"]["message"]}
                         for k, s in enumerate(seeds)],
            "gain_ci_seeds": bootstrap_ci(lambda i, g=gain: g[i].mean(), seed_of),
        }
        if st != ref:
            ra = np.array([[o["success"] for o in runs[ref][s]["after"]] for s in seeds], float)
            d = (a - ra).reshape(-1)
            row[f"after_minus_{ref}"] = {
                "ci_seeds": bootstrap_ci(lambda i, d=d: d[i].mean(), seed_of),
                "ci_pairs": bootstrap_ci(lambda i, d=d: d[i].mean(), np.arange(len(d)))}
        out["strategies"][st] = row
    return out


def write_tables(res: dict, out: Path, title: str) -> None:
    seeds = res["seeds"]
    first = next(iter(res["strategies"].values()))
    judged = (f"{first['trials'] // len(seeds)} unseen "
              + ("validation (explore-split, not explored)" if "--validate" in
                 res.get("demo_flags", []) else "test") + " instances")
    lines = [f"# {title}", "", f"Successes on the {judged}, before -> after "
             "(interactions explored).", "",
             "| strategy | " + " | ".join(f"seed {s}" for s in seeds) + " | all | gained / lost "
             "(exact McNemar p) | mean gain per trial [95 % CI, seeds resampled] |",
             "|---" * (len(seeds) + 4) + "|"]
    for st, r in res["strategies"].items():
        cells = [f"{p['before']} -> {p['after']} ({p['interactions']})" for p in r["per_seed"]]
        g = r["gain_ci_seeds"]
        lines.append(f"| {st} | " + " | ".join(cells) +
                     f" | **{r['before']}/{r['trials']} -> {r['after']}/{r['trials']}** "
                     f"({r['interactions']}) | {r['gained']} / {r['lost']} "
                     f"(p = {r['mcnemar_p']:.3g}) | {100 * g[0]:+.0f} % "
                     f"[{100 * g[1]:+.0f}, {100 * g[2]:+.0f}] |")
    for st, r in res["strategies"].items():
        for k, v in r.items():
            if k.startswith("after_minus_"):
                s_, p_ = v["ci_seeds"], v["ci_pairs"]
                lines += ["", f"{st} after − {k[len('after_minus_'):]} after (same seeds, same "
                          f"test instances): {100 * s_[0]:+.0f} % [{100 * s_[1]:+.0f}, "
                          f"{100 * s_[2]:+.0f}] with seeds resampled; [{100 * p_[1]:+.0f}, "
                          f"{100 * p_[2]:+.0f}] with (seed, instance) pairs resampled."]
    (out / "demo_seeds.md").write_text("\n".join(lines) + "\n")


def plot(res: dict, out: Path, title: str) -> None:
    import matplotlib.pyplot as plt

    from w2e_ros.core.model.viz import write_figure  # selects the Agg backend

    seeds = res["seeds"]
    sts = list(res["strategies"])
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(seeds) * len(sts) / 2, 3.2))
    w = 0.8 / (2 * len(sts))
    for j, st in enumerate(sts):
        per = res["strategies"][st]["per_seed"]
        x = np.arange(len(seeds)) + (2 * j - len(sts) + 0.5) * w
        ax.bar(x, [p["before"] for p in per], w, color=f"C{j}", alpha=0.35,
               label=f"{st}: before")
        ax.bar(x + w, [p["after"] for p in per], w, color=f"C{j}", label=f"{st}: after")
    ax.set_xticks(np.arange(len(seeds)), [f"seed {s}" for s in seeds])
    ax.set_ylabel("test instances moved (of 10)")
    ax.set_ylim(0, 12.9)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, ncol=2 * len(sts), loc="upper center")
    fig.tight_layout()
    write_figure(fig, out / "demo_seeds.png", dpi=110)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--strategies", nargs="+", default=["similarity", "random"],
                   help="the first is the reference of the paired differences")
    p.add_argument("--runs", default="/tmp/demo_seeds", help="one directory per demo run")
    p.add_argument("--out", default="bench/results/demo_seeds")
    p.add_argument("--tag", default="", help="name of this configuration (file prefix)")
    p.add_argument("extra", nargs="*", help="after --: more w2e demo flags")
    a = p.parse_args(argv)
    out = Path(a.out) / a.tag if a.tag else Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    runs: dict[str, dict[int, dict]] = {st: {} for st in a.strategies}
    todo = [(st, s) for s in a.seeds for st in a.strategies]
    t0 = time.perf_counter()
    for k, (st, s) in enumerate(todo):
        d = Path(a.runs) / f"{a.tag + '_' if a.tag else ''}{st}_s{s}"
        runs[st][s] = r = run_demo(d, st, s, a.extra)
        el = time.perf_counter() - t0
        print(f"[demo_seeds] {k + 1}/{len(todo)} {st} seed {s}: "
              f"{r['success_rate_before']:.0%} -> {r['success_rate_after']:.0%} "
              f"({r['explore']['interactions']} interactions); {el:.0f} s, "
              f"ETA {el / (k + 1) * (len(todo) - k - 1):.0f} s", flush=True)
    res = summarise(runs, a.seeds)
    res["demo_flags"] = a.extra
    res["wall_s"] = time.perf_counter() - t0  # of this call (runs found on disk cost ~0)
    res["demo_seconds"] = sum(r["seconds"]["total"] for by in runs.values() for r in by.values())
    first = runs[a.strategies[0]][a.seeds[0]]
    title = (f"w2e demo, {first['category']} {first['primitive']}" +
             (f", {' '.join(a.extra)}" if a.extra else "") +
             f": {len(a.seeds)} exploration seeds")
    (out / "demo_seeds.json").write_text(json.dumps(res, indent=2))
    write_tables(res, out, title)
    plot(res, out, title)
    print((out / "demo_seeds.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
