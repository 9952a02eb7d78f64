"""The one way every node of the stack runs, written once: ``rclpy.init``; build the node; spin
inside ``try``; ``except (KeyboardInterrupt, ExternalShutdownException)``; ``finally``
destroy the node and ``rclpy.try_shutdown()`` (the shape of the ``ros2/examples`` nodes)."""

from __future__ import annotations

import signal
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from w2e_ros.ros.params import ParameterError

SPIN_PERIOD = 0.1  # s: the main thread gets back to Python this often, so signals land
DRAIN_TIMEOUT = 2.0  # s: longest a callback in flight may still run once shutdown is asked


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def run_node(make_node: Callable[[], Node], args: list[str] | None = None,
             threads: int = 1) -> None:
    """Init, build the node, spin until Ctrl-C / SIGTERM / shutdown, then tear down in order.

    ``threads > 1`` uses a MultiThreadedExecutor, for nodes whose callbacks wait on other
    nodes (a service handler that drives an action), so nothing deadlocks.

    Signals are handled here, not by rclpy: rclpy's handler shuts the context down at once,
    under callbacks still running in executor threads, whose next publish then fails ("context
    is invalid") and is printed as an exception nobody retrieved. Here a signal stops the spin
    loop, callbacks in flight get ``DRAIN_TIMEOUT`` to finish with a live context, and only
    then the node and the context go.

    A parameter the node cannot start with (:class:`ParameterError`) is logged as one line
    under the node's name, without a traceback, and the process exits with status 2.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    previous = signal.signal(signal.SIGTERM, _interrupt)
    node = executor = None
    refused = False
    try:
        node = make_node()
        executor = MultiThreadedExecutor(num_threads=threads) if threads > 1 else (
            SingleThreadedExecutor())
        executor.add_node(node)
        while rclpy.ok():
            executor.spin_once(timeout_sec=SPIN_PERIOD)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ParameterError as err:
        refused = True
        logger = err.node.strip("/").replace("/", ".") or "w2e"
        rclpy.logging.get_logger(logger).fatal(err.message)
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second signal must not cut teardown
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if executor is not None:
            executor.shutdown(timeout_sec=0.0)
            # Jazzy's Executor.shutdown() does not wait for work in flight (its check runs
            # after it sets the flag it tests), so wait here.
            tracker = getattr(executor, "_work_tracker", None)
            if tracker is not None:
                tracker.wait(timeout_sec=DRAIN_TIMEOUT)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        signal.signal(signal.SIGTERM, previous)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if refused:
        raise SystemExit(2)
