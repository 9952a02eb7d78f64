"""``w2e bringup`` as a user types it: README and docs/ros_api.md document its flags, so
they must be the flags of ``python -m w2e_ros.bringup`` and must work (a REMAINDER argument
once swallowed none of them: "unrecognized arguments")."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from waits import wait_until

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
    documented = {"--nodes", "--params", "--namespace", "--domain-id", "--log-dir", "--timeout",
                  "--respawn", "--respawn-limit", "--respawn-delay"}
    assert documented <= _flags(cli.stdout), cli.stdout
    assert _flags(cli.stdout) == _flags(module.stdout)


@pytest.mark.slow
def test_w2e_bringup_starts_the_chosen_nodes_in_a_namespace_on_a_domain(tmp_path):
    """--nodes / --namespace / --domain-id / --log-dir take effect: the executor's action shows
    up under /w2e on the domain the flag names (not the environment's), and Ctrl-C stops it."""
    import rclpy
    from rclpy.node import Node

    domain = pick_domain_id()
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
        wait_until(lambda: want in {n for n, _ in probe.get_service_names_and_types()}, 60.0,
                   f"{want} on domain {domain}", poll=0.2)
        probe.destroy_node()
        assert (tmp_path / "log").is_dir()
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        assert proc.wait(30) == 0, "\n".join(lines)
    finally:
        rclpy.try_shutdown(context=ctx)
        stop_process(proc, group=False)
        reader.join(5)
    assert any(line.startswith("[executor]") for line in lines)


@pytest.mark.slow
def test_w2e_bringup_respawn_restarts_a_dead_node_up_to_the_limit(tmp_path):
    """--respawn: a node killed is started again (logged, with its new pid); once it has been
    restarted --respawn-limit times it stays dead, bringup says so and exits."""
    proc = subprocess.Popen(
        [W2E, "bringup", "--nodes", "executor", "--domain-id", str(pick_domain_id()),
         "--log-dir", str(tmp_path / "log"), "--respawn", "--respawn-limit", "1",
         "--respawn-delay", "0.2"],
        env=ros_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    lines: list[str] = []
    pids: list[int] = []
    news = threading.Condition()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))
            m = re.search(r"node executor (?:is up|restarted) \(pid (\d+)\)", line)
            with news:
                if m:
                    pids.append(int(m.group(1)))
                news.notify_all()

    def wait_for(pred, timeout: float) -> None:
        with news:
            assert news.wait_for(pred, timeout), "\n".join(lines)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        wait_for(lambda: len(pids) == 1, 90)
        os.kill(pids[0], signal.SIGKILL)
        wait_for(lambda: len(pids) == 2, 30)
        assert "[bringup] node executor died (SIGKILL); restart 1 of 1 in 0.2 s" in lines
        assert pids[1] != pids[0]
        # let it start (its settings logged a second time), then it dies once too often
        wait_for(lambda: sum(x.startswith("[executor]") and "settings:" in x
                             for x in lines) == 2, 90)
        os.kill(pids[1], signal.SIGKILL)
        assert proc.wait(30) == 1, "\n".join(lines)
    finally:
        stop_process(proc, group=False)
        reader.join(5)
    assert any("node executor died (SIGKILL); not restarted: it was restarted 1 times (limit 1)"
               in x for x in lines), "\n".join(lines)
    assert "[bringup] every node has exited (respawn limit reached)" in lines


def test_nodes_of_a_stack_whose_owner_is_killed_do_not_outlive_it(tmp_path):
    """A ``w2e demo`` (or any script holding a Stack) killed by SIGKILL has no chance to stop
    its nodes; they must not keep running on the domain (they did: five orphans per kill)."""
    script = tmp_path / "owner.py"
    script.write_text(
        "import sys, time\n"
        "from w2e_ros.bringup import Stack\n"
        "from w2e_ros.ros.processes import pick_domain_id, ros_env\n"
        "s = Stack(nodes=['executor'], env=ros_env(domain_id=pick_domain_id()), output=None,\n"
        "          ready_timeout=60.0).start()\n"
        "print(' '.join(str(p.popen.pid) for p in s.procs), flush=True)\n"
        "time.sleep(600)\n")
    owner = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        line = owner.stdout.readline()
        pids = [int(p) for p in line.split()]
        assert pids, "the stack did not start"
        for pid in pids:
            os.kill(pid, 0)  # running
        owner.kill()  # SIGKILL: no handler, no cleanup in the owner
        owner.wait(10)
        wait_until(lambda: not any(_running(p) for p in pids), 60.0,
                   "the nodes to die with their stack's owner", poll=0.2,
                   detail=lambda: f"still running: {[p for p in pids if _running(p)]}")
    finally:
        stop_process(owner, group=False)


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[-1][0] != "Z"  # a zombie has exited
    except FileNotFoundError:
        return False


