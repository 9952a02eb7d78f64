"""What the comment in w2e_ros/ros/qos.py says about matching holds: a best-effort camera
stream is matched by a sensor-QoS subscriber and NOT by a reliable one."""

from __future__ import annotations

import time

import rclpy
from rclpy.node import Node
from std_msgs.msg import String

from w2e_ros.ros.processes import pick_domain_id
from w2e_ros.ros.qos import RELIABLE_QOS, SENSOR_QOS


def test_a_reliable_subscriber_does_not_match_a_best_effort_publisher():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id())
    node = Node("qos_test", context=ctx)
    try:
        best_effort = node.create_publisher(String, "be", SENSOR_QOS)
        reliable = node.create_publisher(String, "rel", RELIABLE_QOS)
        node.create_subscription(String, "be", lambda m: None, RELIABLE_QOS)
        node.create_subscription(String, "rel", lambda m: None, SENSOR_QOS)
        deadline = time.monotonic() + 5.0
        while reliable.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert reliable.get_subscription_count() == 1  # best-effort sub, reliable pub: matched
        time.sleep(0.5)
        assert best_effort.get_subscription_count() == 0  # reliable sub, best-effort pub: not
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
