"""The one way every node of the stack runs (STYLE.md's ``main()`` shape, written once)."""

from __future__ import annotations

from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node


def run_node(make_node: Callable[[], Node], args: list[str] | None = None,
             threads: int = 1) -> None:
    """Init, build the node, spin until Ctrl-C / shutdown, then tear down in order.

    ``threads > 1`` uses a MultiThreadedExecutor, for nodes whose callbacks wait on other
    nodes (a service handler that drives an action), so nothing deadlocks.
    """
    rclpy.init(args=args)
    node = executor = None
    try:
        node = make_node()
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else (
            SingleThreadedExecutor())
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)  # finish callbacks before the node goes
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
