"""What RViz is given: the interaction markers, and a layout whose topics the stack publishes.

The markers are built by the executor from the action it runs (``w2e_ros.ros.markers``); the
layout ``config/w2e.rviz`` must name topics and QoS the nodes really use, or a stock RViz shows
nothing (a transient-local display on a volatile publisher, a renamed topic). The markers as a
second process receives them are checked in ``test_bridge_executor``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from builtin_interfaces.msg import Time
from visualization_msgs.msg import Marker

from w2e_ros.core.robot.primitives import Action
from w2e_ros.ros.markers import (
    APPROACH_LENGTH,
    ARROW,
    COLOURS,
    CONTACT,
    LABEL,
    PATH,
    interaction_markers,
    outcome_state,
)
from w2e_ros.ros.waypoints import plan_waypoints

ROOT = Path(__file__).resolve().parents[1]
PULL = Action(np.array([0.4, -0.1, 0.6]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]),
              "pull")


def _by_id(array) -> dict[int, Marker]:
    return {m.id: m for m in array.markers if m.action == Marker.ADD}


def test_the_arrow_ends_on_the_contact_and_comes_from_the_approach_side():
    plan = plan_waypoints(PULL)
    out = interaction_markers(PULL, plan.positions, "world", Time(sec=3), "success",
                              "success (+0.100)")
    assert out.markers[0].action == Marker.DELETEALL  # only the latest interaction is shown
    m = _by_id(out)
    tail, head = m[ARROW].points
    assert np.allclose([head.x, head.y, head.z], PULL.point)
    assert np.allclose([tail.x, tail.y, tail.z], PULL.point + APPROACH_LENGTH * PULL.up)
    c = m[CONTACT].pose.position
    assert np.allclose([c.x, c.y, c.z], PULL.point)
    assert len(m[PATH].points) == len(plan.positions)
    assert np.allclose([[p.x, p.y, p.z] for p in m[PATH].points], plan.positions)
    assert m[LABEL].text == "pull: success (+0.100)"
    for marker in m.values():
        assert marker.header.frame_id == "world" and marker.header.stamp.sec == 3
        assert (marker.color.r, marker.color.g, marker.color.b) == pytest.approx(
            COLOURS["success"])


def test_outcome_colours_and_bad_state():
    assert [outcome_state(v, s) for v, s in ((True, True), (True, False), (False, False))] == [
        "success", "failure", "invalid"]
    with pytest.raises(ValueError, match="unknown marker state"):
        interaction_markers(PULL, np.zeros((2, 3)), "world", Time(), "exploded")


def _published_topics() -> dict[str, str]:
    """Topic name -> QoS constant of every ``create_publisher(Type, "name", QOS)`` in the
    nodes, the ROS helpers and the bridge."""
    found: dict[str, str] = {}
    pattern = re.compile(r'create_publisher\(\s*\w+,\s*"([\w/]+)",\s*(\w+)')
    for path in [*ROOT.glob("w2e_ros/**/*.py"), *ROOT.glob("sim_bridge/*.py")]:
        for name, qos in pattern.findall(path.read_text()):
            found[name] = qos
    return found


def test_the_rviz_layout_shows_topics_the_stack_publishes_with_their_qos():
    layout = yaml.safe_load((ROOT / "config" / "w2e.rviz").read_text())
    displays = layout["Visualization Manager"]["Displays"]
    published = _published_topics()
    expected = {"Transient Local": "LATCHED_QOS", "Volatile": "SENSOR_QOS"}
    topics = {}
    for d in displays:
        if "Topic" not in d:
            continue
        name = d["Topic"]["Value"].lstrip("/")
        assert name in published, f"{d['Name']}: no node publishes {name!r}"
        assert published[name] == expected[d["Topic"]["Durability Policy"]], d["Name"]
        if published[name] == "SENSOR_QOS":
            assert d["Topic"]["Reliability Policy"] == "Best Effort", d["Name"]
        topics[name] = d["Class"]
    assert topics["interaction_markers"] == "rviz_default_plugins/MarkerArray"
    assert {"camera/points", "affordance_map", "planned_path"} <= set(topics)
    assert layout["Visualization Manager"]["Global Options"]["Fixed Frame"] == "world"
