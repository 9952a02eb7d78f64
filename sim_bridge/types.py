"""What the simulated camera sees: a partial cloud with the simulator's ground truth.

The primitives contract (``Action``, ``TrialResult``) belongs to the core
(:mod:`w2e_ros.core.robot.primitives`); this observation, with its per-point link, movable and
object labels, exists only in simulation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Observation:
    """A partial point cloud of one or more objects as the camera sees them."""

    points: np.ndarray  # (N, 3) float32, world frame
    normals: np.ndarray  # (N, 3) float32, unit, facing the camera
    link_ids: np.ndarray  # (N,) int32, index into ObjectModel.links (-1: none)
    movable: np.ndarray  # (N,) bool, point lies on a part with a movable joint (ground truth)
    object_ids: np.ndarray  # (N,) int32, which object of the scene the point belongs to
    camera_pose: np.ndarray  # (4, 4) camera-to-world, x forward, y left, z up (SAPIEN convention)
    pixels: np.ndarray  # (N,) int64, row-major index of each point's pixel
