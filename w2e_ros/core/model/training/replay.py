"""What few-shot fine-tuning replays of the training data: the train-split interactions of
the categories a model was trained on, or a small pack of them shipped beside a checkpoint."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.model.training.selection import load_training_data_from


def replay_data(data: InteractionData, meta: dict, primitive: str) -> InteractionData:
    """What a few-shot run replays: the train-split interactions of the categories the model
    was trained on (its checkpoint's ``aff_categories`` + ``sim_categories``), one primitive."""
    cats = list(dict.fromkeys(list(meta.get("aff_categories", [])) +
                              list(meta.get("sim_categories", []))))
    cfg = load_categories()
    train_split = cfg.training_instances(cats[0] if cats else cfg.categories[0])
    return data.select(primitive=primitive, categories=cats or None, instances=train_split)


REPLAY_PACK = "replay_pack"  # meta key of a collection that IS a replay sample


def replay_pack(data: InteractionData, method: str, combo: str,
                primitives: Sequence[str] = ("push", "pull"), fraction: float = 0.01,
                seed: int = 0) -> InteractionData:
    """``fraction`` of the train-split interactions of the method's training categories (per
    primitive, distinct interactions, with only the clouds they refer to): what fine-tuning
    replays, small enough to ship beside a checkpoint so that a stack without the training
    collection still replays it (the reference replays ~1 %). The meta marks it as a pack,
    so a fine-tuner replays all of it instead of ``fraction`` of it again."""
    rng = np.random.default_rng(seed)
    parts, totals = [], []
    for prim in primitives:
        sel = load_training_data_from(data, method, combo, prim)
        n = max(1, int(round(fraction * sel.num_interactions)))
        parts.append(sel.subset(np.sort(rng.choice(sel.num_interactions, n, replace=False))))
        totals.append(sel.num_interactions)
    pack = InteractionData.concat(parts)
    pack.meta = {**data.meta, REPLAY_PACK: {
        "method": method, "combo": combo, "primitives": list(primitives),
        "fraction": fraction, "of": totals, "seed": seed}}
    return pack
