"""The one way the stack waits for an rclpy future from a thread that does not spin.

A service handler (planner, executor, arm adapter) or a client script blocks its own thread
while an executor thread completes the future; the wait gives up after a timeout, at once
when the server is known to be gone (:class:`w2e_ros.ros.peers.PeerWatch`), or once the
server has left the ROS graph.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from rclpy.task import Future

POLL_S = 0.5
"""s between two looks at the server of a request in flight."""

GONE_S = 2.0
"""How long ``alive()`` must say the server is absent before the wait gives up."""


class StackError(RuntimeError):
    """Another node did not answer, answered with an error, or is gone."""


class WaitTimeoutError(StackError, TimeoutError):
    """No answer within the timeout."""


class PeerLostError(StackError):
    """The server died or was restarted while the future waited on it."""


def wait_future(future: Future, timeout: float, what: str,
                alive: Callable[[], bool] | None = None,
                check: Callable[[], str | None] | None = None) -> Any:
    """Block this thread until another thread completes ``future`` and return its result.

    Raises :class:`WaitTimeoutError` after ``timeout`` s, :class:`PeerLostError` at once when
    ``check()`` gives a reason (the server died or restarted) or once ``alive()`` has said
    for :data:`GONE_S` that the server left the graph (a server that does not announce
    itself: ~20 s after a SIGKILL), and :class:`StackError` when the future holds an
    exception. Messages start with ``what``."""
    done = threading.Event()
    future.add_done_callback(lambda _f: done.set())
    deadline = time.monotonic() + timeout
    gone = 0
    while not done.wait(min(POLL_S, max(0.0, deadline - time.monotonic()))):
        if time.monotonic() >= deadline:
            raise WaitTimeoutError(f"{what}: no answer within {timeout:.0f} s (is the node "
                                   "running?)")
        why = check() if check is not None else None
        if why:
            raise PeerLostError(f"{what}: {why}")
        gone = gone + 1 if alive is not None and not alive() else 0
        if gone >= GONE_S / POLL_S:
            raise PeerLostError(f"{what}: the server left the ROS graph while answering (did its "
                           "node die?)")
    if future.exception() is not None:
        raise StackError(f"{what}: {future.exception()}")
    return future.result()