def _panda_params(tmp_path: Path, base: list[float] | None, outcome: str = "clouds",
                  bridge_base: list[float] | None = None) -> Path:
    """config/w2e_stack.yaml with the bridge's simulated Panda switched on; ``base`` for the
    whole stack (its /** section), ``bridge_base`` for the bridge alone."""
    import yaml

    from w2e_ros.bringup import default_params

    data = yaml.safe_load(default_params().read_text())
    data["sim_bridge"]["ros__parameters"]["robot"] = "panda"
    if base is not None:
        data["/**"]["ros__parameters"]["arm_base_pose"] = base
    if bridge_base is not None:
        data["sim_bridge"]["ros__parameters"]["arm_base_pose"] = bridge_base
    data["executor"]["ros__parameters"]["outcome_source"] = outcome
    path = tmp_path / "panda.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


PANDA_BASE = [0.95, 0.0, 0.1, 0.0, 0.0, 1.0, 0.0]


def test_robot_panda_brings_up_the_arm_adapter_live_on_the_bridges_base(tmp_path):
    from w2e_ros.bringup import Stack, node_parameters

    flying = Stack(output=None)
    assert "arm_adapter" not in [s.name for s in flying.specs]
    assert "follow_waypoints" in flying.specs[0].actions
    stack = Stack(params=_panda_params(tmp_path, PANDA_BASE), output=None)
    assert [s.name for s in stack.specs] == ["sim_bridge", "arm_adapter", "segmentation",
                                             "inference", "executor", "planner"]
    bridge, adapter = stack.specs[:2]
    # the bridge is up when it serves the Panda's side; follow_waypoints is the adapter's
    assert bridge.actions == () and "joint_states" in bridge.publishers
    assert adapter.actions == ("follow_waypoints",)
    cmd = " ".join(stack.command(adapter, stack.params))
    assert "dry_run:=false" in cmd and "gripper_interface:=gripper_command" in cmd
    # the base from the file's one /** entry, the same for the bridge, adapter and planner
    for node in ("sim_bridge", "arm_adapter", "planner_node"):
        assert node_parameters(stack.params, node)["arm_base_pose"] == PANDA_BASE


def test_robot_panda_without_what_it_needs_fails_at_once_naming_it(tmp_path):
    """The bring-up that hung 120 s ("nodes ['sim_bridge'] were not up") now says at once what
    the configuration lacks, as a user running ``w2e bringup`` sees it: the check's message,
    not the wait for nodes that cannot come up ("were not up after")."""
    params = _panda_params(tmp_path, None, "joints", bridge_base=PANDA_BASE)
    res = subprocess.run([W2E, "bringup", "--params", str(params),
                          "--domain-id", str(pick_domain_id())], env=ros_env(),
                         capture_output=True, text=True, timeout=100)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "were not up" not in res.stderr
    assert "Traceback" not in res.stderr
    assert "sim_bridge robot: panda needs one arm_base_pose" in res.stderr, res.stderr
    assert f"sim_bridge {PANDA_BASE}, arm_adapter [0.95, 0.0, 0.0" in res.stderr, res.stderr
    assert "executor outcome_source: clouds" in res.stderr, res.stderr
    assert "is up" not in res.stdout  # nothing was started


def test_w2e_bringup_with_robot_panda_comes_up_without_a_separate_adapter(tmp_path):
    proc = subprocess.Popen(
        [W2E, "bringup", "--params", str(_panda_params(tmp_path, PANDA_BASE)), "--nodes",
         "sim_bridge", "arm_adapter", "executor", "--domain-id", str(pick_domain_id()),
         "--log-dir", str(tmp_path / "log"), "--timeout", "150"],
        env=ros_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    lines: list[str] = []
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line.rstrip("\n"))
            if "stack is up" in line:
                break
        assert any("stack is up" in x for x in lines), "\n".join(lines[-40:])
        assert any("node arm_adapter is up" in x for x in lines)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0
    finally:
        stop_process(proc, group=False)
