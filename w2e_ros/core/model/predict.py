"""Model predictions on stored interactions: one encoder pass per cloud, heads per row.

Kept apart from ``evaluate`` (which needs the exploration loop's candidate sampling) so that
training can validate without importing the loop.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np
import torch

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.robot.actions import encode_rotation


def cloud_key(points: np.ndarray) -> str:
    """Content key of a cloud: the same points give the same cached features."""
    a = np.ascontiguousarray(points, dtype=np.float32)
    return hashlib.sha1(a.tobytes()).hexdigest()


def encoder_key(model: W2EModel) -> str:
    """Content key of the encoder's weights (features depend on nothing else)."""
    h = hashlib.sha1()
    for t in model.encoder.state_dict().values():
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


class FeatureCache:
    """Per-cloud encoder features, keyed by (encoder weights, cloud content).

    Shared between explorers and evaluations of one base model: with a frozen encoder a
    cloud is encoded once per process, however many methods, seeds and budgets use it.
    """

    def __init__(self, max_clouds: int = 2048) -> None:
        self.max_clouds = max_clouds
        self._store: dict[tuple[str, str], torch.Tensor] = {}

    @torch.no_grad()
    def get(self, model: W2EModel, enc: str, points: Sequence[np.ndarray]) -> list[torch.Tensor]:
        keys = [(enc, cloud_key(p)) for p in points]
        # held here, so that evicting while storing never drops a cloud of this request
        out = {i: self._store[k] for i, k in enumerate(keys) if k in self._store}
        todo = [i for i in range(len(keys)) if i not in out]
        model.eval()
        for s in range(0, len(todo), 16):
            idx = todo[s:s + 16]
            pts = torch.from_numpy(np.stack([np.asarray(points[i], np.float32) for i in idx]))
            feats = model.encode(pts.to(model.device))
            for j, i in enumerate(idx):
                if len(self._store) >= self.max_clouds:
                    self._store.pop(next(iter(self._store)))
                self._store[keys[i]] = out[i] = feats[j]
        return [out[i] for i in range(len(keys))]


FEATURES = FeatureCache()


@torch.no_grad()
def encode_clouds(model: W2EModel, points: np.ndarray, chunk: int = 16) -> torch.Tensor:
    """(M, N, 3) clouds -> (M, N, F) encoder features on the model's device."""
    model.eval()
    out = []
    for s in range(0, len(points), chunk):
        pts = torch.from_numpy(np.ascontiguousarray(points[s:s + chunk], np.float32))
        out.append(model.encode(pts.to(model.device)))
    if not out:
        return torch.zeros(0, points.shape[1], model.cfg.feat_dim, device=model.device)
    return torch.cat(out)


@torch.no_grad()
def predict_interactions(model: W2EModel, data: InteractionData, chunk: int = 16,
                         cache: FeatureCache | None = FEATURES
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(K,) affordance probabilities and (K,) similarities, one encoder pass per cloud
    (none at all for clouds whose features ``cache`` holds for this encoder)."""
    model.eval()
    aff = np.zeros(data.num_interactions, np.float32)
    sim = np.zeros(data.num_interactions, np.float32)
    order = np.argsort(data.obs_index, kind="stable")
    obs_sorted = data.obs_index[order]
    dev = model.device
    enc = encoder_key(model) if cache is not None else ""
    for s in range(0, data.num_observations, chunk):
        lo, hi = np.searchsorted(obs_sorted, [s, s + chunk])
        rows = order[lo:hi]
        if not len(rows):
            continue
        pts = data.points[s:s + chunk]
        if cache is not None:
            feats = torch.stack(cache.get(model, enc, list(pts)))
        else:
            feats = encode_clouds(model, pts, chunk)
        f = feats[torch.from_numpy(data.obs_index[rows] - s).long().to(dev),
                  torch.from_numpy(data.point_index[rows]).long().to(dev)]
        a = torch.from_numpy(encode_rotation(data.up[rows], data.forward[rows])).to(dev)
        logit, similarity = model.heads(f, a)
        aff[rows] = torch.sigmoid(logit).cpu().numpy()
        sim[rows] = similarity.cpu().numpy()
    return aff, sim
