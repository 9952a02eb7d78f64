"""``w2e bringup`` as a user types it: the README documents its flags on ``w2e bringup``, so
they must be the flags of ``python -m w2e_ros.bringup`` and must work (a REMAINDER argument
once swallowed none of them: "unrecognized arguments")."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env, stop_process

W2E = str(Path(sys.executable).parent / "w2e")  # the console script next to this Python
clean_shm_at_exit()


def _flags(help_text: str) -> set[str]:
    return set(re.findall(r"(?<![\w-])--[a-z][a-z-]*", help_text))


def test_w2e_bringup_help_lists_the_flags_of_the_bringup_module():
    env = ros_env()
    cli = subprocess.run([W2E, "bringup", "--help"], env=env, capture_output=True, text=True,
                         timeout=60)
    assert cli.returncode == 0, cli.stderr
    module = subprocess.run([sys.executable, "-m", "w2e_ros.bringup", "--help"], env=env,
                            capture_output=True, text=True, timeout=60)
    assert module.returncode == 0, module.stderr
    documented = {"--nodes", "--params", "--namespace", "--domain-id", "--log-dir", "--timeout"}
    assert documented <= _flags(cli.stdout), cli.stdout
    assert _flags(cli.stdout) == _flags(module.stdout)


@pytest.mark.slow
def test_w2e_bringup_starts_the_chosen_nodes_in_a_namespace_on_a_domain(tmp_path):
    """--nodes / --namespace / --domain-id / --log-dir take effect: the executor's action shows
    up under /w2e on the domain the flag names (not the environment's), and Ctrl-C stops it."""
    import rclpy
    from rclpy.node import Node

    domain = pick_domain_id(21)
    env = ros_env(domain_id=100 + (domain + 50) % 100)  # the flag, not this, must count
    proc = subprocess.Popen(
        [W2E, "bringup", "--nodes", "executor", "--namespace", "w2e", "--domain-id",
         str(domain), "--log-dir", str(tmp_path / "log"), "--timeout", "60"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    lines: list[str] = []
    up = threading.Event()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))
            if "stack is up" in line:
                up.set()

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    ctx = rclpy.Context()
    try:
        deadline = time.monotonic() + 90
        while not up.wait(0.2) and proc.poll() is None and time.monotonic() < deadline:
            pass
        assert up.is_set(), "\n".join(lines)
        rclpy.init(context=ctx, domain_id=domain)
        probe = Node("test_bringup_probe", context=ctx, start_parameter_services=False)
        want = "/w2e/execute_interaction/_action/send_goal"
        deadline = time.monotonic() + 20
        while want not in {n for n, _ in probe.get_service_names_and_types()}:
            assert time.monotonic() < deadline, f"{want} not on domain {domain}"
            time.sleep(0.2)
        probe.destroy_node()
        assert (tmp_path / "log").is_dir()
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        assert proc.wait(30) == 0, "\n".join(lines)
    finally:
        rclpy.try_shutdown(context=ctx)
        stop_process(proc, group=False)
        reader.join(5)
    assert any(line.startswith("[executor]") for line in lines)
