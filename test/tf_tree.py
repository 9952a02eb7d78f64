"""A robot_state_publisher stand-in for the TF tests, run as its own process.

    python test/tf_tree.py '<json>'

The JSON holds ``static``: [[parent, child, x, y, z, qx, qy, qz, qw], ...], published once on
``/tf_static`` in one message (reliable, transient local: what StaticTransformBroadcaster and
robot_state_publisher's fixed joints do), and ``dynamic``: [[parent, child, stamp_ns, x, y,
z, qx, qy, qz, qw], ...], the samples of moving edges, published on ``/tf`` (reliable,
volatile: TransformBroadcaster) at ``rate_hz``, all of them each time (a listener that joins
late still gets every stamp). Plain rclpy and tf2_msgs, nothing of w2e_ros. Prints ``ready``
once both publishers exist; runs until SIGTERM / SIGINT.
"""

from __future__ import annotations

import json
import signal
import sys
import time

import rclpy
from geometry_msgs.msg import TransformStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage


def transform(parent: str, child: str, stamp_ns: int, pose: list[float]) -> TransformStamped:
    ts = TransformStamped()
    ts.header.frame_id, ts.child_frame_id = parent, child
    ts.header.stamp.sec, ts.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    t, q = ts.transform.translation, ts.transform.rotation
    t.x, t.y, t.z, q.x, q.y, q.z, q.w = (float(v) for v in pose)
    return ts


def main() -> None:
    spec = json.loads(sys.argv[1])
    rclpy.init()
    node = rclpy.create_node("tf_tree")
    static_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                            reliability=ReliabilityPolicy.RELIABLE,
                            durability=DurabilityPolicy.TRANSIENT_LOCAL)
    static_pub = node.create_publisher(TFMessage, "/tf_static", static_qos)
    dynamic_pub = node.create_publisher(TFMessage, "/tf", QoSProfile(depth=100))
    static = TFMessage(transforms=[transform(p, c, 0, pose)
                                   for p, c, *pose in spec.get("static", [])])
    dynamic = TFMessage(transforms=[transform(p, c, stamp, pose)
                                    for p, c, stamp, *pose in spec.get("dynamic", [])])
    if static.transforms:
        static_pub.publish(static)
    print("ready", flush=True)
    running = True

    def stop(*_args) -> None:
        nonlocal running
        running = False

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    period = 1.0 / float(spec.get("rate_hz", 10.0))
    while running:
        if dynamic.transforms:
            dynamic_pub.publish(dynamic)
        time.sleep(period)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
