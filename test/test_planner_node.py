"""The planner node as a user's own code meets it: plain rclpy clients in separate processes.

A second explore or manipulate sent while an explore runs must answer "busy" at once, as
docs/ros_api.md says, not wait silently until the first one ends (the services once shared a
mutually exclusive callback group: measured, no answer within 30 s while a budget-3 explore
ran). "At once" is asserted as "while the first explore still ran": each client prints the
system-wide CLOCK_MONOTONIC at its answer, and the busy answers must come before the first
one's, which comes after its observe timeout.
"""

from __future__ import annotations

import io
import json
import subprocess
import sys
import threading
import time

import pytest

from w2e_ros.bringup import Stack
from w2e_ros.core.exploration.strategies import STRATEGIES
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env

pytestmark = pytest.mark.slow
clean_shm_at_exit()

OBSERVE_TIMEOUT_S = 12.0  # how long the first explore runs: it waits for objects that never come

# A user's client: waits for the service, says "ready", sends one request when told "go" on
# stdin, says "sent", then prints the answer, how long it took and when (CLOCK_MONOTONIC, the
# same clock in every process of the machine) as one JSON line.
CLIENT = """
import json, os, sys, time
import rclpy
from w2e_msgs.srv import Explore, Manipulate

verb = sys.argv[1]
srv = {"explore": Explore, "manipulate": Manipulate}[verb]
rclpy.init()
node = rclpy.create_node(f"user_{verb}_{os.getpid()}")
cli = node.create_client(srv, verb)
assert cli.wait_for_service(timeout_sec=60.0), "no service"
req = srv.Request(primitive="push")
if verb == "explore":
    req.budget = 1
print("ready", flush=True)
sys.stdin.readline()
t0 = time.monotonic()
future = cli.call_async(req)
print("sent", flush=True)
rclpy.spin_until_future_complete(node, future, timeout_sec=float(sys.argv[2]))
res = future.result()
print(json.dumps({"answered": res is not None, "seconds": time.monotonic() - t0,
                  "at": time.monotonic(),
                  "success": bool(res.success) if res else None,
                  "message": res.message if res else ""}), flush=True)
node.destroy_node()
rclpy.try_shutdown()
"""


