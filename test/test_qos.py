"""What the comment in w2e_ros/ros/qos.py says about matching holds: a best-effort camera
stream is matched by a sensor-QoS subscriber and NOT by a reliable one."""

from __future__ import annotations

import rclpy
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSPolicyKind
from std_msgs.msg import String
from waits import wait_until

from w2e_ros.ros.processes import pick_domain_id
from w2e_ros.ros.qos import RELIABLE_QOS, SENSOR_QOS


def test_a_reliable_subscriber_does_not_match_a_best_effort_publisher():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id())
    node = Node("qos_test", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        incompatible = []
        best_effort = node.create_publisher(
            String, "be", SENSOR_QOS,
            event_callbacks=PublisherEventCallbacks(incompatible_qos=incompatible.append))
        reliable = node.create_publisher(String, "rel", RELIABLE_QOS)
        got = {"be": [], "rel": []}
        node.create_subscription(String, "be", got["be"].append, RELIABLE_QOS)
        node.create_subscription(String, "rel", got["rel"].append, SENSOR_QOS)
        # best-effort sub, reliable pub: matched, and its messages arrive
        wait_until(lambda: reliable.get_subscription_count() == 1, 30.0,
                   "the best-effort subscription to match the reliable publisher", executor=ex)

        def delivered():
            reliable.publish(String(data="r"))
            best_effort.publish(String(data="b"))
            return got["rel"]

        wait_until(delivered, 30.0, "a message on the matched pair", executor=ex, poll=0.05)
        # reliable sub, best-effort pub: discovered (DDS reports the incompatible offer, naming
        # reliability) and not matched; what it published after that never arrived
        wait_until(lambda: incompatible, 30.0, "the incompatible-QoS event", executor=ex)
        assert incompatible[-1].last_policy_kind == QoSPolicyKind.RELIABILITY
        best_effort.publish(String(data="b"))
        ex.spin_once(timeout_sec=0.2)
        assert best_effort.get_subscription_count() == 0
        assert got["be"] == []
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
