"""Held-out interactions that judge a training run and pick its best checkpoint."""

from __future__ import annotations

import numpy as np

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.model.metrics import auroc, classification_metrics, within_class_auroc
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.model.predict import predict_interactions


class Validator:
    """Held-out interactions, judged during training: per group of categories (``caff`` =
    the affordance categories, ``csim`` = the other similarity categories, ``novel`` =
    categories the model never trains on, if the data holds any), on all trials and on
    valid trials only: F-score, AUROC, average precision; and the AUROC of the similarity
    score for "the affordance prediction is correct" (the similarity head's job).

    The score that picks the best checkpoint is the mean affordance AUROC over the training
    categories only: novel categories must not steer training.
    """

    def __init__(self, data: InteractionData, aff_cats: tuple[str, ...],
                 sim_cats: tuple[str, ...], primitive: str) -> None:
        train_split = set()
        cats_cfg = load_categories()
        for c in np.unique(data.category):
            train_split |= {(str(c), i) for i in cats_cfg.training_instances(str(c))}
        held_out = np.array([(str(c), int(i)) not in train_split
                             for c, i in zip(data.category, data.instance, strict=True)])
        mask = (data.primitive == primitive) & held_out[data.obs_index]
        self.data = data.subset(mask)
        self.train_cats = tuple(dict.fromkeys(aff_cats + sim_cats))
        cats = self.data.interaction_category
        self.groups = {"caff": np.isin(cats, aff_cats),
                       "csim": np.isin(cats, [c for c in sim_cats if c not in aff_cats]),
                       "novel": ~np.isin(cats, self.train_cats)}
        self.groups = {k: v for k, v in self.groups.items() if v.any()}
        self.by_cat = {c: cats == c for c in self.train_cats if (cats == c).any()}
        if not self.by_cat:
            raise ValueError("validation data holds no held-out instances of the training "
                             f"categories {', '.join(self.train_cats)}: collect some with "
                             "`w2e collect --split test --categories ...`")

    def describe(self) -> str:
        return ", ".join(f"{k} {int(v.sum())}" for k, v in self.groups.items()) + \
            f" interactions on {self.data.num_observations} clouds"

    def run(self, model: W2EModel) -> dict[str, float]:
        aff, sim = predict_interactions(model, self.data)
        y, valid = self.data.success, self.data.valid
        correct = (aff > 0.5) == y
        out: dict[str, float] = {}
        for g, m in self.groups.items():
            for tag, mm in (("", m), ("valid_", m & valid)):
                met = classification_metrics(aff[mm], y[mm])
                for k in ("fscore", "auroc", "ap"):
                    out[f"{g}_{tag}{k}"] = met[k]
            out[f"{g}_simcorr_auroc"] = auroc(sim[m], correct[m])
            # what the similarity must beat: the affordance head's own confidence
            out[f"{g}_confidence_simcorr_auroc"] = auroc(np.abs(aff[m] - 0.5), correct[m])
            # ... and within one predicted class, where the prediction alone says nothing
            out[f"{g}_simcorr_within_auroc"] = within_class_auroc(sim[m], correct[m],
                                                                  aff[m] > 0.5)
            out[f"{g}_confidence_simcorr_within_auroc"] = within_class_auroc(
                np.abs(aff[m] - 0.5), correct[m], aff[m] > 0.5)
            out[f"{g}_sim_mean"] = float(sim[m].mean())
        per_cat = [auroc(aff[m], y[m]) for m in self.by_cat.values()]
        out["score"] = float(np.nanmean(per_cat)) if np.isfinite(per_cat).any() else 0.0
        return out
