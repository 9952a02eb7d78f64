"""``w2e train``: the affordance and similarity heads trained together (paper §3.2, §3.4).

Where2Explore splits the three training categories: ``C_aff`` (the first) trains the
affordance head with BCE; ``C_sim`` (all three) trains the similarity head against the
affordance head's running accuracy on each interaction (correct / total predictions made on
that interaction so far, the current one included), with soft-target BCE as the reference
code does (L1 as the paper says is a setting). Interactions on the other ``C_sim`` categories
never reach the affordance head or send it gradient through the encoder: their affordance
prediction is made without gradient and is only counted.

Batches are a few clouds x many interactions (grouped by observation): a fixed
share of the clouds from ``C_aff`` (so the affordance head is not starved by the other
``C_sim`` categories), the rest equally per category; per cloud half positives, a quarter
negatives and a quarter flipped-approach copies (``up`` reversed, labelled failure: the
reference's extra negatives, sharing the original's accuracy counter). With validation data
the run is judged every ``val_every`` steps on held-out instances, keeps the best model and
stops when the score has not improved for ``patience`` validations.
Baselines: ``where2act`` (affordance only, all three training categories) and ``fulldata``
(affordance only, all 14 categories).

Under ``torchrun`` (``WORLD_SIZE`` > 1) the same run is data-parallel with PyTorch's
DistributedDataParallel (gloo on CPUs, NCCL on GPUs): every process draws the same global
batch of ``clouds x processes`` clouds and trains on its own ``clouds``; the losses are
weighted by the global row counts and the running-accuracy counters are summed over the
processes, so N processes follow the loss curve of one process with an N times larger batch.
Process 0 writes the run directory.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from w2e_ros.core.actions import encode_rotation
from w2e_ros.core.categories import load_categories
from w2e_ros.core.config import METHODS, ModelConfig, TrainConfig
from w2e_ros.core.data import InteractionData
from w2e_ros.core.metrics import auroc, classification_metrics, within_class_auroc
from w2e_ros.core.model import W2EModel, default_device, load_model, save_model
from w2e_ros.core.predict import predict_interactions

log = logging.getLogger("w2e.train")


def make_deterministic(seed: int) -> None:
    """Same seed => same weights: seed torch and pick deterministic kernels (the backward of
    the feature gather accumulates in a thread-dependent order otherwise)."""
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True, warn_only=True)


def method_categories(method: str, combo: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(categories training the affordance head, categories training the similarity head)."""
    cats = load_categories()
    members = cats.combination(combo)
    if method == "w2e":
        return (members[0],), tuple(members)
    if method == "where2act":
        return tuple(members), ()
    if method == "fulldata":
        return tuple(cats.categories), ()
    raise ValueError(f"unknown method {method!r}; known: {', '.join(METHODS)}")


def retarget(meta: dict, combo: str, source: str = "the model") -> dict:
    """A w2e checkpoint's metadata for another combination with the same C_aff.

    The affordance head of a w2e model trains on C_aff alone, so cfw / csr (cabinet) and
    tfr / tsw (table) can share one; what differs is the similarity, which the caller then
    fits on the new combination's categories (``w2e calibrate --combo``)."""
    method, own = str(meta.get("method", "w2e")), str(meta.get("combo", "cfw"))
    if combo == own:
        return meta
    if method != "w2e":
        raise ValueError(f"{source}: only w2e models can be given another combination (a "
                         f"{method} model's affordance head trains on every category of {own})")
    have, want = method_categories(method, own)[0][0], method_categories(method, combo)[0][0]
    if have != want:
        raise ValueError(f"{source}: trained for {own} (C_aff {have}); {combo} has C_aff "
                         f"{want}: train a model for it (w2e train --combo {combo})")
    return {**meta, "combo": combo, "retargeted_from": own}


