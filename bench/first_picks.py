"""How often does each selection rule's first pick succeed? (issue 8 diagnostic)

On the EXPLORE instances of the given categories, the base model scores the first round's
candidates (the benchmark's proposal distribution, the simulator's movable mask), each rule
picks its ``--picks`` best per object, and the simulator executes them. A rule that finds
fewer successes than random starves the affordance head of positives, whatever else its picks
teach. Rules: random, similarity (least familiar), nosim (least certain), top affordance, and
the least familiar predicted failure (sim argmin among affordance <= 0.5). With
``--collection``, also the same rules ranked over a whole collection's rows (pooled over its
objects, the tenth each rule ranks first), which is where the last rule looked promising.
With ``--familiarity``, the mean similarity of the first round's candidates per object,
averaged per category, for every novel category: what the paper's bar and an object-level
rule would act on.

    .venv/bin/python bench/first_picks.py --model runs/w2e_cfw_pull/model.pt --primitive pull \
        --categories bucket kitchen_pot kettle box trashcan --collection data/valset/novel_cfw \
        --out bench/results/first_picks
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from w2e_ros.core.exploration.config import ExploreConfig
from w2e_ros.core.exploration.explore import explore_targets, sample_candidates
from w2e_ros.core.exploration.finetune import W2EExplorer
from w2e_ros.core.model.metrics import bootstrap_ci
from w2e_ros.core.model.network import load_model
from w2e_ros.experiments.sim_world import SimWorld


def rule_keys(aff: np.ndarray, sim: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Lower key = picked first."""
    return {"random": rng.random(len(aff)), "similarity": sim, "nosim": np.abs(aff - 0.5),
            "top affordance": -aff, "least familiar predicted failure": np.where(
                aff <= 0.5, sim, np.inf)}


def pooled_table(model, collection: str, categories: list[str], primitive: str,
                 seed: int) -> list[str]:
    """Success of the tenth of a collection's rows each rule ranks first, pooled."""
    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.model.predict import predict_interactions

    d = InteractionData.load(collection)
    keep = (np.char.startswith(d.primitive.astype(str), primitive)
            & np.isin(d.interaction_category.astype(str), categories))
    d = d.subset(keep)
    aff, sim = predict_interactions(model, d)
    y = d.success.astype(float)
    n = len(y) // 10
    out = [f"Pooled over {collection} ({len(y)} {primitive} rows, {int(y.sum())} successful): "
           f"success of the tenth ({n} rows) each rule ranks first, in %.", "",
           "| rule | success |", "|---|---|"]
    for rule, key in rule_keys(aff, sim, np.random.default_rng(seed)).items():
        out.append(f"| {rule} | {100 * y[np.argsort(key, kind='stable')[:n]].mean():.1f} |")
    return out


def familiarity_table(scorer: W2EExplorer, world: SimWorld, objects: int, seed: int,
                      combo: str) -> list[str]:
    """Mean similarity of each novel category's first-round candidates (object means)."""
    from w2e_ros.core.dataset.categories import load_categories

    cfg, rng = ExploreConfig(), np.random.default_rng(seed)
    rows = []
    for cat in load_categories().novel(combo):
        means = []
        for t in explore_targets([cat], objects):
            cloud = world.observe(t)
            cand = sample_candidates(cloud, cfg.points_per_object, cfg.dirs_per_point, rng,
                                     cloud.movable)
            means.append(float(scorer.score([cloud], [cand])[0].similarity.mean()))
        rows.append((float(np.mean(means)), cat, min(means), max(means)))
    out = ["Mean similarity of the first round's candidates (per object, then per category; "
           f"{objects} explore objects each), least familiar first.", "",
           "| category | mean similarity | object min | object max |", "|---|---|---|---|"]
    out += [f"| {c} | {m:.3f} | {lo:.3f} | {hi:.3f} |" for m, c, lo, hi in sorted(rows)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="runs/w2e_cfw_pull/model.pt")
    ap.add_argument("--primitive", default="pull")
    ap.add_argument("--categories", nargs="+",
                    default=["bucket", "kitchen_pot", "kettle", "box", "trashcan"])
    ap.add_argument("--objects", type=int, default=10, help="explore instances per category")
    ap.add_argument("--picks", type=int, default=4, help="picks per object and rule")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--collection", default=None,
                    help="also rank a collection's rows (w2e collect) pooled over its objects")
    ap.add_argument("--familiarity", action="store_true",
                    help="also the mean candidate similarity of every novel category")
    ap.add_argument("--out", default="bench/results/first_picks")
    a = ap.parse_args()
    torch.set_num_threads(1)
    model, meta = load_model(a.model, "cpu")
    cfg = ExploreConfig()
    scorer = W2EExplorer(model, cfg.finetuning, None, tuple(meta.get("aff_categories", ())),
                         tuple(meta.get("sim_categories", ())))
    world = SimWorld()
    rng = np.random.default_rng(a.seed)
    rows: list[dict] = []
    for t in explore_targets(a.categories, a.objects):
        cloud = world.observe(t)
        cand = sample_candidates(cloud, cfg.points_per_object, cfg.dirs_per_point, rng,
                                 cloud.movable)
        s = scorer.score([cloud], [cand])[0]
        for rule, key in rule_keys(s.affordance, s.similarity, rng).items():
            for i in np.argsort(key, kind="stable")[:a.picks]:
                r = world.execute(t, cand.action(cloud, int(i), a.primitive))
                rows.append({"rule": rule, "category": t.category, "object": t.name,
                             "success": bool(r.success), "valid": bool(r.valid),
                             "affordance": float(s.affordance[i]),
                             "similarity": float(s.similarity[i])})
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "picks.json").write_text(json.dumps(rows, indent=1))
    n_obj = len({r["object"] for r in rows})
    lines = [f"First-round picks on {n_obj} explore objects "
             f"({', '.join(a.categories)}; {a.primitive}, {a.picks} per object and rule, "
             f"seed {a.seed}); success in %, 95 % bootstrap interval over objects.", "",
             "| rule | success | valid | mean affordance | mean similarity |",
             "|---|---|---|---|---|"]
    for rule in dict.fromkeys(r["rule"] for r in rows):
        sel = [r for r in rows if r["rule"] == rule]
        ok = np.array([r["success"] for r in sel], float)
        objs = np.array([r["object"] for r in sel])
        _, lo, hi = bootstrap_ci(lambda idx, ok=ok: float(ok[idx].mean()), objs)
        lines.append(f"| {rule} | {100 * ok.mean():.1f} [{100 * lo:.1f}, {100 * hi:.1f}] | "
                     f"{100 * np.mean([r['valid'] for r in sel]):.0f} | "
                     f"{np.mean([r['affordance'] for r in sel]):.2f} | "
                     f"{np.mean([r['similarity'] for r in sel]):.2f} |")
    if a.collection:
        lines += ["", *pooled_table(model, a.collection, a.categories, a.primitive, a.seed)]
    if a.familiarity:
        lines += ["", *familiarity_table(scorer, world, a.objects, a.seed, str(
            meta.get("combo", "cfw")))]
    (out / "first_picks.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
