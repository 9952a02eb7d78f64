"""Fixtures shared by the test modules."""

from __future__ import annotations

import pytest


@pytest.fixture
def ros_context():
    """A private rclpy context per test: nodes of one test never see another's."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)
