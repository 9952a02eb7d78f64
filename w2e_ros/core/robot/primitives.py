"""The primitives contract between the learning core and a robot.

What the core asks a robot to do (an :class:`Action`: contact point, gripper frame and one of
the :data:`PRIMITIVES`), how the wrist moves for it (:func:`schedule`, from the start pose
:data:`PUSH_START` behind the point) and how the outcome is judged (:func:`judge_motion`), and
what comes back (a :class:`TrialResult`). The simulator (``sim_bridge``) and a real-arm
adapter both implement this contract; nothing here imports either, so a robot workstation
without the simulator runs the core and the nodes on it alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PRIMITIVES: tuple[str, ...] = ("push", "pull", "push-left", "push-up", "pull-left", "pull-up")
"""Primitive names. The learned models cover the base primitives ``push`` and ``pull``."""

BASE_PRIMITIVES: tuple[str, ...] = ("push", "pull")

PUSH_START = 0.15  # wrist behind the contact point at the start (m, along -up)
PUSH_END = 0.10  # wrist behind the contact point at the end of the push / approach
SIDE_MOVE = 0.05  # extra move of the -left / -up variants
MOTION_THRESHOLD = 0.01  # success needs |motion| > 0.01 (m or rad)
RANGE_FRACTION = 0.5  # ... or |motion| / range > 0.5
PULL_COSINE = 0.5  # pull: contact point must move along -up

# The hand's collision shapes (a Panda-size hand), wrist-relative in the gripper frame
# [forward, left, up], metres. The simulator builds its flying gripper from these
# (sim_bridge.physics) and the approach check (w2e_ros.core.robot.feasibility) sweeps them; a real
# hand of another size changes them here.
FINGER_JOINT_Z = 0.0584  # finger joints ahead of the wrist along up; the palm ends there
FINGER_LENGTH = 0.055  # along up: fingertips FINGER_JOINT_Z + FINGER_LENGTH ahead of the wrist
FINGER_HALF = (0.01, 0.01)  # finger box half size (forward, left)
FINGER_MAX = 0.04  # largest opening of each finger (m along +-left)
PALM_HALF = (0.03, 0.1, 0.023)  # palm box half size (forward, left, up), behind the joints


@dataclass(frozen=True)
class Action:
    """One interaction: contact point, gripper frame and primitive.

    ``up`` is the approach direction (into the surface), ``forward`` the gripper
    orientation about it; both unit vectors, orthogonal, in the world frame.
    """

    point: np.ndarray  # (3,)
    up: np.ndarray  # (3,)
    forward: np.ndarray  # (3,)
    primitive: str = "push"


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


def _normalize(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def gripper_frame(action: Action) -> np.ndarray:
    """(3, 3) rotation with columns [forward, left, up] (forward made orthogonal to up)."""
    up = _normalize(action.up)
    fwd = np.asarray(action.forward, float) - (np.asarray(action.forward, float) @ up) * up
    fwd = _normalize(fwd)
    return np.stack([fwd, np.cross(up, fwd), up], axis=1)


def schedule(primitive: str) -> tuple[list[tuple[np.ndarray, float, str]], float]:
    """Waypoints (wrist offset in the gripper frame, finger target, kind) and start fingers.

    The offset is measured from the start pose (0.15 m behind the point along up).
    """
    approach = np.array([0.0, 0.0, PUSH_START - PUSH_END])
    side = {"left": np.array([SIDE_MOVE, 0, 0]), "up": np.array([0, SIDE_MOVE, 0])}
    base, _, variant = primitive.partition("-")
    if base == "push":
        steps = [(approach, 0.0, "move")]
        if variant:
            steps.append((approach + side[variant], 0.0, "move"))
        return steps, 0.0
    if base == "pull":
        steps = [(approach, 0.04, "move"), (approach, 0.0, "close"), (np.zeros(3), 0.0, "move")]
        if variant:
            steps.append((side[variant], 0.0, "move"))
        return steps, 0.04
    raise ValueError(f"unknown primitive {primitive!r}")


def pull_direction(action: Action) -> np.ndarray:
    """(3,) unit direction the hand moves while pulling: from the grasp to the end of the
    primitive's schedule (-up for ``pull``), in the world frame."""
    steps, _ = schedule(action.primitive)
    move = gripper_frame(action) @ (steps[-1][0] - steps[0][0])
    n = float(np.linalg.norm(move))
    return move / n if n > 0 else -gripper_frame(action)[:, 2]


def judge_motion(motion: np.ndarray, target_joint: int, joint_range: float, pulling: bool,
                 displacement: np.ndarray, pull_direction: np.ndarray) -> tuple[bool, str]:
    """The success rule for a valid trial, shared by the simulator and the executor
    (which judges from robot-side measurements): the touched part is movable and moved
    > 0.01 (m or rad) or more than half its range, and a pull moved the contact point along
    the hand's pulling direction. Returns (success, reason when not)."""
    if not 0 <= target_joint < len(motion):
        return False, "contact point is on a fixed part"
    mv = abs(float(motion[target_joint]))
    if not (mv > MOTION_THRESHOLD or mv / max(float(joint_range), 1e-9) > RANGE_FRACTION):
        return False, "part did not move enough"
    if pulling:
        d = np.asarray(displacement, float)
        cos = float(d @ pull_direction) / max(float(np.linalg.norm(d)), 1e-12)
        if cos <= PULL_COSINE:
            return False, "pull moved the part the wrong way"
    return True, ""
