"""Every QoS the stack uses, chosen in one place so publishers and subscribers agree.

* Sensor streams (camera clouds): best effort, keep the last few; a late frame is worth
  nothing. A subscriber must ask for best effort too (``SENSOR_QOS``): a reliable subscriber
  does NOT match a best-effort publisher (requested reliability exceeds what is offered) and
  receives nothing, while a best-effort subscriber matches either kind of publisher.
* Commands, results and progress: reliable, so no step of a loop is silently lost.
* State that a node needs on start-up (the latest segmented objects, the latest affordance
  maps for RViz): reliable + transient local, depth 1, so a late joiner gets the last one.
"""

from __future__ import annotations

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

SENSOR_QOS: QoSProfile = qos_profile_sensor_data
"""Camera clouds: best effort, volatile, keep last 5."""

RELIABLE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
"""Progress and events: every message delivered, none kept for late joiners."""

LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""Latest state (segmented objects, affordance maps): a late subscriber gets the last one."""
