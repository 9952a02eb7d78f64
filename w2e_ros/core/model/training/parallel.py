"""Data-parallel training under ``torchrun`` (``WORLD_SIZE`` > 1), with PyTorch's
DistributedDataParallel (gloo on CPUs, NCCL on GPUs): every process draws the same global
batch of ``clouds x processes`` clouds and trains on its own ``clouds``; the losses are
weighted by the global row counts and the running-accuracy counters are summed over the
processes, so N processes follow the loss curve of one process with an N times larger batch.
Process 0 writes the run directory.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from w2e_ros.core.model.network import W2EModel, default_device
from w2e_ros.core.model.training.batch import Batch
from w2e_ros.core.model.training.losses import RunningAccuracy


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


class LossModule(nn.Module):
    """The model with the loss as its forward: what DDP wraps, so that a forward through
    DDP prepares the gradient all-reduce of the backward that follows."""

    def __init__(self, model: W2EModel) -> None:
        super().__init__()
        self.model = model

    def forward(self, batch: Batch, loss_fn: Callable[..., tuple[torch.Tensor, dict]]
                ) -> tuple[torch.Tensor, dict[str, float]]:
        return loss_fn(self.model, batch)
