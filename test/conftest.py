"""Fixtures shared by the test modules."""

from __future__ import annotations

import os

import pytest

from w2e_ros.core.infra.allocator import keep_freed_memory


def pytest_configure(config: pytest.Config) -> None:
    keep_freed_memory()  # tests that train in-process run as `w2e train` does


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    """A failed test's report names the processes that map deleted Fast DDS ports: the trace
    of the rare lost-message failures between this process and a stack (w2e_ros.ros.processes
    .deleted_shm_ports)."""
    outcome = yield
    rep = outcome.get_result()
    if rep.when == "call" and rep.failed:
        from w2e_ros.ros.processes import deleted_shm_ports

        ports = deleted_shm_ports()
        if ports:
            rep.sections.append(("Fast DDS ports mapped after their files were removed", "\n".join(
                f"pid {pid}{' (this test process)' if pid == os.getpid() else ''}: "
                f"{' '.join(names)}" for pid, names in sorted(ports.items()))))


@pytest.fixture
def ros_context():
    """A private rclpy context per test: nodes of one test never see another's."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)
