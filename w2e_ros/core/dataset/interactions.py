"""Interaction data grouped by observation, and its on-disk shard format.

One observed cloud (instance, start state, camera) carries many interactions and is stored
once: the encoder runs once per cloud and the heads read the features at each interaction's
contact point.

Shard format (``<dir>/shard-XXXXX.npz``, written atomically, ``np.load`` without pickle):

==============  ==============  ============================================================
key             shape / dtype   meaning
==============  ==============  ============================================================
points          (M, N, 3) f4    FPS-downsampled partial cloud, world frame
normals         (M, N, 3) f4    unit normals, facing the camera
movable         (M, N) bool     point lies on a movable part (ground truth, evaluation only)
category        (M,) str        object category
instance        (M,) i4         instance id (see config/categories.yaml for the splits)
state           (M, J) f4       joint positions of the observed start state (NaN padded)
obs_seed        (M,) i8         seed of the observation (start state and camera)
camera_pose     (M, 4, 4) f4    camera-to-world pose
obs_index       (K,) i4         row of the interaction's observation in this shard
point_index     (K,) i4         contact point = points[obs_index, point_index]
up, forward     (K, 3) f4       gripper frame: approach direction and orientation
primitive       (K,) str        push | pull (or a -left / -up variant)
motion          (K,) f4         motion of the target part's joint (m or rad)
valid, success  (K,) bool       trial validity and the success label
trial_seed      (K,) i8         seed the simulator ran the trial with
meta            () str          JSON: format version, collection settings
==============  ==============  ============================================================
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

FORMAT_VERSION = 1
OBS_KEYS = ("points", "normals", "movable", "category", "instance", "state", "obs_seed",
            "camera_pose")
INTERACTION_KEYS = ("obs_index", "point_index", "up", "forward", "primitive", "motion",
                    "valid", "success", "trial_seed")


@dataclass
class InteractionData:
    """Observations (M rows) and the interactions (K rows) that refer to them."""

    points: np.ndarray
    normals: np.ndarray
    movable: np.ndarray
    category: np.ndarray
    instance: np.ndarray
    state: np.ndarray
    obs_seed: np.ndarray
    camera_pose: np.ndarray
    obs_index: np.ndarray
    point_index: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    primitive: np.ndarray
    motion: np.ndarray
    valid: np.ndarray
    success: np.ndarray
    trial_seed: np.ndarray
    meta: dict = field(default_factory=dict)

    # ---- sizes ---------------------------------------------------------------------------
    @property
    def num_observations(self) -> int:
        return len(self.points)

    @property
    def num_interactions(self) -> int:
        return len(self.obs_index)

    def __len__(self) -> int:
        return self.num_interactions

    @property
    def interaction_category(self) -> np.ndarray:
        """(K,) category of every interaction."""
        return self.category[self.obs_index]

    @property
    def contact_points(self) -> np.ndarray:
        """(K, 3) contact point of every interaction."""
        return self.points[self.obs_index, self.point_index]

    # ---- subsets -------------------------------------------------------------------------
    def subset(self, interactions: np.ndarray) -> InteractionData:
        """Keep the given interactions (bool mask or indices) and only their observations."""
        idx = np.arange(self.num_interactions)[interactions]
        keep_obs, new_obs_index = np.unique(self.obs_index[idx], return_inverse=True)
        kw = {k: getattr(self, k)[keep_obs] for k in OBS_KEYS}
        kw.update({k: getattr(self, k)[idx] for k in INTERACTION_KEYS})
        kw["obs_index"] = new_obs_index.astype(np.int32)
        return InteractionData(**kw, meta=dict(self.meta))

    def select(
        self,
        primitive: str | None = None,
        categories: list[str] | tuple[str, ...] | None = None,
        instances: list[int] | range | None = None,
        valid_only: bool = False,
    ) -> InteractionData:
        """Interactions of one primitive / some categories / some instances, re-indexed."""
        mask = np.ones(self.num_interactions, dtype=bool)
        if primitive is not None:
            mask &= self.primitive == primitive
        if categories is not None:
            mask &= np.isin(self.interaction_category, list(categories))
        if instances is not None:
            mask &= np.isin(self.instance[self.obs_index], list(instances))
        if valid_only:
            mask &= self.valid
        return self.subset(mask)

    @staticmethod
    def concat(parts: list[InteractionData]) -> InteractionData:
        parts = [p for p in parts if p.num_observations]
        if not parts:
            return empty_data()
        width = max(p.state.shape[1] for p in parts)
        kw: dict[str, np.ndarray] = {}
        for k in OBS_KEYS + INTERACTION_KEYS:
            arrays = [getattr(p, k) for p in parts]
            if k == "state":
                arrays = [_pad_cols(a, width) for a in arrays]
            if k == "obs_index":
                offsets = np.cumsum([0] + [p.num_observations for p in parts[:-1]])
                arrays = [a + o for a, o in zip(arrays, offsets, strict=True)]
            if k in ("category", "primitive"):
                arrays = [a.astype(str) for a in arrays]
            kw[k] = np.concatenate(arrays)
        return InteractionData(**kw, meta=dict(parts[0].meta))

    def positive_rate(self) -> float:
        return float(self.success.mean()) if self.num_interactions else float("nan")

    # ---- disk ----------------------------------------------------------------------------
    def save_shard(self, path: str | Path) -> Path:
        """Write atomically, so an interrupted collection never leaves a half shard."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        arrays = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "meta"}
        arrays["category"] = arrays["category"].astype(str)
        arrays["primitive"] = arrays["primitive"].astype(str)
        meta = {"format_version": FORMAT_VERSION, **self.meta}
        np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), **arrays)
        os.replace(tmp, path)
        return path

    @staticmethod
    def load_shard(path: str | Path) -> InteractionData:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in OBS_KEYS + INTERACTION_KEYS if k not in z]
            if missing:
                raise ValueError(f"{path}: not a w2e shard (missing {', '.join(missing)})")
            meta = json.loads(str(z["meta"])) if "meta" in z else {}
            if meta.get("format_version", FORMAT_VERSION) != FORMAT_VERSION:
                raise ValueError(f"{path}: shard format {meta.get('format_version')} "
                                 f"is not {FORMAT_VERSION}")
            kw = {k: z[k] for k in OBS_KEYS + INTERACTION_KEYS}
        return InteractionData(**kw, meta=meta)

    @staticmethod
    def load(directory: str | Path) -> InteractionData:
        """All shards under a directory (sub-collections included), in path order."""
        directory = Path(directory)
        shards = sorted(directory.rglob("shard-*.npz"))
        shards = [s for s in shards if not s.name.endswith(".tmp.npz")]
        if not shards:
            raise FileNotFoundError(
                f"no shards in {directory}: run `w2e collect --out {directory}` first")
        return InteractionData.concat([InteractionData.load_shard(s) for s in shards])


def _pad_cols(a: np.ndarray, width: int) -> np.ndarray:
    if a.shape[1] == width:
        return a
    out = np.full((a.shape[0], width), np.nan, dtype=a.dtype)
    out[:, : a.shape[1]] = a
    return out


def empty_data(num_points: int = 0) -> InteractionData:
    f4, i4 = np.float32, np.int32
    return InteractionData(
        points=np.zeros((0, num_points, 3), f4), normals=np.zeros((0, num_points, 3), f4),
        movable=np.zeros((0, num_points), bool), category=np.zeros(0, "<U32"),
        instance=np.zeros(0, i4), state=np.zeros((0, 0), f4), obs_seed=np.zeros(0, np.int64),
        camera_pose=np.zeros((0, 4, 4), f4), obs_index=np.zeros(0, i4),
        point_index=np.zeros(0, i4), up=np.zeros((0, 3), f4), forward=np.zeros((0, 3), f4),
        primitive=np.zeros(0, "<U16"), motion=np.zeros(0, f4), valid=np.zeros(0, bool),
        success=np.zeros(0, bool), trial_seed=np.zeros(0, np.int64),
    )
