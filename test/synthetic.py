"""A small learnable stand-in for collected data, for tests that must not wait on the simulator.

Each cloud is a noisy box with a 'handle' patch; an action succeeds when its point lies on
the handle and it approaches roughly along -z. The affordance is learnable from geometry and
direction, as in the real data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.robot.primitives import Action, TrialResult


def synthetic_data(categories=("cabinet", "faucet", "window"), obs_per_cat: int = 4,
                   per_obs: int = 24, num_points: int = 256, primitive: str = "push",
                   seed: int = 0, instance_start: int = 0) -> InteractionData:
    rng = np.random.default_rng(seed)
    pts, nrm, mov, cat, inst, obs_index, pidx, up, fwd, succ = ([] for _ in range(10))
    M = 0
    for ci, c in enumerate(categories):
        for j in range(obs_per_cat):
            p = rng.uniform(-0.5, 0.5, size=(num_points, 3)).astype(np.float32)
            p[:, 2] = 0.5 * (ci % 2)  # a flat front face whose height depends on the category
            handle = p[:, 0] > 0.2 + 0.05 * ci
            p[handle, 2] += 0.08  # the handle sticks out
            n = np.zeros_like(p)
            n[:, 2] = 1.0
            pts.append(p)
            nrm.append(n)
            mov.append(handle)
            cat.append(c)
            inst.append(instance_start + j)
            k = rng.integers(0, num_points, size=per_obs)
            k[: per_obs // 2] = rng.choice(np.flatnonzero(handle), per_obs // 2)
            u = rng.normal(size=(per_obs, 3))
            u[:, 2] = -np.abs(u[:, 2]) * rng.uniform(0.2, 3.0, size=per_obs)[:]
            u /= np.linalg.norm(u, axis=1, keepdims=True)
            f = np.cross(u, [1.0, 0.0, 0.0])
            f /= np.linalg.norm(f, axis=1, keepdims=True)
            obs_index.append(np.full(per_obs, M))
            pidx.append(k)
            up.append(u)
            fwd.append(f)
            succ.append(handle[k] & (u[:, 2] < -0.7))
            M += 1
    K = M * per_obs
    return InteractionData(
        points=np.stack(pts), normals=np.stack(nrm), movable=np.stack(mov),
        category=np.array(cat), instance=np.array(inst, np.int32),
        state=np.zeros((M, 1), np.float32), obs_seed=np.arange(M, dtype=np.int64),
        camera_pose=np.tile(np.eye(4, dtype=np.float32), (M, 1, 1)),
        obs_index=np.concatenate(obs_index).astype(np.int32),
        point_index=np.concatenate(pidx).astype(np.int32),
        up=np.concatenate(up).astype(np.float32), forward=np.concatenate(fwd).astype(np.float32),
        primitive=np.full(K, primitive), motion=np.concatenate(succ).astype(np.float32) * 0.05,
        valid=np.ones(K, bool), success=np.concatenate(succ), trial_seed=np.arange(K),
    )


@dataclass
class Cloud:
    points: np.ndarray
    normals: np.ndarray
    movable: np.ndarray


class RuleWorld:
    """The synthetic data's own rule as a world: push the handle straight in to move it."""

    def __init__(self, data):
        self.data = data
        self.executed: list[tuple[int, Action]] = []

    def observe(self, target: int) -> Cloud:
        d = self.data
        return Cloud(d.points[target], d.normals[target], d.movable[target])

    def execute(self, target: int, action: Action) -> TrialResult:
        self.executed.append((target, action))
        i = int(np.argmin(np.linalg.norm(self.data.points[target] - action.point, axis=1)))
        ok = bool(self.data.movable[target, i] and action.up[2] < -0.7)
        return TrialResult(valid=True, success=ok, motion=np.array([0.05 * ok]),
                           moved_joint=0 if ok else -1, moved_link="")
