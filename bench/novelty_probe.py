"""Does any label-free signal of the model tell which novel categories it gets wrong?

The claim needs a familiarity score that is low where the affordance model is wrong on unseen
categories. The similarity head is trained for that and fails (bench/RESEARCH.md, "csr push,
tfr pull and tsw pull"). This probe puts beside it the plainest label-free alternatives, per
novel category and per interaction:

* ``similarity``: the model's similarity head;
* ``knn``: closeness of the contact point's encoder feature to the training categories' contact
  features: minus the mean distance to its k nearest bank features, each feature standardised
  by the bank's mean and spread (cosine closeness is ~1 for every pair: the features share a
  large common direction);
* ``confidence``: |p - 0.5| of the affordance itself;
* ``geometry``: the same k-NN closeness in a descriptor that owes nothing to the model: the
  shape of the contact's neighbourhood at 3 / 6 / 12 cm (linearity, planarity, scattering of
  the local covariance), its normal and the action's approach direction.

For each it reports the rank correlation, across the novel categories, of the category's mean
score with the model's AUROC on that category (high = the score calls familiar what the model
ranks well), and the AUROC of the score for "the prediction is right" over all interactions.

    .venv/bin/python bench/novelty_probe.py --model checkpoints/w2e_cfw_pull.pt \
        --train-data data/train/cfw --test-data data/valset/novel_cfw \
        --out bench/results/novelty/cfw_pull_val
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.exploration.familiarity import describe_data, knn_closeness
from w2e_ros.core.model.metrics import auroc
from w2e_ros.core.model.network import load_model
from w2e_ros.core.model.predict import encode_clouds, predict_interactions
from w2e_ros.core.model.training import method_categories

SCORES = ("similarity", "knn", "confidence", "geometry")


def contact_features(model, data: InteractionData) -> torch.Tensor:
    """(K, F) encoder features at each interaction's contact point."""
    out = []
    for s in range(0, data.num_observations, 16):
        rows = np.flatnonzero((data.obs_index >= s) & (data.obs_index < s + 16))
        feats = encode_clouds(model, data.points[s:s + 16])
        out.append((rows, feats[torch.from_numpy(data.obs_index[rows] - s).long(),
                                torch.from_numpy(data.point_index[rows]).long()]))
    f = torch.zeros(data.num_interactions, model.cfg.feat_dim)
    for rows, x in out:
        f[torch.from_numpy(rows)] = x.cpu()
    return f


def raw_knn_distance(query: torch.Tensor, bank: torch.Tensor, k: int) -> float:
    """Mean distance of the query rows to their k nearest bank rows, in raw feature units."""
    return float(torch.cat([torch.cdist(query[s:s + 1024], bank).topk(k, dim=1, largest=False)
                            .values.mean(1) for s in range(0, len(query), 1024)]).mean())


def silent_features(model, points: np.ndarray) -> int:
    """Output features that are never positive on any point of these clouds."""
    f = encode_clouds(model, points).reshape(-1, model.cfg.feat_dim)
    return int(((f > 1e-6).sum(0) == 0).sum())


