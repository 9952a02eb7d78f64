"""w2e_ros.core.robot.primitives (the plain contract) <-> w2e_msgs / geometry_msgs messages.

The nodes talk messages, the core and the simulator talk :class:`Action` and
:class:`TrialResult`; these functions are the only place the two meet, and the message ->
plain direction validates (finite, unit, known primitive) so a bad request is refused with a
clear :class:`ValueError` before it reaches the simulator or the robot.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point, Pose, Quaternion, Vector3
from w2e_msgs.msg import Interaction, InteractionOutcome

from w2e_ros.core.robot.actions import gripper_frame
from w2e_ros.core.robot.primitives import PRIMITIVES, Action, TrialResult

# --- geometry_msgs <-> numpy -----------------------------------------------------------------


def to_point(v) -> Point:
    """(3,) -> geometry_msgs/Point."""
    x, y, z = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    return Point(x=x, y=y, z=z)


def to_vector3(v) -> Vector3:
    """(3,) -> geometry_msgs/Vector3."""
    x, y, z = (float(c) for c in np.asarray(v, dtype=np.float64).reshape(3))
    return Vector3(x=x, y=y, z=z)


def from_xyz(msg: Point | Vector3) -> np.ndarray:
    """geometry_msgs/Point or Vector3 -> (3,) float64."""
    return np.array([msg.x, msg.y, msg.z], dtype=np.float64)


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (x, y, z, w) unit quaternion with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m = [
        (1.0 + R[0, 0] + R[1, 1] + R[2, 2], 3),
        (1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0),
        (1.0 - R[0, 0] + R[1, 1] - R[2, 2], 1),
        (1.0 - R[0, 0] - R[1, 1] + R[2, 2], 2),
    ]
    t, k = max(m)
    s = 0.5 / np.sqrt(t)
    q = np.zeros(4)
    if k == 3:
        q = np.array([(R[2, 1] - R[1, 2]) * s, (R[0, 2] - R[2, 0]) * s,
                      (R[1, 0] - R[0, 1]) * s, 0.25 / s])
    elif k == 0:
        q = np.array([0.25 / s, (R[0, 1] + R[1, 0]) * s, (R[0, 2] + R[2, 0]) * s,
                      (R[2, 1] - R[1, 2]) * s])
    elif k == 1:
        q = np.array([(R[0, 1] + R[1, 0]) * s, 0.25 / s, (R[1, 2] + R[2, 1]) * s,
                      (R[0, 2] - R[2, 0]) * s])
    else:
        q = np.array([(R[0, 2] + R[2, 0]) * s, (R[1, 2] + R[2, 1]) * s, 0.25 / s,
                      (R[1, 0] - R[0, 1]) * s])
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def matrix_from_quaternion(q) -> np.ndarray:
    """(x, y, z, w) -> (3, 3) rotation (the quaternion is normalised first)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def to_pose(position, rotation: np.ndarray) -> Pose:
    """Position (3,) + rotation (3, 3) -> geometry_msgs/Pose."""
    x, y, z, w = quaternion_from_matrix(rotation)
    return Pose(position=to_point(position), orientation=Quaternion(x=x, y=y, z=z, w=w))


def from_pose(msg: Pose) -> tuple[np.ndarray, np.ndarray]:
    """geometry_msgs/Pose -> (position (3,), rotation (3, 3)); a zero quaternion is refused."""
    q = np.array([msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w])
    if not np.isfinite(q).all() or np.linalg.norm(q) < 1e-9:
        raise ValueError("pose orientation is not a valid quaternion")
    return from_xyz(msg.position), matrix_from_quaternion(q)


# --- Action <-> Interaction ------------------------------------------------------------------


def action_to_interaction(action: Action, object_id: int = 0) -> Interaction:
    """A plain :class:`Action` as the message the planner sends the executor."""
    return Interaction(
        object_id=int(object_id),
        point=to_point(action.point),
        up=to_vector3(action.up),
        forward=to_vector3(action.forward),
        primitive=str(action.primitive),
    )


def interaction_to_action(msg: Interaction) -> Action:
    """Validate an Interaction and return it as an :class:`Action` (unit, orthogonal frame).

    Raises ValueError for an unknown primitive, non-finite values, a zero ``up`` or a
    ``forward`` parallel to ``up``; ``forward`` is re-orthogonalised against ``up``.
    """
    if msg.primitive not in PRIMITIVES:
        raise ValueError(f"unknown primitive {msg.primitive!r}; expected one of {PRIMITIVES}")
    point, up, forward = from_xyz(msg.point), from_xyz(msg.up), from_xyz(msg.forward)
    if not (np.isfinite(point).all() and np.isfinite(up).all() and np.isfinite(forward).all()):
        raise ValueError("interaction has NaN or infinite values")
    up, forward = gripper_frame(up, forward)
    return Action(point=point, up=up, forward=forward, primitive=msg.primitive)


# --- TrialResult <-> InteractionOutcome ------------------------------------------------------


def trial_result_to_outcome(result: TrialResult) -> InteractionOutcome:
    """What the simulator (or the executor's measurement) found, as a message."""
    motion = np.asarray(result.motion, dtype=np.float64).reshape(-1)
    j = int(result.moved_joint)
    return InteractionOutcome(
        valid=bool(result.valid),
        success=bool(result.success),
        motion=float(motion[j]) if 0 <= j < len(motion) else 0.0,
        joint_motion=[float(m) for m in motion],
        moved_part=str(result.moved_link),
        joint_index=j,
        contact_displacement=to_vector3(result.contact_displacement),
        reason=str(result.reason),
    )


def outcome_to_trial_result(msg: InteractionOutcome) -> TrialResult:
    """An InteractionOutcome as the core's :class:`TrialResult` (e.g. to train on it)."""
    return TrialResult(
        valid=bool(msg.valid),
        success=bool(msg.success),
        motion=np.asarray(msg.joint_motion, dtype=np.float64),
        moved_joint=int(msg.joint_index),
        moved_link=str(msg.moved_part),
        reason=str(msg.reason),
        contact_displacement=from_xyz(msg.contact_displacement),
    )