@dataclass
class Batch:
    """Interactions grouped by cloud, as tensors on the model's device."""

    clouds: torch.Tensor  # (B, N, 3)
    cloud_of: torch.Tensor  # (K,) long, row in clouds
    point_index: torch.Tensor  # (K,) long
    actions: torch.Tensor  # (K, 6)
    success: torch.Tensor  # (K,) float 0/1
    interaction: np.ndarray  # (K,) int, key of the running-accuracy counters (-1: none)
    aff_mask: torch.Tensor  # (K,) bool, trains the affordance head
    sim_mask: torch.Tensor  # (K,) bool, trains the similarity head
    weight: torch.Tensor | None = None  # (K,) weight of each affordance term (None: 1)

    @staticmethod
    def cat(parts: list[Batch]) -> Batch:
        offsets = np.cumsum([0] + [len(p.clouds) for p in parts[:-1]])
        weight = None
        if any(p.weight is not None for p in parts):
            weight = torch.cat([p.weight if p.weight is not None
                                else torch.ones_like(p.success) for p in parts])
        return Batch(
            clouds=torch.cat([p.clouds for p in parts]),
            cloud_of=torch.cat([p.cloud_of + int(o) for p, o in zip(parts, offsets,
                                                                    strict=True)]),
            point_index=torch.cat([p.point_index for p in parts]),
            actions=torch.cat([p.actions for p in parts]),
            success=torch.cat([p.success for p in parts]),
            interaction=np.concatenate([p.interaction for p in parts]),
            aff_mask=torch.cat([p.aff_mask for p in parts]),
            sim_mask=torch.cat([p.sim_mask for p in parts]),
            weight=weight,
        )


def make_batch(data: InteractionData, rows: np.ndarray, aff_categories: tuple[str, ...],
               sim_categories: tuple[str, ...], device: torch.device,
               key_offset: int = 0, flip: np.ndarray | None = None) -> Batch:
    """Interactions ``rows`` of ``data`` -> a Batch holding each of their clouds once.

    ``flip`` (K,) bool: those rows enter with the approach reversed and labelled failure.
    """
    rows = np.asarray(rows, dtype=np.int64)
    flip = np.zeros(len(rows), bool) if flip is None else np.asarray(flip, bool)
    obs, cloud_of = np.unique(data.obs_index[rows], return_inverse=True)
    cats = data.category[data.obs_index[rows]]
    up = np.where(flip[:, None], -data.up[rows], data.up[rows])
    actions = encode_rotation(up, data.forward[rows])
    success = data.success[rows] & ~flip
    t = lambda a, dt=torch.float32: torch.as_tensor(np.asarray(a), dtype=dt, device=device)  # noqa: E731
    return Batch(
        clouds=t(data.points[obs]),
        cloud_of=t(cloud_of.reshape(-1), torch.long),
        point_index=t(data.point_index[rows], torch.long),
        actions=t(actions),
        success=t(success.astype(np.float32)),
        interaction=rows + key_offset,
        aff_mask=t(np.isin(cats, list(aff_categories)), torch.bool),
        sim_mask=t(np.isin(cats, list(sim_categories)), torch.bool),
    )


def rotate_yaw(batch: Batch, angles: np.ndarray) -> Batch:
    """The batch with cloud ``b`` and the actions on it turned by ``angles[b]`` about the
    vertical axis. Physics is the same under a turn about gravity (the object, the camera and
    the gripper turned together), so every label still holds: an augmentation that adds
    views without simulating them."""
    c, s_ = np.cos(angles), np.sin(angles)
    rot = np.zeros((len(angles), 3, 3), np.float32)
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s_, s_, c, 1.0
    r = torch.as_tensor(rot, device=batch.clouds.device)  # (B, 3, 3)
    clouds = batch.clouds @ r.transpose(1, 2)
    # each action's two vectors (up, forward) as rows, turned with its cloud's rotation
    actions = batch.actions.view(-1, 2, 3) @ r[batch.cloud_of].transpose(1, 2)  # (K, 2, 3)
    return replace(batch, clouds=clouds, actions=actions.reshape(-1, 6))


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


@dataclass
class Shard:
    """This process's part of a data-parallel global batch: what it needs to know of the
    whole (every process draws the same global batch, so no exchange is needed for it)."""

    world: int  # processes
    aff_rows: int  # affordance rows in the global batch
    sim_keys: np.ndarray  # (S,) counter keys of the global batch's similarity rows, in order
    sim_offset: int  # where this process's similarity rows start among them

    def update(self, acc: RunningAccuracy, right: np.ndarray,
               device: torch.device) -> np.ndarray:
        """Count every process's predictions (one all-reduce), as one process with the whole
        batch would; return the running accuracy of this process's rows."""
        full = torch.zeros(len(self.sim_keys), dtype=torch.int64, device=device)
        full[self.sim_offset:self.sim_offset + len(right)] = torch.as_tensor(
            np.asarray(right, np.int64), device=device)
        dist.all_reduce(full)
        rate = acc.update(self.sim_keys, full.cpu().numpy())
        return rate[self.sim_offset:self.sim_offset + len(right)]


