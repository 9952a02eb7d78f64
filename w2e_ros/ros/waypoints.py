"""Primitive <-> gripper waypoints, and the outcome of a trial from what the robot measured.

Plain Python (no rclpy). The executor turns an :class:`Action` into the wrist waypoints of
its primitive (``w2e_ros.core.robot.primitives``: start 0.15 m behind the point along ``up``,
...); the simulator
bridge, which can only run whole primitives, maps such a trajectory back to the action it
encodes and refuses anything else. Both directions use the core's schedule
(:func:`w2e_ros.core.robot.primitives.schedule`), which the simulator runs too, so there is one
definition of each primitive's motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from w2e_ros.core.robot.primitives import (
    PRIMITIVES,
    PUSH_START,
    Action,
    TrialResult,
    gripper_frame,
    judge_motion,
    pull_direction,
    schedule,
)

GRIPPER_KEEP, GRIPPER_OPEN, GRIPPER_CLOSE = 0, 1, 2  # = FollowWaypoints.Goal constants
POSITION_TOLERANCE = 0.005  # m: a trajectory within this of a primitive's is that primitive
ROTATION_TOLERANCE = 0.02  # max |R_i - R_0| entry: primitives keep the hand's orientation


@dataclass
class WaypointPlan:
    """Wrist waypoints of one primitive in the world frame (orientation fixed throughout)."""

    positions: np.ndarray  # (K, 3) wrist positions
    rotation: np.ndarray  # (3, 3) columns [forward, left, up]
    gripper: list[int]  # command applied once waypoint k is reached
    initial_gripper: int  # GRIPPER_OPEN or GRIPPER_CLOSE before the first waypoint
    phases: list[str]  # what the move to waypoint k is, for feedback


def plan_waypoints(action: Action) -> WaypointPlan:
    """The wrist trajectory of ``action``'s primitive (raises ValueError if unknown)."""
    if action.primitive not in PRIMITIVES:
        raise ValueError(f"unknown primitive {action.primitive!r}; expected one of {PRIMITIVES}")
    R = gripper_frame(action)
    start = np.asarray(action.point, float) - PUSH_START * R[:, 2]
    steps, fingers = schedule(action.primitive)
    base = action.primitive.split("-")[0]
    positions, gripper, phases = [start], [GRIPPER_KEEP], ["pre-contact"]
    for k, (offset, _finger, kind) in enumerate(steps):
        if kind == "close":
            positions.append(positions[-1].copy())
            gripper.append(GRIPPER_CLOSE)
            phases.append("grasp")
            continue
        positions.append(start + R @ np.asarray(offset, float))
        gripper.append(GRIPPER_KEEP)
        if k == 0:
            phases.append("push" if base == "push" else "approach")
        elif np.linalg.norm(offset) < 1e-9:
            phases.append("pull")
        else:
            phases.append(action.primitive)
    return WaypointPlan(
        positions=np.stack(positions),
        rotation=R,
        gripper=gripper,
        initial_gripper=GRIPPER_OPEN if fingers > 0 else GRIPPER_CLOSE,
        phases=phases,
    )


def action_from_waypoints(
    positions: np.ndarray,
    rotations: np.ndarray,
    gripper: list[int],
    initial_gripper: int,
) -> Action:
    """The primitive a wrist trajectory encodes (inverse of :func:`plan_waypoints`).

    Raises ValueError, saying why, for a trajectory that is not one of the primitives (the
    simulated flying gripper executes whole primitives, not arbitrary paths).
    """
    positions = np.asarray(positions, float).reshape(-1, 3)
    rotations = np.asarray(rotations, float).reshape(-1, 3, 3)
    if len(positions) < 2:
        raise ValueError(f"a primitive needs at least 2 waypoints, got {len(positions)}")
    if len(rotations) != len(positions) or len(gripper) != len(positions):
        raise ValueError("waypoints, orientations and gripper commands differ in length")
    if not (np.isfinite(positions).all() and np.isfinite(rotations).all()):
        raise ValueError("waypoints contain NaN or infinite values")
    if np.abs(rotations - rotations[0]).max() > ROTATION_TOLERANCE:
        raise ValueError("the hand's orientation changes along the waypoints; primitives keep it")
    if initial_gripper not in (GRIPPER_OPEN, GRIPPER_CLOSE):
        raise ValueError("initial_gripper must be GRIPPER_OPEN (pull) or GRIPPER_CLOSE (push)")
    R = rotations[0]
    up, forward = R[:, 2], R[:, 0]
    point = positions[0] + PUSH_START * up
    base = "push" if initial_gripper == GRIPPER_CLOSE else "pull"
    best = np.inf
    for primitive in (p for p in PRIMITIVES if p.split("-")[0] == base):
        plan = plan_waypoints(Action(point=point, up=up, forward=forward, primitive=primitive))
        if len(plan.positions) != len(positions) or list(plan.gripper) != list(gripper):
            continue
        err = float(np.linalg.norm(plan.positions - positions, axis=1).max())
        best = min(best, err)
        if err <= POSITION_TOLERANCE:
            return Action(point=point, up=plan.rotation[:, 2], forward=plan.rotation[:, 0],
                          primitive=primitive)
    detail = f" (closest {base} primitive is {best * 100:.1f} cm off)" if np.isfinite(best) else ""
    raise ValueError(
        f"the {len(positions)} waypoints with gripper commands {list(gripper)} are not a "
        f"{base} primitive the simulated gripper can execute{detail}")


def outcome_from_measurement(
    action: Action,
    joints_before: np.ndarray,
    joints_after: np.ndarray,
    joint_ranges: np.ndarray,
    child_links: list[str],
    contact_joint: int,
    contact_displacement: np.ndarray,
    valid: bool,
    reason: str = "",
) -> TrialResult:
    """Judge a trial from what the robot side measured, with the success rule of
    ``w2e_ros.core.robot.primitives``.

    Success: valid, the touched part is movable, it moved > 0.01 (m or rad) or more than half
    its range, and for pulls the contact point moved along the hand's pulling direction
    (cosine > 0.5). This is what a real robot adapter reports too, so the executor judges
    real and simulated trials the same way.
    """
    before = np.asarray(joints_before, float).reshape(-1)
    after = np.asarray(joints_after, float).reshape(-1)
    if before.shape != after.shape:
        raise ValueError(f"joint states differ in size: {before.shape} vs {after.shape}")
    motion = after - before
    moved = int(np.argmax(np.abs(motion))) if len(motion) else -1
    if moved >= 0 and abs(motion[moved]) <= 1e-3:
        moved = -1
    moved_link = child_links[moved] if 0 <= moved < len(child_links) else ""
    disp = np.asarray(contact_displacement, float).reshape(3)
    success = False
    if valid:
        pulling = action.primitive.startswith("pull")
        pull = pull_direction(action) if pulling else np.zeros(3)
        in_range = 0 <= contact_joint < len(motion)
        success, why = judge_motion(motion, contact_joint,
                                    float(joint_ranges[contact_joint]) if in_range else 0.0,
                                    pulling, disp, pull)
        reason = reason or why
    if success:
        reason = ""
    return TrialResult(valid=bool(valid), success=bool(success), motion=motion,
                       moved_joint=moved, moved_link=moved_link, reason=reason,
                       contact_displacement=disp, target_joint=int(contact_joint))