def _client(verb: str, env: dict[str, str], wait_s: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", CLIENT, verb, str(wait_s)], env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)


def _expect(proc: subprocess.Popen, word: str) -> None:
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    assert line == word, f"client said {line!r}, expected {word!r}"


def _go(proc: subprocess.Popen) -> None:
    assert proc.stdin is not None
    proc.stdin.write("go\n")
    proc.stdin.flush()


def _answer(proc: subprocess.Popen, timeout: float) -> dict:
    """The client's JSON line, read as soon as it is printed.

    Only the answer is under test: the client's own teardown (rclpy shutdown, DDS threads)
    once hung for a minute on CI after the answer was out, so its exit is not waited for.
    """
    assert proc.stdout is not None
    seen: list[str] = []
    answer: list[dict] = []

    def read() -> None:
        for line in proc.stdout:
            seen.append(line)
            if line.startswith("{"):
                answer.append(json.loads(line))
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    assert answer, f"no answer within {timeout} s (rc={proc.poll()}): {''.join(seen)!r}"
    return answer[0]


def test_a_second_request_while_explore_runs_answers_busy_at_once(tmp_path):
    env = ros_env(domain_id=pick_domain_id(), log_dir=tmp_path / "ros_log")
    # no camera at all: without a longer frame_timeout_s the wait would end at it (5 s)
    extra = {"planner": ["-p", f"observe_timeout_s:={OBSERVE_TIMEOUT_S}",
                         "-p", f"frame_timeout_s:={2 * OBSERVE_TIMEOUT_S}",
                         "-p", f"exploration_log_dir:={tmp_path / 'exploration'}"]}
    with Stack(nodes=["planner"], env=env, output=io.StringIO(), extra_args=extra):
        # the scene is empty (no segmentation node): the first explore waits for objects
        first = _client("explore", env, 60.0)
        # a waiting service shows as an answer after the first one's or none at all
        others = [_client("explore", env, 60.0), _client("manipulate", env, 60.0)]
        try:
            for proc in (first, *others):
                _expect(proc, "ready")
            _go(first)
            _expect(first, "sent")
            # the first request reaches its handler (nothing outside the node shows when;
            # too short a wait fails the test: the first one would answer "busy", not hide it)
            time.sleep(2.0)
            for proc in others:
                _go(proc)
            answers = {verb: _answer(proc, 90)
                       for verb, proc in zip(("explore", "manipulate"), others, strict=True)}
            done = _answer(first, 90)
            # the first one ran to its end: no objects seen, a real answer, not "busy"
            assert done["answered"] and done["success"] is False, done
            assert "busy" not in done["message"] and "not seen" in done["message"], done
            assert done["seconds"] >= OBSERVE_TIMEOUT_S - 0.5, done  # it waited for objects
            for verb, got in answers.items():
                assert got["answered"], f"second {verb}: no answer while explore ran"
                assert got["success"] is False and "busy" in got["message"], got
                assert got["at"] < done["at"], f"second {verb}: 'busy' only after the wait: {got}"
                print(f"\n[planner] second {verb}: busy in {got['seconds']:.2f} s, "
                      f"{done['at'] - got['at']:.1f} s before the first explore ended")
        finally:
            for proc in (first, *others):
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()


@pytest.mark.parametrize("strategy, words", [("geometry", "is an experiment"),
                                             ("oracle", "is an experiment"),
                                             ("simlarity", "unknown strategy")])
def test_a_strategy_the_stack_cannot_run_stops_the_planner_at_start_up(tmp_path, strategy, words):
    """geometry needs the training collection and oracle hindsight labels, and both are
    experiments: the planner says so and names the rules it runs, and exits, instead of failing
    at the first explore request."""
    env = ros_env(domain_id=pick_domain_id(), log_dir=tmp_path / "ros_log")
    proc = subprocess.run([sys.executable, "-m", "w2e_ros.nodes.planner_node", "--ros-args",
                           "-p", f"strategy:={strategy}"], env=env, capture_output=True,
                          text=True, timeout=60)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0, out
    assert words in out and strategy in out, out
    assert f"the rules: {', '.join(STRATEGIES)}" in out, out


# A user's code changing the planner's parameters between calls, as `ros2 param set` does.
SET_PARAMS = """
import json, sys
import rclpy
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters

rclpy.init()
node = rclpy.create_node("user_params")
set_cli = node.create_client(SetParameters, "planner_node/set_parameters")
get_cli = node.create_client(GetParameters, "planner_node/get_parameters")
assert set_cli.wait_for_service(timeout_sec=60.0) and get_cli.wait_for_service(timeout_sec=60.0)


def call(cli, req):
    future = cli.call_async(req)
    rclpy.spin_until_future_complete(node, future, timeout_sec=30.0)
    return future.result()


out = []
for name, kind, value in json.loads(sys.argv[1]):
    v = ParameterValue(type=kind)
    if kind == ParameterType.PARAMETER_STRING:
        v.string_value = value
    else:
        v.integer_value = value
    (r,) = call(set_cli, SetParameters.Request(parameters=[Parameter(name=name, value=v)])).results
    (now,) = call(get_cli, GetParameters.Request(names=["strategy"])).values
    out.append({"name": name, "ok": r.successful, "reason": r.reason,
                "strategy": now.string_value})
print(json.dumps(out), flush=True)
"""


def test_strategy_and_seed_change_between_calls_and_nothing_else_does(tmp_path):
    """``strategy`` is a live parameter (w2e demo runs two rules on one stack so): a user-facing
    rule is taken, an experiment or a typo refused with the allowed rules named, and a
    parameter the planner reads at start-up refused with what to do instead."""
    env = ros_env(domain_id=pick_domain_id(), log_dir=tmp_path / "ros_log")
    string, integer = 4, 2  # rcl_interfaces ParameterType
    sets = [("strategy", string, "similarity"), ("strategy", string, "coverage_success"),
            ("strategy", string, "simlarity"), ("seed", integer, 7),
            ("points_per_object", integer, 8)]
    with Stack(nodes=["planner"], env=env, output=io.StringIO()):
        proc = subprocess.run([sys.executable, "-c", SET_PARAMS, json.dumps(sets)], env=env,
                              capture_output=True, text=True, timeout=180)
    lines = [x for x in proc.stdout.splitlines() if x.startswith("[")]
    assert lines, proc.stdout + proc.stderr
    took, experiment, typo, seed, startup = json.loads(lines[-1])
    assert took["ok"] and took["strategy"] == "similarity", took
    assert not experiment["ok"] and "is an experiment" in experiment["reason"], experiment
    assert experiment["strategy"] == "similarity"  # unchanged by a refused set
    assert not typo["ok"] and "unknown strategy" in typo["reason"], typo
    assert seed["ok"], seed
    assert not startup["ok"] and "restart the planner" in startup["reason"], startup
