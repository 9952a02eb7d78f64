"""Interactions grouped by cloud, as the model trains on them: a few clouds x many
interactions, each cloud held once; and the turn about the vertical that augments them."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.robot.actions import encode_rotation


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