@dataclass
class Distributed:
    """This process's place in a ``torchrun`` job (its ``RANK``, ``WORLD_SIZE`` and
    ``LOCAL_RANK``); the default is a single process."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def active(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        """Process 0 writes the run directory and logs."""
        return self.rank == 0

    @staticmethod
    def from_env() -> Distributed:
        """Join the process group ``torchrun`` describes in the environment: NCCL when this
        host has GPUs (one per local rank), gloo on CPUs. No torchrun: a single process."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        if world <= 1:
            return Distributed()
        d = Distributed(int(os.environ["RANK"]), world, int(os.environ.get("LOCAL_RANK", "0")))
        if not dist.is_initialized():
            if torch.cuda.is_available():
                torch.cuda.set_device(d.local_rank)
            dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        return d

    @property
    def device(self) -> torch.device:
        if self.active and torch.cuda.is_available():
            return torch.device("cuda", self.local_rank)
        return default_device()

    def mean(self, stats: dict[str, float], keys: tuple[str, ...]) -> dict[str, float]:
        """``keys`` of ``stats`` averaged over the processes (every process has them)."""
        if not self.active:
            return stats
        t = torch.tensor([stats[k] for k in keys], dtype=torch.float64, device=self.device)
        dist.all_reduce(t)
        return {**stats, **{k: float(v) / self.world for k, v in zip(keys, t.tolist(),
                                                                      strict=True)}}


class _Losses(nn.Module):
    """The model with the loss as its forward: what DDP wraps, so that a forward through
    DDP prepares the gradient all-reduce of the backward that follows."""

    def __init__(self, model: W2EModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, batch: Batch, loss_fn: Callable[..., tuple[torch.Tensor, dict]]
                ) -> tuple[torch.Tensor, dict[str, float]]:
        return loss_fn(self.model, batch)


class BalancedSampler:
    """Batches of ``clouds`` observations x ``per_cloud`` interactions (+ flipped copies).

    ``aff_share`` of the clouds come from ``aff_categories`` (when given and present), the
    rest from the other categories drawn equally; half the clouds come from observations
    that have a positive interaction, and each cloud gives half positives, half negatives
    where it can. ``flip_share`` x ``per_cloud`` of a cloud's negatives are flipped copies
    of its interactions instead of stored failures (the reference's extra negatives).
    """

    def __init__(self, data: InteractionData, categories: tuple[str, ...], clouds: int,
                 per_cloud: int, rng: np.random.Generator,
                 aff_categories: tuple[str, ...] = (), aff_share: float = 0.0,
                 flip_share: float = 0.0) -> None:
        self.data, self.clouds, self.per_cloud, self.rng = data, clouds, per_cloud, rng
        self.flip_share = flip_share
        order = np.argsort(data.obs_index, kind="stable")
        bounds = np.searchsorted(data.obs_index[order], np.arange(data.num_observations + 1))
        self.all: list[np.ndarray] = []
        self.pos: list[np.ndarray] = []
        self.neg: list[np.ndarray] = []
        for o in range(data.num_observations):
            rows = order[bounds[o]:bounds[o + 1]]
            self.all.append(rows)
            self.pos.append(rows[data.success[rows]])
            self.neg.append(rows[~data.success[rows]])
        self.by_cat: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for c in categories:
            obs = np.flatnonzero(data.category == c)
            obs = obs[[len(self.all[o]) > 0 for o in obs]]
            if len(obs) == 0:
                continue
            with_pos = obs[[len(self.pos[o]) > 0 for o in obs]]
            self.by_cat[c] = (obs, with_pos)
        if not self.by_cat:
            raise ValueError(f"no interactions of categories {', '.join(categories)} in the "
                             "training data: collect them with `w2e collect`")
        self.categories = tuple(self.by_cat)
        aff = [c for c in self.categories if c in aff_categories]
        rest = [c for c in self.categories if c not in aff_categories]
        # probability of drawing each category for a cloud
        if aff and rest and aff_share > 0:
            p = [aff_share / len(aff) if c in aff else (1 - aff_share) / len(rest)
                 for c in self.categories]
        else:
            p = [1.0 / len(self.categories)] * len(self.categories)
        self.cat_prob = np.asarray(p) / np.sum(p)

    def sample(self) -> tuple[np.ndarray, np.ndarray]:
        """(rows, flip): the interactions of one batch and which of them enter flipped."""
        rng, half = self.rng, self.per_cloud // 2
        cats = rng.choice(len(self.categories), size=self.clouds, p=self.cat_prob)
        rows, flips = [], []
        for i, ci in enumerate(cats):
            obs, with_pos = self.by_cat[self.categories[ci]]
            pool = with_pos if (i % 2 == 0 and len(with_pos)) else obs
            o = int(pool[rng.integers(len(pool))])
            pos, neg = self.pos[o], self.neg[o]
            n_flip = int(round(self.flip_share * self.per_cloud))
            n_pos = half if len(pos) else 0
            n_neg = self.per_cloud - n_pos - n_flip
            if not len(neg):
                n_neg, n_pos = 0, self.per_cloud - n_flip
            for pool_rows, n, flipped in ((pos, n_pos, False), (neg, n_neg, False),
                                          (self.all[o], n_flip, True)):
                if n > 0 and len(pool_rows):
                    rows.append(rng.choice(pool_rows, size=n, replace=len(pool_rows) < n))
                    flips.append(np.full(n, flipped))
        return np.concatenate(rows), np.concatenate(flips)


