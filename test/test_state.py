"""Each stack keeps its exploration state to itself: the session logs and the fine-tuned
checkpoints go under a directory named for the stack (ROS domain and namespace, or the
``state_scope`` parameter), a stack never resumes another's run, and a refused request
creates nothing on disk."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.node import Node

from w2e_ros.core.exploration.session_log import open_session
from w2e_ros.core.robot.primitives import Action, TrialResult
from w2e_ros.ros.params import ParameterError
from w2e_ros.ros.processes import (
    clean_shm_at_exit,
    pick_domain_id,
    ros_env,
    stop_process,
)
from w2e_ros.ros.state import scoped_dir, state_scope

clean_shm_at_exit()


@pytest.mark.parametrize("domain,namespace,explicit,scope", [
    (0, "/", "", "domain0"),
    (7, "/lab/arm1", "", "domain7.lab.arm1"),
    (0, "/lab", "cell_2", "cell_2"),
])
def test_the_scope_is_the_domain_and_namespace_or_the_parameter(domain, namespace, explicit,
                                                                 scope):
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node("planner_node", namespace=namespace, context=ctx)
    try:
        assert state_scope(node, explicit) == scope
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_a_deep_namespace_and_a_bad_explicit_scope():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=3)
    a = Node("n", namespace="/" + "/".join(["segment_of_a_long_namespace"] * 4), context=ctx)
    b = Node("n", namespace="/" + "/".join(["segment_of_a_long_namespace"] * 5), context=ctx)
    try:
        sa, sb = state_scope(a), state_scope(b)
        assert len(sa) <= 64 and len(sb) <= 64 and sa != sb and sa.startswith("domain3.")
        with pytest.raises(ParameterError, match="state_scope"):
            state_scope(a, "../other")
    finally:
        a.destroy_node()
        b.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _record_one(run) -> None:
    action = Action(np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0]), "pull")
    result = TrialResult(True, True, np.array([0.1, 0.0]), 0, "door")
    run.append(1, None, action, result, np.zeros((8, 3)), np.zeros((8, 3)))


def test_a_stack_never_resumes_another_stacks_run(tmp_path: Path):
    base = tmp_path / "exploration"
    mine = open_session(scoped_dir(base, "domain0.a"), "", "door", "pull")
    mine.start({"budget": 3})
    _record_one(mine)  # interrupted: no "end"
    theirs = open_session(scoped_dir(base, "domain0.b"), "", "door", "pull")
    assert theirs.count == 0 and not theirs.path.is_relative_to(base / "domain0.a")
    # the same stack, restarted, continues its own run
    assert open_session(scoped_dir(base, "domain0.a"), "", "door", "pull").count == 1


def test_opening_a_run_creates_nothing_until_the_run_starts(tmp_path: Path):
    run = open_session(tmp_path / "exploration", "s", "door", "pull")
    assert not (tmp_path / "exploration").exists()
    run.start({})
    assert (run.path / "events.jsonl").is_file() and (run.path / "clouds").is_dir()


# A user's client: one explore request to <namespace>/explore, the answer as one JSON line.
CLIENT = """
import json, sys
import rclpy
from w2e_msgs.srv import Explore
rclpy.init()
node = rclpy.create_node("user_explore")
cli = node.create_client(Explore, sys.argv[1] + "/explore")
assert cli.wait_for_service(timeout_sec=60.0), "no service"
future = cli.call_async(Explore.Request(primitive="pull", budget=1, session="lab"))
rclpy.spin_until_future_complete(node, future, timeout_sec=60.0)
res = future.result()
print(json.dumps({"success": bool(res.success), "message": res.message}), flush=True)
node.destroy_node()
rclpy.try_shutdown()
"""


def _planner(namespace: str, base: Path, env: dict[str, str]) -> tuple[subprocess.Popen, str]:
    """A planner node process in ``namespace``; the directory it says it keeps sessions in."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "w2e_ros.nodes.planner_node", "--ros-args",
         "-r", f"__ns:={namespace}", "-p", f"exploration_log_dir:={base}",
         "-p", "observe_timeout_s:=1.0", "-p", "settle_s:=0.0"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        if "exploration sessions in " in line:
            return proc, line.split("exploration sessions in ", 1)[1].strip()
    stop_process(proc)
    raise AssertionError(f"planner in {namespace} did not start: rc={proc.poll()}")


def test_two_stacks_keep_apart_and_a_refused_explore_leaves_nothing(tmp_path: Path):
    domain = pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=tmp_path / "ros_log")
    base = tmp_path / "exploration"  # the same directory given to both, as a shared YAML does
    procs = []
    try:
        a, dir_a = _planner("/a", base, env)
        procs.append(a)
        b, dir_b = _planner("/b", base, env)
        procs.append(b)
        assert Path(dir_a) == base / f"domain{domain}.a"
        assert Path(dir_b) == base / f"domain{domain}.b"
        # no segmentation node: the explore is refused (no objects seen) ...
        res = subprocess.run([sys.executable, "-c", CLIENT, "/a"], env=env, text=True,
                             capture_output=True, timeout=120)
        assert res.returncode == 0, res.stderr
        answer = json.loads(res.stdout.strip().splitlines()[-1])
        assert answer["success"] is False and answer["message"], answer
        # ... and leaves no run directory behind
        assert not base.exists() or not any(base.rglob("*")), sorted(base.rglob("*"))
    finally:
        for p in procs:
            stop_process(p)
