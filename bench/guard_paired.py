"""Paired per-seed comparison of benchmark runs of one rule made with different fine-tuning
settings (issue 40 item 4: the update guard). Each run directory holds the benchmark's
predictions_<combo>_<prim>.npz; budget 0 of any run is the un-adapted model (`none`).

    python bench/guard_paired.py --arm off=results/g_off --arm average=results/g_avg \
        --method random --out bench/results/guard/validation/paired.json

An arm may name several run directories (other seeds of the same setting).

Per arm and budget: mean AUROC / F-score over seeds, the paired difference to the first arm
with a 95 % bootstrap interval over seeds, and the seeds whose AUROC (F-score) ends below
the un-adapted model's.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from w2e_ros.core.model.metrics import auroc, fscore


def per_seed(path: Path, method: str) -> dict[tuple[int, int], dict[str, float]]:
    z = np.load(path)
    y = z["test:success"]
    out: dict[tuple[int, int], dict[str, float]] = {}
    for k in z.files:
        if k.startswith(f"pred:{method}|") and k.endswith("|aff"):
            _, seed, b, _ = k[5:].split("|")
            a = z[k]
            out[(int(seed), int(b))] = {"auroc": auroc(a, y),
                                        "fscore": fscore(a > 0.5, y)["fscore"]}
    return out


def boot_ci(d: np.ndarray, rng: np.random.Generator, n: int = 2000) -> tuple[float, float]:
    idx = rng.integers(len(d), size=(n, len(d)))
    lo, hi = np.percentile(d[idx].mean(1), [2.5, 97.5])
    return float(lo), float(hi)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--arm", action="append", required=True,
                   help="NAME=RUN_DIR[,RUN_DIR...] (the first arm is the base)")
    p.add_argument("--method", default="random")
    p.add_argument("--file", default="predictions_cfw_pull.npz")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    arms = dict(x.split("=", 1) for x in a.arm)
    vals = {name: {k: v for d in dirs.split(",") for k, v in
                   per_seed(Path(d) / a.file, a.method).items()}
            for name, dirs in arms.items()}
    base = next(iter(arms))
    seeds = sorted(set.intersection(*({s for s, _ in v} for v in vals.values())))
    budgets = sorted({b for v in vals.values() for _, b in v if b > 0})
    rng = np.random.default_rng(0)
    rows, lines = [], [f"Seeds {seeds} ({len(seeds)}), method {a.method}; values in %, "
                       f"paired 95 % bootstrap intervals over seeds; 'below none': seeds whose "
                       f"value ends below the un-adapted model's (budget 0).", "",
                       "| arm | budget | AUROC | vs " + base + " | below none | F-score | vs "
                       + base + " | below none |", "|---|---|---|---|---|---|---|---|"]
    for name, v in vals.items():
        for b in budgets:
            row = {"arm": name, "budget": b, "seeds": seeds}
            cells = []
            for m in ("auroc", "fscore"):
                x = np.array([v[(s, b)][m] for s in seeds])
                none = np.array([v[(s, 0)][m] for s in seeds])
                ref = np.array([vals[base][(s, b)][m] for s in seeds])
                d = x - ref
                lo, hi = boot_ci(d, rng)
                below = int(np.sum(x < none - 1e-9))
                row[m] = {"mean": float(x.mean()), "per_seed": x.tolist(),
                          "none": float(none.mean()), "vs_base": float(d.mean()),
                          "vs_base_ci": [lo, hi], "below_none": below}
                cells += [f"{100 * x.mean():.1f}",
                          "" if name == base else f"{100 * d.mean():+.1f} [{100 * lo:+.1f}, "
                          f"{100 * hi:+.1f}]", f"{below}/{len(seeds)}"]
            rows.append(row)
            lines.append(f"| {name} | {b} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(f"none (budget 0): AUROC {100 * rows[0]['auroc']['none']:.1f}, F-score "
                 f"{100 * rows[0]['fscore']['none']:.1f}")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"arms": arms, "method": a.method, "rows": rows}, indent=1))
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
