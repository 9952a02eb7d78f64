"""Waits on a condition with a deadline, shared by the test modules (issue 41): a test waits for
the event it needs, never a fixed time that a loaded machine can outlast, and a wait that runs
out names what it waited for."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


def wait_until(pred: Callable[[], T], timeout: float, what: str, *, executor: Any = None,
               poll: float = 0.02, detail: Callable[[], str] | None = None) -> T:
    """Poll ``pred()`` until it is truthy and return that value. With an rclpy ``executor``,
    spin it between polls (``spin_once(timeout_sec=poll)``), else sleep ``poll`` s. After
    ``timeout`` s an AssertionError names ``what`` and, when given, ``detail()`` (a log tail)."""
    end = time.monotonic() + timeout
    while not (value := pred()):
        if time.monotonic() >= end:
            more = f"\n{detail()}" if detail is not None else ""
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}{more}")
        if executor is not None:
            executor.spin_once(timeout_sec=poll)
        else:
            time.sleep(poll)
    return value


def result_of(future: Any, timeout: float, what: str, *, executor: Any = None,
              poll: float = 0.02) -> Any:
    """The result of an rclpy future: spun by ``executor`` when given, else completed by an
    executor that spins in another thread (the future is polled: rclpy would run a
    ``add_done_callback`` callback as a task of that executor, which may be shut down)."""
    wait_until(future.done, timeout, what, executor=executor, poll=poll)
    return future.result()


class Liveliness:
    """A reader of the announcement topic of ``name`` (``w2e_ros.ros.peers``) beside the
    node's own PeerWatch, counting the announcing writers that became alive to this process.
    Fast DDS asserts automatic liveliness in its own messages, not with the data: a process
    killed before the first of them arrived was never alive to the reader, and its death is
    not reported. Create it before the process starts; :meth:`wait` for its writer to count
    instead of sleeping a lease."""

    def __init__(self, node: Any, name: str) -> None:
        from rclpy.event_handler import SubscriptionEventCallbacks
        from std_msgs.msg import String

        from w2e_ros.ros.peers import ALIVE_QOS, alive_topic

        self.name = name
        self._cv = threading.Condition()
        self.came_alive = 0
        self._sub = node.create_subscription(
            String, alive_topic(node, name), lambda _m: None, ALIVE_QOS,
            event_callbacks=SubscriptionEventCallbacks(liveliness=self._on_liveliness))

    def _on_liveliness(self, info: Any) -> None:
        with self._cv:
            self.came_alive += max(0, info.alive_count_change)
            self._cv.notify_all()

    def wait(self, count: int, timeout: float = 60.0) -> None:
        """Until ``count`` writers in all have become alive here."""
        with self._cv:
            assert self._cv.wait_for(lambda: self.came_alive >= count, timeout), (
                f"timed out after {timeout:g} s waiting for writer {count} of {self.name}'s "
                f"announcement to be alive here ({self.came_alive} so far)")
