"""Fixtures shared by the test modules."""

from __future__ import annotations

import pytest

from w2e_ros.core.allocator import keep_freed_memory


def pytest_configure(config: pytest.Config) -> None:
    keep_freed_memory()  # tests that train in-process run as `w2e train` does


@pytest.fixture
def ros_context():
    """A private rclpy context per test: nodes of one test never see another's."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)
