"""The update guard: what the fine-tuned model serves after a fit (issue 40 item 4, "never
unlearn").

A few explored interactions can leave the model worse than before (in the stack, one seed in
ten ended below its start at budget 2). Every fit still continues from the previous fit's
weights (the *adapted* weights, kept here); the guard only decides which weights the model
then holds, i.e. what is scored, snapshotted and saved:

* ``off``: the adapted weights (as before the guard existed).
* ``average``: ``prior + w (adapted - prior)`` (``guard_weight`` = w), the weight-space mix of
  the trained and the adapted model (WiSE-FT, Wortsman et al., arXiv 2109.01903; the heads
  are fine-tuned from the same weights, so the mix stays in one basin).
* ``accept``: an acceptance check on the explored set. Its interactions are split by cloud
  into ``guard_folds`` folds; for each fold the model is fitted from the prior on the others
  (the same fit, replay and stopping rule) and predicts the held-out fold. The update is kept
  when these out-of-fold predictions have a lower class-balanced log-loss than the prior's
  on the same interactions (``guard_metric="loss"``; ``"auroc"``: a higher AUROC), else the
  model serves the prior. The trial fits leave no trace (weights, Adam state, generator,
  running accuracies restored), so an accepted update is exactly the unguarded one.

The *prior* is the model the explorer was built with (the trained checkpoint, also the L2-SP
anchor), captured in ``W2EExplorer.__init__``.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING

import numpy as np
import torch

from w2e_ros.core.exploration.config import GUARD_METRICS, GUARDS
from w2e_ros.core.model.metrics import auroc

if TYPE_CHECKING:
    from w2e_ros.core.exploration.finetune import Rows, W2EExplorer

def mix(prior: dict[str, torch.Tensor], adapted: dict[str, torch.Tensor],
        w: float) -> dict[str, torch.Tensor]:
    """``prior + w (adapted - prior)`` for every floating tensor (others: the adapted)."""
    return {k: (p + w * (adapted[k] - p)) if p.is_floating_point() else adapted[k].clone()
            for k, p in prior.items()}


def fold_of_rows(cloud: np.ndarray, success: np.ndarray, folds: int,
                 rng: np.random.Generator) -> np.ndarray:
    """(K,) fold of each row: whole clouds to a fold (one object's interactions are judged
    together), those with a success first and round-robin, so the successes spread over the
    folds."""
    clouds = np.unique(cloud)
    has_pos = np.array([success[cloud == c].any() for c in clouds])
    order = np.concatenate([rng.permutation(clouds[has_pos]), rng.permutation(clouds[~has_pos])])
    fold_of_cloud = {int(c): i % folds for i, c in enumerate(order)}
    return np.array([fold_of_cloud[int(c)] for c in cloud], np.int64)


def balanced_log_loss(p: np.ndarray, y: np.ndarray) -> float:
    """Log-loss with positives and negatives weighing half each (the fit's objective)."""
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return 0.5 * float(-np.mean(np.log(p[y])) - np.mean(np.log(1 - p[~y])))


def judge(p_prior: np.ndarray, p_adapted: np.ndarray, y: np.ndarray,
          metric: str) -> tuple[bool, float, float]:
    """Whether the adapted out-of-fold predictions beat the prior's on labels ``y``, and both
    scores. One class only: no ranking to judge, the update is kept (the fit itself then
    trains only the similarity head when nothing succeeded)."""
    if metric not in GUARD_METRICS:
        raise ValueError(f"unknown guard metric {metric!r} ({' | '.join(GUARD_METRICS)})")
    if y.all() or not y.any():
        return True, float("nan"), float("nan")
    if metric == "loss":
        a, b = balanced_log_loss(p_prior, y), balanced_log_loss(p_adapted, y)
        return b < a, a, b
    a, b = auroc(p_prior, y), auroc(p_adapted, y)
    return b > a, a, b


@torch.no_grad()
def _predict(ex: W2EExplorer, rows: Rows) -> np.ndarray:
    f = ex._row_features(rows, grad=False)
    a = torch.from_numpy(rows.action).to(ex.device)
    return torch.sigmoid(ex.model.aff_head(f, a)).cpu().numpy()


def _load(ex: W2EExplorer, state: dict[str, torch.Tensor]) -> None:
    ex.model.load_state_dict({k: v.to(ex.device) for k, v in state.items()})


def out_of_fold(ex: W2EExplorer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Out-of-fold check of the next update: (prior's predictions, adapted ones, labels) on
    the explored interactions that train the affordance head. Everything a fit touches is
    restored afterwards."""
    cfg = ex.cfg
    rows = ex.explored.take(np.flatnonzero(ex.explored.aff))
    keep = (copy.deepcopy(ex.opt.state_dict()), ex.rng.bit_generator.state,
            copy.deepcopy(ex.acc), copy.deepcopy(ex.replay_acc), ex.explored,
            list(ex.fit_log), ex._train_affordance, ex.snapshot())
    y = rows.success.copy()
    p_adapted = np.full(len(rows), np.nan, np.float32)
    try:
        _load(ex, ex.prior)
        p_prior = _predict(ex, rows)
        folds = min(cfg.guard_folds, len(np.unique(rows.cloud)))
        fold = fold_of_rows(rows.cloud, y, folds, np.random.default_rng(len(ex.explored)))
        fresh = copy.deepcopy(keep[0])
        fresh["state"] = {}
        for k in range(folds):
            train, held = rows.take(np.flatnonzero(fold != k)), rows.take(np.flatnonzero(fold == k))
            _load(ex, ex.prior)
            ex.opt.load_state_dict(fresh)  # a fit from the prior, fresh Adam moments
            ex.explored = train
            ex._train_affordance = bool(train.success.any() or
                                        ex.replay_rows.success[ex.replay_rows.aff].any())
            ex._fit()
            p_adapted[fold == k] = _predict(ex, held)
    finally:
        (opt, rng, ex.acc, ex.replay_acc, ex.explored, ex.fit_log, ex._train_affordance,
         weights) = keep
        ex.opt.load_state_dict(opt)
        ex.rng.bit_generator.state = rng
        _load(ex, weights)
    return p_prior, p_adapted, y


def guarded_fit(ex: W2EExplorer) -> dict[str, float]:
    """One update as ``W2EExplorer.fit`` makes it, with the guard of ``ex.cfg.guard``: the fit
    continues from the adapted weights, the model then holds what the guard serves."""
    cfg = ex.cfg
    if cfg.guard not in GUARDS:
        raise ValueError(f"unknown guard {cfg.guard!r} ({' | '.join(GUARDS)})")
    if cfg.guard == "off":
        return ex._fit()
    check: dict[str, float] = {}
    if cfg.guard == "accept":
        p_prior, p_adapted, y = out_of_fold(ex)
        ok, s_prior, s_adapted = judge(p_prior, p_adapted, y, cfg.guard_metric)
        check = {"guard_accepted": float(ok), "guard_prior": s_prior,
                 "guard_adapted": s_adapted}
        for m in GUARD_METRICS:  # both measures, whichever decides (to compare them)
            _, check[f"guard_prior_{m}"], check[f"guard_adapted_{m}"] = judge(
                p_prior, p_adapted, y, m)
    if ex.adapted is not None:  # the previous fit's weights, not what was served
        _load(ex, ex.adapted)
    stats = ex._fit()
    ex.adapted = ex.snapshot()
    if cfg.guard == "average":
        _load(ex, mix(ex.prior, ex.adapted, cfg.guard_weight))
    elif not check["guard_accepted"]:
        _load(ex, ex.prior)
    stats.update(check)
    if ex.fit_log:
        ex.fit_log[-1] = stats
    return stats