def load_training_data(data_dir: str | Path, method: str, combo: str, primitive: str,
                       include_invalid: bool = True) -> InteractionData:
    """The train-split interactions of one primitive on the method's training categories."""
    return load_training_data_from(InteractionData.load(data_dir), method, combo, primitive,
                                   include_invalid, source=str(data_dir))


def load_training_data_from(data: InteractionData, method: str, combo: str, primitive: str,
                            include_invalid: bool = True, source: str = "the collection"
                            ) -> InteractionData:
    """:func:`load_training_data` on a collection already in memory."""
    aff, sim = method_categories(method, combo)
    cats = tuple(dict.fromkeys(aff + sim))
    split = load_categories().instances(cats[0], "train")
    sel = data.select(primitive=primitive, categories=cats, instances=split,
                      valid_only=not include_invalid)
    if sel.num_interactions == 0:
        raise ValueError(f"{source}: no {primitive} interactions on train instances of "
                         f"{', '.join(cats)}")
    return sel


def replay_data(data: InteractionData, meta: dict, primitive: str) -> InteractionData:
    """What a few-shot run replays: the train-split interactions of the categories the model
    was trained on (its checkpoint's ``aff_categories`` + ``sim_categories``), one primitive."""
    cats = list(dict.fromkeys(list(meta.get("aff_categories", [])) +
                              list(meta.get("sim_categories", []))))
    cfg = load_categories()
    train_split = cfg.instances(cats[0] if cats else cfg.categories[0], "train")
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


