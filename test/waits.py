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


def result_of(future: Any, timeout: float, what: str, *, executor: Any = None) -> Any:
    """The result of an rclpy future (or anything with ``done``/``add_done_callback``/
    ``result``): spun by ``executor`` when given, else completed by an executor that spins in
    another thread."""
    if executor is not None:
        wait_until(future.done, timeout, what, executor=executor)
    else:
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        assert done.wait(timeout), f"timed out after {timeout:g} s waiting for {what}"
    return future.result()
