"""Faults that are not a dead node, as bench/fault_injection.py injects them, from a user's
plain clients in separate processes against the whole stack:

* a camera that stops publishing mid-explore (the bridge's live ``publish_camera``): the call
  ends within ``frame_timeout_s`` naming the camera, instead of going on with the clouds seen
  before (40 s of ``observe_timeout_s`` per object, acting on stale clouds);
* a trial the robot side never answers (``hold_trials``: a live controller that hangs): the
  call ends at the executor's ``trial_timeout_s`` naming it, and nothing is recorded for the
  trial (it was logged as an invalid interaction and learned as a failure, and the call went
  on to the next one, which hung too).

After each, the next call of the session resumes and completes, the log numbered 1..n.
"""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from scenes import Tee
from test_resume import (
    CATEGORY,
    PRIMITIVE,
    STATUS,
    ActionUser,
    _events,
    _explore_service,
    _interactions,
)

from w2e_ros.bringup import Stack, random_model_args
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env

pytestmark = pytest.mark.slow
clean_shm_at_exit()

TRIAL_TIMEOUT_S = 5.0
FRAME_TIMEOUT_S = 5.0  # the planner's default

# Another user's process, as `ros2 param set sim_bridge <name> <bool>` is: one per line on
# stdin, "ok" or the refusal on stdout (started before it is needed: a Python with rclpy takes
# seconds to start).
PARAM_SETTER = """
import sys
import rclpy
from rclpy.parameter import Parameter
from rcl_interfaces.srv import SetParameters
rclpy.init()
node = rclpy.create_node("user_param_set")
cli = node.create_client(SetParameters, "sim_bridge/set_parameters")
assert cli.wait_for_service(timeout_sec=60.0)
print("ready", flush=True)
for line in sys.stdin:
    name, value = line.split()
    req = SetParameters.Request(parameters=[
        Parameter(name, Parameter.Type.BOOL, value == "true").to_parameter_msg()])
    future = cli.call_async(req)
    rclpy.spin_until_future_complete(node, future, timeout_sec=10.0)
    r = future.result()
    print("ok" if r and r.results[0].successful else f"refused {r}", flush=True)
"""


class ParamSetter:
    def __init__(self, env: dict[str, str]) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", PARAM_SETTER], env=env, text=True,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=1)
        assert self.proc.stdout.readline().strip() == "ready"

    def set(self, name: str, value: bool) -> None:
        self.proc.stdin.write(f"{name} {'true' if value else 'false'}\n")
        self.proc.stdin.flush()
        said = self.proc.stdout.readline().strip()
        assert said == "ok", said

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(10)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("faults")
    domain = pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=tmp / "ros_log")
    log_dir = tmp / "exploration"
    extra = {
        "inference": [*random_model_args(tmp), "-p", "finetune_steps:=2"],
        "executor": ["-p", f"trial_timeout_s:={TRIAL_TIMEOUT_S}"],
        "planner": ["-p", "points_per_object:=64", "-p", f"exploration_log_dir:={log_dir}",
                    "-p", "execute_timeout_s:=20.0", "-p", "observe_timeout_s:=40.0"],
    }
    with Stack(env=env, output=Tee(), ready_timeout=150.0, extra_args=extra) as s:
        setter = ParamSetter(env)
        try:
            yield s, env, log_dir / f"domain{domain}", setter
        finally:
            setter.close()


def _indices(log_dir, session: str) -> list[int]:
    return [e["index"] for e in _interactions(_events(log_dir, session))]


def test_a_camera_that_stops_mid_explore_ends_the_call_naming_it_and_the_next_resumes(stack):
    s, env, log_dir, setter = stack
    goal = dict(category=CATEGORY, instances=[30], primitive=PRIMITIVE, budget=5,
                similarity_bar=1.0, session="camera")
    user = ActionUser(goal, env)
    try:
        assert user.next("goal", 60)["accepted"]
        assert user.next("feedback", 90)["step"] == 1
        setter.set("publish_camera", False)
        t_stop = time.monotonic()
        res = user.next("result", 60)
        took = time.monotonic() - t_stop
    finally:
        user.close()
        setter.set("publish_camera", True)
    print(f"\n[faults] camera stopped: the call ended {took:.1f} s later: {res['message']}")
    assert STATUS[res["status"]] == "aborted" and not res["success"], res
    assert "no frame on 'objects'" in res["message"], res
    assert took <= FRAME_TIMEOUT_S + 10.0  # it acted on the last clouds, 40 s an object
    n = res["interactions_used"]
    assert 1 <= n < 5 and _indices(log_dir, "camera") == list(range(1, n + 1))
    again = _explore_service(goal, env)
    assert again["success"] and again["resumed_from"] == n, again
    assert _indices(log_dir, "camera") == [1, 2, 3, 4, 5]
    assert all(s.alive().values())


def test_a_trial_the_robot_never_answers_ends_the_call_and_records_nothing(stack):
    s, env, log_dir, setter = stack
    goal = dict(category=CATEGORY, instances=[31], primitive=PRIMITIVE, budget=2,
                similarity_bar=1.0, session="hang")
    setter.set("hold_trials", True)  # the robot side accepts the first trial, never answers
    try:
        t0 = time.monotonic()
        res = _explore_service(goal, env, timeout=120.0)
        took = time.monotonic() - t0
    finally:
        setter.set("hold_trials", False)
    print(f"\n[faults] trial held: the call ended after {took:.1f} s: {res['message']}")
    assert not res["success"] and "did not answer in time" in res["message"], res
    # nothing is known of the held trial: no interaction recorded, none learned from
    assert res["interactions_used"] == 0 and _indices(log_dir, "hang") == []
    assert not [e for e in _events(log_dir, "hang") if e["event"] == "update"]
    again = _explore_service(goal, env)
    assert again["success"] and again["interactions_used"] == 2, again
    assert _indices(log_dir, "hang") == [1, 2]
    assert all(s.alive().values())