class Trainer:
    """Model + Adam + sampler + running-accuracy counters; checkpoints and resumes."""

    def __init__(self, cfg: TrainConfig, data: InteractionData,
                 model_cfg: ModelConfig | None = None, device: torch.device | None = None,
                 distributed: Distributed | None = None) -> None:
        self.cfg, self.data = cfg, data
        self.dist = distributed or Distributed()
        self.device = device or self.dist.device
        make_deterministic(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.aff_cats, self.sim_cats = method_categories(cfg.method, cfg.combo)
        mcfg = model_cfg or ModelConfig(num_points=int(data.points.shape[1]))
        self.model = W2EModel(mcfg).to(self.device)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr,
                                    weight_decay=cfg.weight_decay)
        self.acc = RunningAccuracy(data.num_interactions)
        # every process draws the same global batch (same seed) and keeps its own clouds
        self.sampler = BalancedSampler(data, tuple(dict.fromkeys(self.aff_cats + self.sim_cats)),
                                       cfg.clouds_per_batch * self.dist.world,
                                       cfg.interactions_per_cloud, self.rng,
                                       self.aff_cats if self.sim_cats else (), cfg.aff_share,
                                       cfg.flip_share)
        self.ddp: nn.Module | None = None
        if self.dist.active:
            from torch.nn.parallel import DistributedDataParallel

            # a step's batch may hold no affordance (or no similarity) rows: unused heads
            self.ddp = DistributedDataParallel(
                _Losses(self.model), find_unused_parameters=True,
                device_ids=[self.device.index] if self.device.type == "cuda" else None)
        self.step = 0
        self.best_score, self.best_step, self.bad_validations = -np.inf, 0, 0
        self.val_scores: list[float] = []  # every validation's score, in order

    def levelled_off(self, patience: int) -> bool:
        """Stop: ``patience`` validations without a new best AND no upward trend over them
        (a noisy curve that still rises can go ``patience`` checks without a new best)."""
        return (self.bad_validations >= patience
                and not still_rising(self.val_scores[-(patience + 1):]))

    @property
    def steps_per_epoch(self) -> int:
        per_step = self.cfg.clouds_per_batch * self.cfg.interactions_per_cloud * self.dist.world
        return max(1, math.ceil(self.data.num_interactions / per_step))

    def next_batch(self) -> Batch:
        rows, flip = self.sampler.sample()
        if self.dist.active:
            raise RuntimeError("data-parallel steps draw their batch in train_step")
        return self._augment(make_batch(self.data, rows, self.aff_cats, self.sim_cats,
                                        self.device, flip=flip))

    def _augment(self, batch: Batch) -> Batch:
        if not self.cfg.augment_yaw:
            return batch
        return rotate_yaw(batch, self.rng.uniform(0.0, 2 * np.pi, len(batch.clouds)))

    def _shard_batch(self) -> tuple[Batch, Shard]:
        """This process's clouds of the global batch (every cloud gives exactly
        ``interactions_per_cloud`` consecutive rows) and what it needs of the rest."""
        rows, flip = self.sampler.sample()
        cats = self.data.category[self.data.obs_index[rows]]
        sim = np.isin(cats, list(self.sim_cats))
        per = self.cfg.clouds_per_batch * self.cfg.interactions_per_cloud
        lo, hi = self.dist.rank * per, (self.dist.rank + 1) * per
        shard = Shard(self.dist.world, int(np.isin(cats, list(self.aff_cats)).sum()),
                      rows[sim], int(sim[:lo].sum()))
        angles = (self.rng.uniform(0.0, 2 * np.pi, self.cfg.clouds_per_batch * self.dist.world)
                  if self.cfg.augment_yaw else None)  # drawn for the global batch: same rng
        batch = make_batch(self.data, rows[lo:hi], self.aff_cats, self.sim_cats, self.device,
                           flip=flip[lo:hi])
        if angles is not None:
            lo = self.dist.rank * self.cfg.clouds_per_batch  # (a cloud drawn twice is one)
            batch = rotate_yaw(batch, angles[lo:lo + len(batch.clouds)])
        return batch, shard

    def learning_rate(self) -> float:
        """The step's learning rate: a function of the step alone, so a resumed run follows
        the schedule it started with (cosine: from ``lr`` down to ``lr_min_scale`` x ``lr``
        at ``steps``; the checkpoints of a constant rate swing 2-5 AUROC points)."""
        cfg = self.cfg
        if cfg.lr_schedule == "constant":
            return cfg.lr
        if cfg.lr_schedule != "cosine":
            raise ValueError(f"unknown lr schedule {cfg.lr_schedule!r} (constant | cosine)")
        t = min(self.step / max(cfg.steps, 1), 1.0)
        return cfg.lr * (cfg.lr_min_scale + (1 - cfg.lr_min_scale) * 0.5 * (1 + math.cos(
            math.pi * t)))

    def train_step(self, batch: Batch | None = None) -> dict[str, float]:
        self.model.train()
        for group in self.opt.param_groups:
            group["lr"] = self.learning_rate()
        if self.ddp is not None:
            if batch is not None:
                raise ValueError("data-parallel steps draw their own batch")
            batch, shard = self._shard_batch()
            loss, stats = self.ddp(batch, lambda m, b: training_losses(
                m, b, self.acc, self.cfg.sim_weight, self.cfg.sim_grad_to_encoder,
                self.cfg.sim_loss, shard))
            stats = self.dist.mean(stats, ("loss", "loss_aff", "loss_sim"))  # the global ones
        else:
            batch = batch if batch is not None else self.next_batch()
            loss, stats = training_losses(self.model, batch, self.acc, self.cfg.sim_weight,
                                          self.cfg.sim_grad_to_encoder, self.cfg.sim_loss)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.step += 1
        return stats

    def meta(self) -> dict:
        return {"method": self.cfg.method, "combo": self.cfg.combo,
                "primitive": self.cfg.primitive, "step": self.step,
                "aff_categories": list(self.aff_cats), "sim_categories": list(self.sim_cats)}

    def save(self, run_dir: Path, best: bool = True) -> None:
        """``state.pt``: the latest weights and everything to resume; with ``best`` also
        ``model.pt``, the model to use (a few MB): the caller passes ``best`` when the current
        weights are the best validated so far, or always when there is no validation.
        Data-parallel: process 0 only (every process holds the same weights)."""
        if not self.dist.main:
            return
        if best:
            save_model(run_dir / "model.pt", self.model,
                       {**self.meta(), "best_score": float(self.best_score)})
        state = {"step": self.step, "optimizer": self.opt.state_dict(),
                 "model": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
                 "acc": self.acc.state(), "rng": json.dumps(self.rng.bit_generator.state),
                 "torch_rng": torch.get_rng_state(), "meta": json.dumps(self.meta()),
                 "best": torch.tensor([self.best_score, self.best_step, self.bad_validations],
                                      dtype=torch.float64),
                 "val_scores": torch.tensor(self.val_scores, dtype=torch.float64)}
        tmp = run_dir / "state.pt.tmp"
        torch.save(state, tmp)
        tmp.replace(run_dir / "state.pt")

    def resume(self, run_dir: Path) -> None:
        state = torch.load(run_dir / "state.pt", map_location=self.device, weights_only=True)
        meta = json.loads(state["meta"])
        for k in ("method", "combo", "primitive"):
            if meta.get(k) != getattr(self.cfg, k):
                raise ValueError(f"{run_dir} holds a {meta.get(k)} run, not {getattr(self.cfg, k)}")
        self.model.load_state_dict(state["model"])
        self.opt.load_state_dict(state["optimizer"])
        self.acc.load(state["acc"])
        self.rng.bit_generator.state = json.loads(state["rng"])
        torch.set_rng_state(state["torch_rng"].cpu())
        self.step = int(state["step"])
        best = state["best"].tolist()
        self.best_score, self.best_step, self.bad_validations = best[0], int(best[1]), int(best[2])
        self.val_scores = state["val_scores"].tolist() if "val_scores" in state else []