def probe(model_path: str, train_dir: str, test_dir: str, bank_rows: int, k: int,
          seed: int, heldout_dir: str | None = None) -> dict:
    model, meta = load_model(model_path)
    prim = meta["primitive"]
    aff_cats, sim_cats = method_categories(str(meta.get("method", "w2e")),
                                           str(meta.get("combo", "cfw")))
    rng = np.random.default_rng(seed)
    sim_cats = sim_cats or aff_cats  # a Where2Act model: every training category
    train = InteractionData.load(train_dir).select(primitive=prim, categories=sim_cats,
                                                   valid_only=True)
    # the bank: contact features of a random subset of the training observations' trials
    obs = rng.choice(train.num_observations, min(train.num_observations, bank_rows // 24 + 1),
                     replace=False)
    bank_data = train.subset(np.isin(train.obs_index, obs))
    bank = contact_features(model, bank_data)
    test = InteractionData.load(test_dir).select(primitive=prim, valid_only=True)
    p, sim = predict_interactions(model, test)
    test_feats = contact_features(model, test)
    y = test.success.astype(bool)
    right = (p > 0.5) == y
    scores = {"similarity": sim, "knn": knn_closeness(test_feats, bank, k),
              "confidence": np.abs(p - 0.5),
              "geometry": knn_closeness(describe_data(test), describe_data(bank_data), k)}
    cats = test.interaction_category
    per_cat = {}
    for c in sorted(set(cats.tolist())):
        m = cats == c
        per_cat[c] = {"n": int(m.sum()), "success": float(y[m].mean()),
                      "auroc": auroc(p[m], y[m]) if y[m].any() and (~y[m]).any() else float("nan"),
                      "accuracy": float(right[m].mean()),
                      **{s: float(v[m].mean()) for s, v in scores.items()}}
    geometry = {"test_knn_distance": raw_knn_distance(test_feats, bank, k),
                "feature_norm": float(bank.norm(dim=1).mean()),
                "silent_features_train": silent_features(
                    model, train.points[rng.choice(train.num_observations, 32, replace=False)]),
                "silent_features_test": silent_features(
                    model, test.points[rng.choice(test.num_observations, 32, replace=False)])}
    if heldout_dir:  # unseen instances of the training categories: the distance of "familiar"
        held = InteractionData.load(heldout_dir).select(primitive=prim, categories=sim_cats,
                                                        valid_only=True)
        geometry["heldout_knn_distance"] = raw_knn_distance(contact_features(model, held),
                                                            bank, k)
    names = [c for c in per_cat if np.isfinite(per_cat[c]["auroc"])]
    corr = {s: {"auroc": float(spearmanr([per_cat[c][s] for c in names],
                                         [per_cat[c]["auroc"] for c in names])[0]),
                "accuracy": float(spearmanr([per_cat[c][s] for c in names],
                                            [per_cat[c]["accuracy"] for c in names])[0]),
                "right_auroc": auroc(scores[s], right)} for s in SCORES}
    return {"model": model_path, "primitive": prim, "bank_categories": list(sim_cats),
            "bank_rows": len(bank), "k": k, "test": test_dir, "rows": len(y),
            "per_category": per_cat, "scores": corr, "geometry": geometry}


def markdown(r: dict) -> str:
    lines = [f"# Label-free familiarity against the model's per-category AUROC ({r['primitive']})",
             "", f"Model `{r['model']}`, novel interactions `{r['test']}` ({r['rows']} valid), "
             f"k-NN bank: {r['bank_rows']} contact features of {', '.join(r['bank_categories'])}"
             f" (k = {r['k']}). Scores: higher = more familiar.", "",
             "| score | Spearman with category AUROC | with category accuracy | AUROC for "
             "\"prediction right\" |", "|---|---|---|---|"]
    lines += [f"| {s} | {v['auroc']:+.2f} | {v['accuracy']:+.2f} | {100 * v['right_auroc']:.1f} |"
              for s, v in r["scores"].items()]
    g = r["geometry"]
    lines += ["", f"Encoder features (norm {g['feature_norm']:.2f}): mean {r['k']}-NN distance "
              f"to the bank {g['test_knn_distance']:.4f} for these interactions"
              + (f", {g['heldout_knn_distance']:.4f} for unseen instances of the training "
                 "categories" if "heldout_knn_distance" in g else "")
              + f"; {g['silent_features_train']} / {g['silent_features_test']} of the "
              "output features never fire on 32 training / 32 of these clouds."]
    lines += ["", "| category | n | success % | AUROC | accuracy | " + " | ".join(SCORES) + " |",
              "|---" * (5 + len(SCORES)) + "|"]
    for c, v in sorted(r["per_category"].items(), key=lambda kv: kv[1]["auroc"]):
        lines.append(f"| {c} | {v['n']} | {100 * v['success']:.1f} | {100 * v['auroc']:.1f} | "
                     f"{100 * v['accuracy']:.1f} | "
                     + " | ".join(f"{v[s]:.3f}" for s in SCORES) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--train-data", required=True)
    ap.add_argument("--test-data", required=True)
    ap.add_argument("--heldout-data", default=None,
                    help="unseen instances of the training categories (w2e collect --split "
                         "test): their distance to the bank is the reference for familiar")
    ap.add_argument("--bank-rows", type=int, default=20000)
    ap.add_argument("--k", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", required=True, help="writes OUT.md and OUT.json")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    r = probe(a.model, a.train_data, a.test_data, a.bank_rows, a.k, a.seed, a.heldout_data)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(r, indent=1))
    out.with_suffix(".md").write_text(markdown(r))
    print(markdown(r))


if __name__ == "__main__":
    main()
