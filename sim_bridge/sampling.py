"""Random actions on an observation, for tests and quick checks (not the learner's sampler)."""

from __future__ import annotations

import numpy as np

from sim_bridge.types import Observation
from w2e_ros.core.robot.primitives import Action


def random_direction_against(normal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A uniform unit vector in the hemisphere opposite ``normal`` (dot(up, normal) < 0)."""
    while True:
        v = rng.normal(size=3)
        n = np.linalg.norm(v)
        if n > 1e-6 and abs(v @ normal) > 1e-3 * n:
            v /= n
            return -v if v @ normal > 0 else v


def random_perpendicular(up: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A uniform unit vector perpendicular to ``up``."""
    while True:
        v = rng.normal(size=3)
        v -= (v @ up) * up
        n = np.linalg.norm(v)
        if n > 1e-6:
            return v / n


def random_action(
    obs: Observation, rng: np.random.Generator, primitive: str = "push", movable_only: bool = True
) -> tuple[Action, int]:
    """A random (point, up, forward) on the cloud; returns the action and the point's row."""
    rows = np.flatnonzero(obs.movable) if movable_only else np.arange(len(obs.points))
    if len(rows) == 0:
        raise ValueError("observation has no (movable) points")
    i = int(rng.choice(rows))
    normal = obs.normals[i].astype(float)
    up = random_direction_against(normal, rng)
    forward = random_perpendicular(up, rng)
    return Action(obs.points[i].astype(float), up, forward, primitive), i
