"""A model-free familiarity: how much a contact's neighbourhood looks like the training
contacts' neighbourhoods.

Why it exists: the similarity head rates the categories the affordance model ranks upside
down (bucket, kettle) as familiar (bench/RESEARCH.md, "No label-free signal of the model sees
which novel categories it gets wrong"), while this descriptor's k-NN closeness to the
training contacts follows the model's per-category AUROC for every model measured (Spearman
+0.39 to +0.72, ``bench/novelty_probe.py``). The descriptor: per radius (3 / 6 / 12 cm) the
linearity, planarity and scattering of the local covariance around the contact point, then
the point's normal and the action's approach direction (15 numbers). Closeness is minus the
mean distance to the k nearest bank descriptors, each dimension standardised by the bank.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from w2e_ros.core.dataset.interactions import InteractionData

RADII = (0.03, 0.06, 0.12)  # m; the clouds' median point spacing is 23 mm
DIM = 3 * len(RADII) + 6


def local_shape(points: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(len(index), 3 x radii) linearity, planarity, scattering of the covariance of the
    cloud's points within each radius of ``points[index]`` (0 where fewer than 4 points)."""
    pts = np.asarray(points, np.float64)
    tree = cKDTree(pts)
    out = np.zeros((len(index), 3 * len(RADII)), np.float32)
    centres = pts[np.asarray(index, np.int64)]
    for i, r in enumerate(RADII):
        for row, nb in enumerate(tree.query_ball_point(centres, r)):
            if len(nb) < 4:
                continue
            ev = np.sort(np.linalg.eigvalsh(np.cov(pts[nb].T)))[::-1].clip(min=0) + 1e-12
            out[row, 3 * i:3 * i + 3] = ((ev[0] - ev[1]) / ev[0], (ev[1] - ev[2]) / ev[0],
                                         ev[2] / ev[0])
    return out


def describe(points: np.ndarray, normals: np.ndarray, point_index: np.ndarray,
             up: np.ndarray) -> np.ndarray:
    """(C, 15) descriptors of C actions on one cloud (the shape is computed once per point)."""
    point_index = np.asarray(point_index, np.int64)
    uniq, inv = np.unique(point_index, return_inverse=True)
    out = np.empty((len(point_index), DIM), np.float32)
    out[:, :-6] = local_shape(points, uniq)[inv.reshape(-1)]
    out[:, -6:-3] = np.asarray(normals, np.float32)[point_index]
    out[:, -3:] = np.asarray(up, np.float32)
    return out


def describe_data(data: InteractionData) -> np.ndarray:
    """(K, 15) descriptors of every interaction of a collection."""
    out = np.zeros((data.num_interactions, DIM), np.float32)
    for o in range(data.num_observations):
        rows = np.flatnonzero(data.obs_index == o)
        if len(rows):
            out[rows] = describe(data.points[o], data.normals[o], data.point_index[rows],
                                 data.up[rows])
    return out


def knn_closeness(query: torch.Tensor | np.ndarray, bank: torch.Tensor | np.ndarray,
                  k: int) -> np.ndarray:
    """Minus the mean distance to the k nearest bank rows, per dimension, in the bank's
    standardised units (higher = more familiar)."""
    q, b = torch.as_tensor(query, dtype=torch.float32), torch.as_tensor(bank,
                                                                         dtype=torch.float32)
    mu, sd = b.mean(0), b.std(0) + 1e-6
    q, b = (q - mu) / sd, (b - mu) / sd
    k = min(k, len(b))
    out = [-torch.cdist(q[s:s + 1024], b).topk(k, dim=1, largest=False).values.mean(1)
           / np.sqrt(q.shape[1]) for s in range(0, len(q), 1024)]
    return torch.cat(out).numpy() if out else np.zeros(0, np.float32)


@dataclass
class GeometryFamiliarity:
    """The training contacts' descriptors (the bank) and the closeness of new actions to it."""

    bank: np.ndarray  # (B, 15)
    k: int = 16

    @classmethod
    def from_data(cls, data: InteractionData, rows: int = 20000, k: int = 16,
                  seed: int = 0) -> GeometryFamiliarity:
        """A bank of about ``rows`` valid interactions from whole observations drawn at
        random (the training collection of the model's categories, or its replay pack)."""
        valid = data.subset(data.valid.astype(bool))
        if not valid.num_interactions:
            raise ValueError("the geometric familiarity needs valid training interactions; "
                             "the collection given has none")
        per_obs = max(valid.num_interactions / max(valid.num_observations, 1), 1.0)
        n = min(valid.num_observations, int(np.ceil(rows / per_obs)))
        obs = np.random.default_rng(seed).choice(valid.num_observations, n, replace=False)
        return cls(describe_data(valid.subset(np.isin(valid.obs_index, obs))), k)

    def closeness(self, points: np.ndarray, normals: np.ndarray, point_index: np.ndarray,
                  up: np.ndarray) -> np.ndarray:
        """(C,) closeness of C actions on one cloud to the bank (higher = more familiar)."""
        if not len(point_index):
            return np.zeros(0, np.float32)
        return knn_closeness(describe(points, normals, point_index, up), self.bank, self.k)
