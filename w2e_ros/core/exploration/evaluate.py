"""``w2e evaluate``: affordance F-score on held-out interactions and sample success rate.

F-score: every interaction of a test collection (unseen TEST instances of the novel
categories) is predicted from its observation; ``sigmoid(aff) > 0.5`` vs the success label,
pooled counts (``metrics.fscore``). Sample success: per test object, sample actions, execute
the one with the highest affordance in the simulator, report the fraction that succeed.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.exploration.explore import Candidates, map_candidates, sample_candidates
from w2e_ros.core.model.metrics import affordance_fscore_from_probs, success_rate
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.model.policy import ManipulatePolicy, score_actions
from w2e_ros.core.model.predict import FEATURES, encoder_key, predict_interactions
from w2e_ros.core.robot.feasibility import DEFAULT_CHECK, FLYING

log = logging.getLogger("w2e.evaluate")


def affordance_fscore(model: W2EModel, data: InteractionData) -> dict[str, float]:
    """Pooled F-score of the model on every interaction of ``data``."""
    aff, _ = predict_interactions(model, data)
    return affordance_fscore_from_probs(aff, data.success)


def fscore_by_category(model: W2EModel, data: InteractionData) -> dict[str, dict[str, float]]:
    """Per category, plus ``all`` (pooled over the categories) and ``mean`` (of categories)."""
    aff, _ = predict_interactions(model, data)
    cats = data.interaction_category
    out = {str(c): affordance_fscore_from_probs(aff[cats == c], data.success[cats == c])
           for c in np.unique(cats)}
    per_cat = [v["fscore"] for v in out.values()]
    out["all"] = affordance_fscore_from_probs(aff, data.success)
    out["mean"] = {"fscore": float(np.mean(per_cat)) if per_cat else float("nan")}
    return out


PROBE_SAMPLERS = ("proposal", "maps")


@dataclass
class SuccessProbe:
    """Test objects with fixed candidate actions, so every model is judged on the same
    actions, and executed outcomes cached (the simulator is deterministic per target).

    ``sampler`` says where the candidates come from: ``proposal`` (the distribution the
    training data and the exploration are drawn from, on the movable parts when
    ``use_mask``), or ``maps`` (what the stack's ``manipulate`` scores: every point of the
    movable parts x ``dirs_per_point`` frames uniform over the hemisphere; the reference's
    argmax of affordance x movable mask). The model's action is the stack's manipulate
    policy (:class:`w2e_ros.core.model.policy.ManipulatePolicy`): its best one; with
    ``check_approach`` the best of its ``approach_candidates`` highest whose approach does not
    run into the observed cloud (none clear: the object is not touched and counts as a
    failure).
    """

    world: Any  # ExplorationWorld
    targets: list[Any]
    primitive: str
    points_per_object: int = 256
    dirs_per_point: int = 8
    seed: int = 0
    use_mask: bool = True
    sampler: str = "proposal"  # proposal | maps
    check_approach: bool = False
    approach_candidates: int = 256

    def __post_init__(self) -> None:
        if self.sampler not in PROBE_SAMPLERS:
            raise ValueError(f"sampler must be one of {PROBE_SAMPLERS}, got {self.sampler!r}")
        rng = np.random.default_rng(self.seed)
        self.clouds = [self.world.observe(t) for t in self.targets]
        masks = [getattr(c, "movable", None) if self.use_mask else None for c in self.clouds]
        self.candidates: list[Candidates] = [
            sample_candidates(c, self.points_per_object, self.dirs_per_point, rng, m)
            if self.sampler == "proposal" else map_candidates(c, self.dirs_per_point, rng, m)
            for c, m in zip(self.clouds, masks, strict=True)]
        self._outcomes: dict[tuple[int, int], tuple[bool, bool]] = {}

    @property
    def policy(self) -> ManipulatePolicy:
        """The stack's manipulate policy with the flying hand (``w2e_ros.core.model.policy``)."""
        return ManipulatePolicy(DEFAULT_CHECK if self.check_approach else None, FLYING,
                                self.approach_candidates)

    @torch.no_grad()
    def outcomes(self, model: W2EModel) -> list[tuple[bool, bool]]:
        """(success, valid) of the action the policy picks on every target, in order."""
        model.eval()
        enc = encoder_key(model)
        feats = FEATURES.get(model, enc, [c.points for c in self.clouds])
        policy = self.policy
        out = []
        for k, (t, cloud, cand) in enumerate(zip(self.targets, self.clouds, self.candidates,
                                                 strict=True)):
            logit, _ = score_actions(model, feats[k], cand.point_index, cand.up, cand.forward,
                                     similarity=False)
            i = policy.pick(logit.cpu().numpy(), cloud.points, cand.point_index, cand.up,
                            cand.forward, self.primitive)
            if i < 0:  # the stack leaves such an object untouched: a failure
                out.append((False, False))
                continue
            if (k, i) not in self._outcomes:
                res = self.world.execute(t, cand.action(cloud, i, self.primitive))
                self._outcomes[(k, i)] = (bool(res.success), bool(res.valid))
            out.append(self._outcomes[(k, i)])
        return out

    def run(self, model: W2EModel) -> dict[str, float]:
        """Success rate per category (and ``all`` / ``mean``) of the highest-affordance action."""
        by_cat: dict[str, list[bool]] = defaultdict(list)
        for t, (ok, _) in zip(self.targets, self.outcomes(model), strict=True):
            by_cat[str(getattr(t, "category", "all"))].append(ok)
        out = {c: success_rate(v) for c, v in by_cat.items()}
        out["all"] = success_rate([x for v in by_cat.values() for x in v])
        out["mean"] = float(np.mean([out[c] for c in by_cat])) if by_cat else float("nan")
        return out


def evaluation_targets(categories: Sequence[str], per_category: int, state_seeds: int = 1,
                       validate: bool = False, explored: int = 10) -> list[Any]:
    """The first ``per_category`` evaluation instances of each category (x start states)."""
    from w2e_ros.core.dataset.categories import load_categories
    from w2e_ros.core.dataset.targets import Target

    cats = load_categories()
    return [Target(c, i, s) for c in categories
            for i in cats.evaluation_instances(c, validate, explored)[:per_category]
            for s in range(state_seeds)]


def evaluate(model: W2EModel, test_data: InteractionData | None,
             probe: SuccessProbe | None) -> dict[str, Any]:
    """Both metrics of one model: {"fscore": {cat: {...}}, "success": {cat: rate}}."""
    out: dict[str, Any] = {}
    if test_data is not None and test_data.num_interactions:
        out["fscore"] = fscore_by_category(model, test_data)
    if probe is not None:
        out["success"] = probe.run(model)
    return out
