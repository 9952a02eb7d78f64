"""Fixtures shared by the test modules."""

from __future__ import annotations

import os
import re

import pytest

from w2e_ros.core.infra.allocator import keep_freed_memory


def pytest_configure(config: pytest.Config) -> None:
    keep_freed_memory()  # tests that train in-process run as `w2e train` does


# A test may skip only for hardware or a platform this machine does not have. Any other skip
# (a module that does not import, a missing interface package) is a broken install and fails,
# so CI cannot go green by skipping what it should have run.
HARDWARE_SKIPS = re.compile(r"CUDA|rendering device|glibc|C compiler")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    """A failed test's report names the processes that map deleted Fast DDS ports: the trace
    of the rare lost-message failures between this process and a stack (w2e_ros.ros.processes
    .deleted_shm_ports). A skip for anything but missing hardware is made a failure."""
    outcome = yield
    rep = outcome.get_result()
    if rep.skipped and not hasattr(rep, "wasxfail"):
        reason = rep.longrepr[2] if isinstance(rep.longrepr, tuple) else str(rep.longrepr)
        if not HARDWARE_SKIPS.search(reason):
            rep.outcome = "failed"
            rep.longrepr = f"skipped for a reason that is not missing hardware: {reason}"
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