def still_rising(scores: Sequence[float]) -> bool:
    """Whether the least-squares slope of ``scores`` (equally spaced validations) is above
    zero by more than its standard error: a trend the noise does not explain."""
    y = np.asarray(scores, dtype=np.float64)
    if len(y) < 3:
        return False
    x = np.arange(len(y), dtype=np.float64) - (len(y) - 1) / 2
    slope = float(x @ (y - y.mean()) / (x @ x))
    resid = y - y.mean() - slope * x
    se = float(np.sqrt(resid @ resid / (len(y) - 2) / (x @ x)))
    return slope > se


def run_name(method: str, combo: str, primitive: str) -> str:
    return f"{method}_{combo}_{primitive}"


def train(cfg: TrainConfig, data_dir: str | Path, out_dir: str | Path, resume: bool = False,
          val_data: InteractionData | None = None, progress: bool = True,
          model_cfg: ModelConfig | None = None) -> Path:
    """Train one model; writes ``model.pt`` (best validated, else last), ``state.pt``,
    ``metrics.jsonl`` and, with validation data, ``curves.png`` into ``out_dir``.

    Under ``torchrun`` every process runs this with the same arguments; each validates the
    (identical) model so all stop together, and process 0 writes and logs."""
    torch.set_num_threads(cfg.threads)
    distributed = Distributed.from_env()
    if not distributed.main:  # a torchrun worker: process 0 speaks for the run
        logging.getLogger("w2e").setLevel(logging.WARNING)
    run_dir = Path(out_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    data = load_training_data(data_dir, cfg.method, cfg.combo, cfg.primitive,
                              cfg.include_invalid)
    trainer, validator = _open_run(cfg, data, run_dir, resume, val_data, model_cfg,
                                   distributed)
    _fit(trainer, validator, run_dir, progress and distributed.main, distributed.main)
    trainer.save(run_dir, best=validator is None)
    if distributed.active:  # the rest is one process's work on the saved model
        dist.destroy_process_group()
        if not distributed.main:
            return run_dir / "model.pt"
    if validator is not None:
        from w2e_ros.core.viz import training_curves

        training_curves(run_dir / "metrics.jsonl", run_dir / "curves.png",
                        title=f"{run_dir.name}: validation on held-out instances")
        log.info("best validation score %.4f at step %d (model.pt)", trainer.best_score,
                 trainer.best_step)
    if trainer.sim_cats and cfg.calibrate_steps <= 0 and cfg.sim_weight == 0:
        log.warning("the similarity head was neither trained (--sim-weight 0) nor calibrated "
                    "(--calibrate-steps 0): its scores are meaningless; run `w2e calibrate`")
    if trainer.sim_cats and cfg.calibrate_steps > 0:
        _calibrate_run(trainer, data, validator, run_dir)
    return run_dir / "model.pt"


def _open_run(cfg: TrainConfig, data: InteractionData, run_dir: Path, resume: bool,
              val_data: InteractionData | None, model_cfg: ModelConfig | None,
              distributed: Distributed) -> tuple[Trainer, Validator | None]:
    """The trainer (resumed from ``run_dir`` if asked) and its validator; writes the run's
    config.json. A resumed run keeps the network it started with, whatever the flags say."""
    if resume and (run_dir / "state.pt").exists() and (run_dir / "config.json").exists():
        model_cfg = ModelConfig.from_dict(json.loads((run_dir / "config.json").read_text())
                                          ["model"])
    elif model_cfg is not None:  # the network's input size is the collection's
        model_cfg = replace(model_cfg, num_points=int(data.points.shape[1]))
    trainer = Trainer(cfg, data, model_cfg, distributed=distributed)
    validator = None
    if val_data is not None:
        validator = Validator(val_data, trainer.aff_cats, trainer.sim_cats, cfg.primitive)
        log.info("validation: %s", validator.describe())
    if resume and (run_dir / "state.pt").exists():
        trainer.resume(run_dir)
        log.info("resumed %s at step %d", run_dir, trainer.step)
    elif distributed.main and (run_dir / "metrics.jsonl").exists():
        (run_dir / "metrics.jsonl").unlink()
    if distributed.main:
        (run_dir / "config.json").write_text(json.dumps(
            {"train": asdict(trainer.cfg), "model": trainer.model.cfg.to_dict(),
             "interactions": data.num_interactions, "observations": data.num_observations,
             "positive_rate": data.positive_rate(), "processes": distributed.world,
             **trainer.meta()}, indent=2))
    log.info("%s: %d interactions on %d clouds (%.0f%% positive), aff=%s sim=%s, up to %d "
             "steps (%d per epoch) on %s x %d", run_dir.name, data.num_interactions,
             data.num_observations, 100 * data.positive_rate(), ",".join(trainer.aff_cats),
             ",".join(trainer.sim_cats) or "-", cfg.steps, trainer.steps_per_epoch,
             trainer.device, distributed.world)
    return trainer, validator


def _fit(trainer: Trainer, validator: Validator | None, run_dir: Path, bar_on: bool,
         main: bool) -> None:
    """Steps until ``cfg.steps`` or until validation levels off; a metrics line every
    ``log_every`` steps, a checkpoint every ``ckpt_every``."""
    cfg = trainer.cfg
    window: list[dict[str, float]] = []
    t0, start = time.perf_counter(), trainer.step
    bar = tqdm(total=cfg.steps, initial=trainer.step, disable=not bar_on, unit="step",
               dynamic_ncols=True)
    stop = validator is not None and trainer.levelled_off(cfg.patience)  # a finished run
    with (run_dir / "metrics.jsonl" if main else Path(os.devnull)).open("a") as mlog:
        while trainer.step < cfg.steps and not stop:
            window.append(trainer.train_step())
            bar.update(1)
            last = trainer.step == cfg.steps
            validate = validator is not None and (trainer.step % cfg.val_every == 0 or last)
            if trainer.step % cfg.log_every == 0 or last or validate:
                rec = {k: float(np.mean([w[k] for w in window if k in w]))
                       for k in window[-1]}
                rate = (trainer.step - start) / (time.perf_counter() - t0)
                rec.update(step=trainer.step, epoch=trainer.step / trainer.steps_per_epoch,
                           steps_per_s=rate, eta_s=(cfg.steps - trainer.step) / rate)
                if validate:
                    stop = _validate(trainer, validator, run_dir, rec)
                mlog.write(json.dumps(rec) + "\n")
                mlog.flush()
                bar.set_postfix(loss=f"{rec['loss']:.3f}", aff=f"{rec.get('aff_acc', 0):.2f}")
                if not bar_on and main:
                    log.info("step %d/%d loss %.4f (aff %.4f sim %.4f) %.2f step/s eta %.0fs",
                             trainer.step, cfg.steps, rec["loss"], rec["loss_aff"],
                             rec["loss_sim"], rate, rec["eta_s"])
                window = []
            if trainer.step % cfg.ckpt_every == 0 or last or stop:
                trainer.save(run_dir, best=validator is None)
    bar.close()


def _validate(trainer: Trainer, validator: Validator, run_dir: Path, rec: dict) -> bool:
    """Score the model on the held-out data, keep it if best; whether to stop now."""
    val = validator.run(trainer.model)
    trainer.val_scores.append(float(val["score"]))
    rec.update({f"val_{k}": v for k, v in val.items()})
    stop = False
    if val["score"] > trainer.best_score:
        trainer.best_score, trainer.best_step = val["score"], trainer.step
        trainer.bad_validations = 0
        trainer.save(run_dir, best=True)
    else:
        trainer.bad_validations += 1
        stop = trainer.levelled_off(trainer.cfg.patience)
    rec.update(best_score=trainer.best_score, best_step=trainer.best_step)
    log.info("step %d validation score %.4f (best %.4f at %d)%s", trainer.step, val["score"],
             trainer.best_score, trainer.best_step, ": levelled off, stopping" if stop else "")
    return stop


def _calibrate_run(trainer: Trainer, data: InteractionData, validator: Validator | None,
                   run_dir: Path) -> None:
    """Re-fit the saved model's similarity head to its affordance head's correctness and
    record the similarity's validation scores before and after."""
    cfg = trainer.cfg
    model, meta = load_model(run_dir / "model.pt", trainer.device)
    before = validator.run(model) if validator is not None else {}
    stats = calibrate_similarity(model, data, trainer.sim_cats, cfg.calibrate_steps,
                                 cfg.seed, balanced=cfg.calibrate_balanced)
    after = validator.run(model) if validator is not None else {}
    for k in ("csim_simcorr_auroc", "novel_simcorr_auroc", "novel_sim_mean",
              "novel_confidence_simcorr_auroc", "novel_simcorr_within_auroc",
              "novel_confidence_simcorr_within_auroc"):
        if k in after:
            stats[f"val_{k}_before"], stats[f"val_{k}"] = before[k], after[k]
    save_model(run_dir / "model.pt", model, {**meta, "calibration": stats})
    (run_dir / "calibration.json").write_text(json.dumps(stats, indent=1))
    log.info("similarity calibrated: %s", ", ".join(f"{k} {v:.3f}" for k, v in stats.items()))


def calibrate_similarity(model: W2EModel, data: InteractionData, sim_cats: tuple[str, ...],
                         steps: int = 2000, seed: int = 0, batch: int = 512,
                         balanced: bool = False) -> dict[str, float]:
    """Re-fit the similarity head to predict whether the FINAL affordance head is right.

    Measured (docs/results.md, issue 8): the jointly trained head, whose target is the running
    accuracy accumulated since step 0, ranked correctness on novel categories below chance
    (AUROC 0.41 push), while a head fitted afterwards to the final head's correctness ranked
    it at 0.66. The encoder and the affordance head stay as they are; the target is the hard
    correct / wrong label with unweighted BCE, so the similarity stays an estimate of the
    probability of being right and the 0.9 bar keeps its meaning.

    ``balanced``: batches draw successes and failures half and half, so the similarity is
    the probability of being right under a 50/50 prior, not the data's: on a pull (7 % of
    training pulls succeed) "predict fail" is right almost everywhere and the plain head
    calls exactly the geometry where successes are missed familiar.
    """
    from w2e_ros.core.predict import FEATURES, encoder_key

    gen = torch.Generator().manual_seed(seed)
    sel = data.select(categories=sim_cats)
    dev = model.device
    enc = encoder_key(model)
    feats = FEATURES.get(model, enc, list(sel.points))
    f = torch.stack([feats[o][p] for o, p in zip(sel.obs_index.tolist(),
                                                  sel.point_index.tolist(), strict=True)])
    a = torch.from_numpy(encode_rotation(sel.up, sel.forward)).to(dev)
    with torch.no_grad():
        correct = ((model.aff_head(f, a) > 0).cpu().numpy() == sel.success)
    y = torch.from_numpy(correct.astype(np.float32)).to(dev)
    head = model.sim_head
    with torch.no_grad():  # fresh weights: the joint head's ranking is the problem
        for layer in (head.point_fc, head.action_fc, *head.hidden, head.out):
            g = torch.Generator().manual_seed(seed + 1)
            w = torch.empty_like(layer.weight)
            bound = 1.0 / math.sqrt(layer.weight.shape[1])
            layer.weight.copy_(w.uniform_(-bound, bound, generator=g))
            if layer.bias is not None:
                layer.bias.zero_()
    opt = torch.optim.Adam(head.parameters(), lr=1e-3)
    head.train()
    pos = torch.from_numpy(np.flatnonzero(sel.success)).to(dev)
    neg = torch.from_numpy(np.flatnonzero(~sel.success)).to(dev)
    balanced = balanced and len(pos) > 0 and len(neg) > 0
    for _ in range(steps):
        if balanced:
            h = batch // 2
            i = torch.cat([pos[torch.randint(len(pos), (h,), generator=gen).to(dev)],
                           neg[torch.randint(len(neg), (batch - h,), generator=gen).to(dev)]])
        else:
            i = torch.randint(len(y), (batch,), generator=gen).to(dev)
        loss = F.binary_cross_entropy_with_logits(head(f[i], a[i]), y[i])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        sim = torch.sigmoid(head(f, a)).cpu().numpy()
    return {"rows": float(len(y)), "train_correct_rate": float(correct.mean()),
            "train_simcorr_auroc": auroc(sim, correct), "final_loss": float(loss.detach())}


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
            train_split |= {(str(c), i) for i in cats_cfg.instances(str(c), "train")}
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
