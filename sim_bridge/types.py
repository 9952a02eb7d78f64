"""Plain data passed between the simulator, the learning core and the ROS nodes.

These types are the contract of the SAPIEN world: the core and the nodes only ever see
them, never SAPIEN objects, so a real robot adapter can produce the same values.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PRIMITIVES: tuple[str, ...] = ("push", "pull", "push-left", "push-up", "pull-left", "pull-up")
"""Primitive names. The learned models cover the base primitives ``push`` and ``pull``."""


@dataclass(frozen=True)
class Action:
    """One interaction: contact point, gripper frame and primitive (DESIGN §3).

    ``up`` is the approach direction (into the surface), ``forward`` the gripper
    orientation about it; both unit vectors, orthogonal, in the world frame.
    """

    point: np.ndarray  # (3,)
    up: np.ndarray  # (3,)
    forward: np.ndarray  # (3,)
    primitive: str = "push"


@dataclass
class Observation:
    """A partial point cloud of one or more objects as the camera sees them."""

    points: np.ndarray  # (N, 3) float32, world frame
    normals: np.ndarray  # (N, 3) float32, unit, facing the camera
    link_ids: np.ndarray  # (N,) int32, index into ObjectModel.links (-1: none)
    movable: np.ndarray  # (N,) bool, point lies on a part with a movable joint (ground truth)
    object_ids: np.ndarray  # (N,) int32, which object of the scene the point belongs to
    camera_pose: np.ndarray  # (4, 4) camera-to-world, x forward, y left, z up (SAPIEN convention)


@dataclass
class TrialResult:
    """What one executed interaction did to the object."""

    valid: bool  # False: contact at the first step, or a push touching a non-target part
    success: bool  # valid and the part moved enough (and, for pull, in the right direction)
    motion: np.ndarray  # (J,) change of every movable joint (m or rad)
    moved_joint: int  # index of the joint that moved most, -1 if none moved
    moved_link: str  # name of the child link of that joint ("" if none)
    reason: str = ""  # why a trial is invalid or failed; empty on success
    contact_displacement: np.ndarray = field(default_factory=lambda: np.zeros(3))
    target_joint: int = -1  # index (qpos order) of the joint moving the touched part, -1: none
    target_link: str = ""  # name of the link the contact point lies on
