"""The training losses: BCE on the affordance interactions and the similarity's loss to the
affordance head's running accuracy, counted per interaction."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.model.training.batch import Batch

if TYPE_CHECKING:
    from w2e_ros.core.model.training.parallel import Shard


class RunningAccuracy:
    """Per-interaction counters of the affordance head's correct / total predictions."""

    def __init__(self, size: int = 0) -> None:
        self.correct = np.zeros(size, dtype=np.int64)
        self.total = np.zeros(size, dtype=np.int64)

    def _grow(self, size: int) -> None:
        if size > len(self.total):
            pad = size - len(self.total)
            self.correct = np.concatenate([self.correct, np.zeros(pad, np.int64)])
            self.total = np.concatenate([self.total, np.zeros(pad, np.int64)])

    def update(self, keys: np.ndarray, correct: np.ndarray) -> np.ndarray:
        """Count this round's predictions, then return correct / total for each key."""
        keys = np.asarray(keys, dtype=np.int64)
        if len(keys):
            self._grow(int(keys.max()) + 1)
        np.add.at(self.correct, keys, np.asarray(correct, dtype=np.int64))
        np.add.at(self.total, keys, 1)
        return self.correct[keys] / self.total[keys]

    def state(self) -> dict:
        return {"correct": torch.from_numpy(self.correct), "total": torch.from_numpy(self.total)}

    def load(self, state: dict) -> None:
        self.correct = state["correct"].numpy().copy()
        self.total = state["total"].numpy().copy()


def training_losses(model: W2EModel, batch: Batch, acc: RunningAccuracy,
                    sim_weight: float = 1.0, sim_grad_to_encoder: bool = True,
                    sim_loss: str = "bce", shard: Shard | None = None
                    ) -> tuple[torch.Tensor, dict[str, float]]:
    """BCE on the affordance interactions + similarity loss to the running accuracy
    (``bce``: soft-target BCE, ``l1``: absolute error).

    The affordance head (and, through it, the encoder) only sees ``aff_mask`` interactions;
    the other interactions' affordance is predicted without gradient, to count accuracy.
    With ``shard`` (data-parallel: ``batch`` is this process's part of a global batch) each
    mean is weighted so that DDP's average over processes is the global batch's mean, and
    the accuracy counters are updated with every process's predictions.
    """
    feats = model.encode(batch.clouds)  # (B, N, F)
    f = feats[batch.cloud_of, batch.point_index]  # (K, F)
    zero = f.sum() * 0.0
    am, sm = batch.aff_mask, batch.sim_mask
    scale_aff = scale_sim = 1.0
    if shard is not None:
        scale_aff = shard.world * int(am.sum()) / max(shard.aff_rows, 1)
        scale_sim = shard.world * int(sm.sum()) / max(len(shard.sim_keys), 1)
    stats: dict[str, float] = {}
    if bool(am.any()):
        logits = model.aff_head(f[am], batch.actions[am])
        w = batch.weight[am] if batch.weight is not None else None
        loss_aff = F.binary_cross_entropy_with_logits(logits, batch.success[am], weight=w)
        stats["aff_acc"] = float(((logits > 0).float() == batch.success[am]).float().mean())
    else:
        loss_aff = zero
    loss_sim = zero
    if bool(sm.any()):
        with torch.no_grad():  # counted only: no gradient to the affordance head
            pred = model.aff_head(f[sm].detach(), batch.actions[sm]) > 0
            right = (pred.float() == batch.success[sm]).cpu().numpy()
        keys = batch.interaction[sm.cpu().numpy()]
        rate = acc.update(keys, right) if shard is None else shard.update(acc, right, f.device)
        target = torch.as_tensor(rate, dtype=torch.float32, device=f.device)
        fs = f[sm] if sim_grad_to_encoder else f[sm].detach()
        sim_logit = model.sim_head(fs, batch.actions[sm])
        sim = torch.sigmoid(sim_logit)
        if sim_loss == "bce":
            loss_sim = F.binary_cross_entropy_with_logits(sim_logit, target)
        elif sim_loss == "l1":
            loss_sim = F.l1_loss(sim, target)
        else:
            raise ValueError(f"unknown similarity loss {sim_loss!r} (bce | l1)")
        stats["sim_mean"] = float(sim.detach().mean())
        stats["sim_target"] = float(target.mean())
        stats["pred_acc"] = float(right.mean())
    loss_aff, loss_sim = scale_aff * loss_aff, scale_sim * loss_sim
    loss = loss_aff + sim_weight * loss_sim
    stats.update(loss=loss.item(), loss_aff=loss_aff.item(), loss_sim=loss_sim.item(),
                 pos_rate=float(batch.success.mean()))
    return loss, stats
