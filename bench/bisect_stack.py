"""Which setting change moved the stack's result? Bisection over settings, validation buckets.

Between two measurements of the demo (2026-12-04: similarity 67/100, random 42/100; 2026-12-05:
39/100 and 54/100, bucket pull, 10 seeds x 10 unseen test buckets) 78 commits touched the code.
The old commits cannot be judged on the validation buckets (``w2e demo --validate`` came in the
range), but every change of the range that alters what the stack learns from an exploration
is a setting on HEAD (the fine-tuning's steps, stop and anchor; the stack's prior was added and
left off). So the bisection runs on HEAD: each probe is the stack's config with a subset of the
changes reverted to the old values, measured as a user runs it (``w2e demo --validate``, one run
per seed and rule through ``bench/demo_seeds.py``'s runner, cached by ``summary.json``).

1. Measure the new end (HEAD's config) and the old end (every change reverted), paired by seed
   and judged instance (``before`` depends on the seed only).
2. If the old end's successes after exploring differ from the new end's with a seed-resampled
   95 % interval covering 0, the shift does not show on validation: nothing to bisect (and no
   evidence to revert). Otherwise halve the changes: revert the first half; the half whose
   reversal carries more than half of the shift holds the change; repeat until one is left.

A single ``--change`` makes it a paired A/B test of one setting on the same runs (seeds, scenes,
judged instances): the table says what the setting does to each rule.

    .venv/bin/python bench/bisect_stack.py --seeds 0 1 2 3 4 5 6 7 8 9 \
        --strategies similarity random --runs /tmp/bisect --out bench/results/bisect_stack \
        --change inference_node.finetune_steps=500 inference_node.fit_target=0.0 \
                 inference_node.anchor=0.1
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from demo_seeds import run_demo  # noqa: E402

from w2e_ros.core.model.metrics import bootstrap_ci  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config" / "w2e_stack.yaml"
VALIDATION = ["--validate", "--explore-instances", "5"]


def parse_change(text: str) -> tuple[str, str, object]:
    """``node.parameter=value`` -> (node, parameter, value as YAML reads it)."""
    key, sep, value = text.partition("=")
    node, dot, name = key.partition(".")
    if not sep or not dot or not node or not name:
        raise argparse.ArgumentTypeError(f"{text!r}: expected node.parameter=value")
    return node, name, yaml.safe_load(value)


def params_file(changes: list[tuple[str, str, object]], folder: Path, tag: str) -> Path:
    """HEAD's stack config with ``changes`` applied; a parameter it does not hold is an error
    (a typo would otherwise measure HEAD twice)."""
    cfg = yaml.safe_load(CONFIG.read_text())
    for node, name, value in changes:
        section = cfg.get(node, {}).get("ros__parameters")
        if section is None or name not in section:
            raise SystemExit(f"bisect_stack: {node}.{name} is not in {CONFIG}")
        section[name] = value
    path = folder / f"{tag}.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def tag_of(changes: list[tuple[str, str, object]]) -> str:
    return "new" if not changes else "set-" + "+".join(n for _, n, _ in changes)


class Probe:
    """Runs (cached) and reads one arm: the after-exploring successes per (seed, instance)."""

    def __init__(self, a: argparse.Namespace) -> None:
        self.a = a
        self.runs = Path(a.runs)
        self.runs.mkdir(parents=True, exist_ok=True)
        self.arms: dict[str, dict] = {}
        self.t0 = time.perf_counter()

    def __call__(self, changes: list[tuple[str, str, object]]) -> dict:
        tag = tag_of(changes)
        if tag in self.arms:
            return self.arms[tag]
        pf = params_file(changes, self.runs, tag)
        extra = [*self.a.demo_flags, "--params-file", str(pf)]
        arm: dict = {"tag": tag, "changes": [f"{n}.{p}={v}" for n, p, v in changes],
                     "rules": {}}
        for st in self.a.strategies:
            before, after, spent = [], [], 0
            for s in self.a.seeds:
                r = run_demo(self.runs / f"{tag}_{st}_s{s}", st, s, extra)
                before.append([o["success"] for o in r["before"]])
                after.append([o["success"] for o in r["after"]])
                spent += int(r["explore"]["interactions"])
                print(f"[bisect] {tag} {st} seed {s}: {sum(before[-1])} -> {sum(after[-1])}; "
                      f"{time.perf_counter() - self.t0:.0f} s", flush=True)
            arm["rules"][st] = {"before": np.array(before, bool).tolist(),
                                "after": np.array(after, bool).tolist(),
                                "interactions": spent}
        self.arms[tag] = arm
        return arm


def shift(arm: dict, ref: dict, rule: str, seeds: list[int]) -> dict:
    """arm − ref in successes after exploring per trial, paired by (seed, instance)."""
    a = np.array(arm["rules"][rule]["after"], float)
    b = np.array(ref["rules"][rule]["after"], float)
    d = (a - b).reshape(-1)
    seed_of = np.repeat(np.arange(len(seeds)), a.shape[1])
    mean, lo, hi = bootstrap_ci(lambda i: d[i].mean(), seed_of)
    return {"mean": mean, "ci": [lo, hi], "after": int(a.sum()), "ref_after": int(b.sum()),
            "trials": int(a.size)}


def bisect(a: argparse.Namespace) -> dict:
    probe = Probe(a)
    changes = list(a.change)
    rule = a.strategies[0]
    new, old = probe([]), probe(changes)
    total = shift(old, new, rule, a.seeds)
    steps: list[dict] = [{"reverted": old["changes"], **total}]
    out: dict = {"rule": rule, "seeds": a.seeds, "demo_flags": a.demo_flags,
                 "changes": old["changes"], "total_shift": total, "steps": steps}
    if total["ci"][0] <= 0 <= total["ci"][1]:
        out["verdict"] = (f"no shift on validation: reverting every change moves {rule}'s "
                          f"successes by {100 * total['mean']:+.0f} % "
                          f"[{100 * total['ci'][0]:+.0f}, {100 * total['ci'][1]:+.0f}]")
    else:
        suspects = changes
        while len(suspects) > 1:
            half = suspects[: len(suspects) // 2]
            part = shift(probe(half), new, rule, a.seeds)
            steps.append({"reverted": [f"{n}.{p}={v}" for n, p, v in half], **part})
            carries = abs(part["mean"]) > abs(total["mean"]) / 2
            suspects = half if carries else suspects[len(suspects) // 2:]
        n, p, v = suspects[0]
        out["culprit"] = f"{n}.{p}={v}"
        out["verdict"] = f"the shift follows {n}.{p} (old value {v})"
    out["arms"] = {t: {"changes": arm["changes"],
                       "rules": {st: {"before": int(np.sum(r["before"])),
                                      "after": int(np.sum(r["after"])),
                                      "trials": int(np.size(r["after"])),
                                      "interactions": r["interactions"],
                                      "below_start": int(np.sum(
                                          np.sum(r["after"], 1) < np.sum(r["before"], 1))),
                                  "above_start": int(np.sum(
                                          np.sum(r["after"], 1) > np.sum(r["before"], 1)))}
                                 for st, r in arm["rules"].items()},
                       "minus_new": {st: shift(arm, new, st, a.seeds) for st in a.strategies}}
                   for t, arm in probe.arms.items()}
    return out


def write_table(res: dict, out: Path) -> None:
    lines = [f"# Bisection over settings: {res['rule']}, {len(res['seeds'])} seeds, "
             f"w2e demo {' '.join(res['demo_flags'])}", "",
             f"**{res['verdict']}.**", "",
             "| arm | rule | before -> after (of trials) | interactions | seeds below / above "
             "start | after − new [95 % CI, seeds resampled] |", "|---|---|---|---|---|---|"]
    for tag, arm in res["arms"].items():
        for st, r in arm["rules"].items():
            m = arm["minus_new"][st]
            diff = ("" if tag == "new" else f"{100 * m['mean']:+.0f} % "
                    f"[{100 * m['ci'][0]:+.0f}, {100 * m['ci'][1]:+.0f}]")
            lines.append(f"| {tag} | {st} | {r['before']} -> {r['after']} ({r['trials']}) | "
                         f"{r['interactions']} | {r['below_start']} / {r['above_start']} of "
                         f"{len(res['seeds'])} | "
                         f"{diff} |")
    lines += ["", "Arms: " + "; ".join(f"{t} = {', '.join(a['changes']) or 'HEAD config'}"
                                       for t, a in res["arms"].items())]
    (out / "bisect.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--change", type=parse_change, nargs="+", required=True,
                   help="node.parameter=old_value, the settings of the old end")
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    p.add_argument("--strategies", nargs="+", default=["similarity", "random"],
                   help="the first decides the bisection")
    p.add_argument("--runs", default="/tmp/bisect_stack", help="one directory per demo run")
    p.add_argument("--out", default="bench/results/bisect_stack")
    p.add_argument("demo_flags", nargs="*", help="after --: the w2e demo flags of every run "
                   f"(default: {' '.join(VALIDATION)}, the validation buckets)")
    a = p.parse_args(argv)
    a.demo_flags = a.demo_flags or VALIDATION
    res = bisect(a)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bisect.json").write_text(json.dumps(res, indent=2))
    write_table(res, out)
    print((out / "bisect.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
