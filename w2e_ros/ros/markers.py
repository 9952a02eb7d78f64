"""What RViz shows of one interaction: ``visualization_msgs/MarkerArray`` built from an action.

The executor publishes these on ``interaction_markers`` when it plans an interaction and again
when the outcome is known, so a user watching a stock RViz (``config/w2e.rviz``) sees where the
robot is about to act and how it went: an arrow along the approach ending at the contact, a
sphere on the contact, the gripper's waypoint path and a label. Colours: amber while planned,
green for a success, red for a failure, grey for an invalid trial. Every publication starts
with a DELETEALL of the namespace, so the display holds the latest interaction only.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from w2e_ros.core.robot.primitives import Action

NAMESPACE = "w2e_interaction"
ARROW, CONTACT, PATH, LABEL = 0, 1, 2, 3  # marker ids within the namespace
COLOURS = {"planned": (1.0, 0.7, 0.0), "success": (0.1, 0.8, 0.2),
           "failure": (0.9, 0.1, 0.1), "invalid": (0.5, 0.5, 0.5)}
APPROACH_LENGTH = 0.15  # m drawn along the approach, as far back as the first waypoint starts


def _point(p: Sequence[float]) -> Point:
    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _marker(kind: int, mid: int, frame_id: str, stamp: TimeMsg, state: str) -> Marker:
    m = Marker(type=kind, id=mid, ns=NAMESPACE, action=Marker.ADD)
    m.header.frame_id, m.header.stamp = frame_id, stamp
    m.pose.orientation.w = 1.0
    r, g, b = COLOURS[state]
    m.color = ColorRGBA(r=r, g=g, b=b, a=1.0)
    return m


def interaction_markers(action: Action, waypoints: np.ndarray, frame_id: str, stamp: TimeMsg,
                        state: str = "planned", label: str = "") -> MarkerArray:
    """The markers of ``action`` (contact ``action.point``, approach along ``-action.up``)
    whose wrist follows ``waypoints`` (K, 3), in ``state`` (a key of :data:`COLOURS`)."""
    if state not in COLOURS:
        raise ValueError(f"unknown marker state {state!r}; known: {', '.join(COLOURS)}")
    contact = np.asarray(action.point, float)
    up = np.asarray(action.up, float)
    up = up / max(float(np.linalg.norm(up)), 1e-9)
    clear = Marker(ns=NAMESPACE, action=Marker.DELETEALL)
    clear.header.frame_id, clear.header.stamp = frame_id, stamp

    arrow = _marker(Marker.ARROW, ARROW, frame_id, stamp, state)
    arrow.points = [_point(contact + APPROACH_LENGTH * up), _point(contact)]
    arrow.scale.x, arrow.scale.y, arrow.scale.z = 0.008, 0.016, 0.02  # shaft, head, head length

    sphere = _marker(Marker.SPHERE, CONTACT, frame_id, stamp, state)
    sphere.pose.position = _point(contact)
    sphere.scale.x = sphere.scale.y = sphere.scale.z = 0.02

    path = _marker(Marker.LINE_STRIP, PATH, frame_id, stamp, state)
    path.points = [_point(p) for p in np.asarray(waypoints, float).reshape(-1, 3)]
    path.scale.x = 0.004
    path.color.a = 0.6

    text = _marker(Marker.TEXT_VIEW_FACING, LABEL, frame_id, stamp, state)
    text.pose.position = _point(contact + np.array([0.0, 0.0, 0.08]))
    text.scale.z = 0.03
    text.text = f"{action.primitive}: {label or state}"
    return MarkerArray(markers=[clear, arrow, sphere, path, text])


def outcome_state(valid: bool, success: bool) -> str:
    """The colour key of a judged interaction."""
    return "invalid" if not valid else ("success" if success else "failure")
