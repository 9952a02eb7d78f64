"""Operations a lab expects, driven as a user's own code would: plain rclpy clients in separate
processes against the whole stack (bridge, segmentation, inference, executor, planner) started
with respawn.

* ``explore`` as an action: feedback per executed interaction, a second goal while one runs is
  rejected, cancel stops between interactions and keeps what was executed (on disk, learned).
* Resume: SIGKILL the inference node and the executor mid-explore; bringup restarts them; the
  next call of the session continues where the run stopped: the interactions on disk continue,
  none recorded is lost, and the budget they spent counts.

The models have random weights (as in test_stack_integration.py): this checks the plumbing.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from scenes import Tee
from waits import wait_until

from w2e_ros.bringup import Stack, random_model_args
from w2e_ros.core.exploration.session_log import EVENTS, session_dir
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env

pytestmark = pytest.mark.slow
clean_shm_at_exit()

CATEGORY, PRIMITIVE = "door", "pull"  # novel for the default combination cfw
STATUS = {4: "succeeded", 5: "canceled", 6: "aborted"}  # action_msgs/GoalStatus

# A user's action client: sends one goal (JSON in argv[1]), prints the goal's acceptance, each
# feedback and the result as JSON lines; on stdin, "cancel" cancels the goal and "second"
# sends a second goal while the first runs (printing whether it was accepted).
ACTION_CLIENT = """
import json, os, sys, threading
import rclpy
from rclpy.action import ActionClient
from rclpy.executors import SingleThreadedExecutor
from w2e_msgs.action import Explore

def say(**kw):
    print(json.dumps(kw), flush=True)

def wait(future, timeout=120.0):
    done = threading.Event()
    future.add_done_callback(lambda _f: done.set())
    done.wait(timeout)
    return future.result()

rclpy.init()
node = rclpy.create_node(f"user_explore_action_{os.getpid()}")
client = ActionClient(node, Explore, "explore")
executor = SingleThreadedExecutor()
executor.add_node(node)
spinner = threading.Thread(target=executor.spin, daemon=True)
spinner.start()
if not client.wait_for_server(timeout_sec=60.0):
    say(kind="error", message="no explore action server")
    sys.exit(1)

def on_feedback(msg):
    p = msg.feedback.progress
    say(kind="feedback", step=p.step, budget=p.budget, object_id=p.interaction.object_id,
        success=p.outcome.success, valid=p.outcome.valid,
        similarity=p.predicted_similarity, mean_similarity=p.mean_similarity)

goal = Explore.Goal(**json.loads(sys.argv[1]))
handle = wait(client.send_goal_async(goal, feedback_callback=on_feedback))
say(kind="goal", accepted=bool(handle.accepted))
if not handle.accepted:
    sys.exit(0)
result = handle.get_result_async()

def commands():
    for line in sys.stdin:
        if line.strip() == "cancel":
            handle.cancel_goal_async()
            say(kind="cancel_sent")
        elif line.strip() == "second":
            other = wait(client.send_goal_async(goal))
            say(kind="second", accepted=bool(other.accepted))

threading.Thread(target=commands, daemon=True).start()
r = wait(result, 600.0)
res = r.result
say(kind="result", status=int(r.status), success=bool(res.success),
    interactions_used=int(res.interactions_used), resumed_from=int(res.resumed_from),
    checkpoint_path=res.checkpoint_path, message=res.message)
executor.shutdown()
spinner.join()
node.destroy_node()
rclpy.try_shutdown()
"""

# A user's service client: one explore request (JSON in argv[1]), the response as JSON.
SERVICE_CLIENT = """
import json, os, sys
import rclpy
from w2e_msgs.srv import Explore

rclpy.init()
node = rclpy.create_node(f"user_explore_service_{os.getpid()}")
cli = node.create_client(Explore, "explore")
assert cli.wait_for_service(timeout_sec=60.0), "no explore service"
future = cli.call_async(Explore.Request(**json.loads(sys.argv[1])))
rclpy.spin_until_future_complete(node, future, timeout_sec=300.0)
r = future.result()
print(json.dumps({"success": bool(r.success), "interactions_used": int(r.interactions_used),
                  "successes": int(r.successes), "resumed_from": int(r.resumed_from),
                  "checkpoint_path": r.checkpoint_path, "message": r.message}), flush=True)
node.destroy_node()
rclpy.try_shutdown()
"""


class ActionUser:
    """The action client process, its JSON lines read as they come."""

    def __init__(self, goal: dict, env: dict[str, str]) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", ACTION_CLIENT, json.dumps(goal)],
                                     env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, bufsize=1)
        self.lines: queue.Queue[dict] = queue.Queue()
        self.seen: list[dict] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.startswith("{"):
                self.lines.put(json.loads(line))

    def next(self, kind: str, timeout: float) -> dict:
        end = time.monotonic() + timeout
        while (left := end - time.monotonic()) > 0:
            try:
                msg = self.lines.get(timeout=left)
            except queue.Empty:
                break
            self.seen.append(msg)
            assert msg["kind"] != "error", msg
            if msg["kind"] == kind:
                return msg
        raise AssertionError(f"no {kind!r} from the client within {timeout:.0f} s; "
                             f"seen {self.seen}")

    def send(self, word: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(word + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()


def _explore_service(request: dict, env: dict[str, str], timeout: float = 300.0) -> dict:
    proc = subprocess.run([sys.executable, "-c", SERVICE_CLIENT, json.dumps(request)], env=env,
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _events(log_dir: Path, session: str) -> list[dict]:
    path = session_dir(log_dir, session, CATEGORY, PRIMITIVE) / "run-0001" / EVENTS
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def _interactions(events: list[dict]) -> list[dict]:
    return [e for e in events if e["event"] == "interaction"]


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("resume")
    domain = pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=tmp / "ros_log")
    out = Tee()
    log_dir = tmp / "exploration"
    extra = {
        "inference": [*random_model_args(tmp), "-p", "finetune_steps:=2"],
        # a killed server is noticed by its missing answer: short waits keep the test short
        "planner": ["-p", "points_per_object:=64", "-p", f"exploration_log_dir:={log_dir}",
                    "-p", "execute_timeout_s:=15.0", "-p", "service_timeout_s:=15.0",
                    "-p", "observe_timeout_s:=40.0", "-p", "connect_timeout_s:=5.0"],
    }
    with Stack(env=env, output=out, ready_timeout=150.0, extra_args=extra, respawn=True,
               respawn_delay=0.5) as s:
        yield s, env, log_dir / f"domain{domain}", out  # the stack's state scope


def test_explore_action_feedback_busy_goal_rejected_and_cancel_between_interactions(stack):
    s, env, log_dir, _ = stack
    t0 = time.monotonic()
    goal = dict(category=CATEGORY, instances=[30], primitive=PRIMITIVE, budget=4,
                similarity_bar=1.0, session="cancel")
    user = ActionUser(goal, env)
    try:
        assert user.next("goal", 60)["accepted"]
        fb = user.next("feedback", 60)  # interaction 1, after its model update
        assert fb["step"] == 1 and fb["budget"] == 4 and fb["object_id"] > 0
        assert 0.0 <= fb["similarity"] <= 1.0 and 0.0 <= fb["mean_similarity"] <= 1.0
        user.send("second")  # one goal at a time, like the service's "busy"
        assert user.next("second", 30)["accepted"] is False
        user.send("cancel")
        user.next("cancel_sent", 10)
        n_at_cancel = len(_interactions(_events(log_dir, "cancel")))
        res = user.next("result", 60)
    finally:
        user.close()
    print(f"\n[resume] cancel: {time.monotonic() - t0:.1f} s: {res['message']}")
    assert STATUS[res["status"]] == "canceled" and not res["success"], res
    assert "cancelled after" in res["message"]
    # stopped between interactions: at most the one running when the cancel came finished
    n = res["interactions_used"]
    assert 1 <= n_at_cancel <= n <= n_at_cancel + 1 and n < 4, (n_at_cancel, res)
    steps = [m["step"] for m in user.seen if m["kind"] == "feedback"]
    assert steps == list(range(1, len(steps) + 1)) and len(steps) <= n
    # what was executed is on disk and learned from (the last update covers all of it), the
    # run is left open for the next call, and nothing starts after the cancel
    events = _events(log_dir, "cancel")
    assert [e["index"] for e in _interactions(events)] == list(range(1, n + 1))
    updates = [e for e in events if e["event"] == "update"]
    assert updates and updates[-1]["interactions"] == n
    assert Path(updates[-1]["checkpoint"]).exists() and res["checkpoint_path"]
    assert events[-1]["event"] == "end" and events[-1]["stopped"] == "cancelled"
    assert not events[-1]["complete"]
    time.sleep(2.0)  # the behaviour: time passes after the run's proven end, nothing starts
    assert len(_interactions(_events(log_dir, "cancel"))) == n


def test_killed_nodes_are_respawned_and_the_next_explore_continues_where_it_stopped(stack):
    s, env, log_dir, out = stack
    t0 = time.monotonic()
    # the default session, as a plain request; one door, three interactions in all
    goal = dict(category=CATEGORY, instances=[31], primitive=PRIMITIVE, budget=3,
                similarity_bar=1.0)
    user = ActionUser(goal, env)
    try:
        assert user.next("goal", 60)["accepted"]
        assert user.next("feedback", 60)["step"] == 1
        killed = {name: s.pid(name) for name in ("inference", "executor")}
        for pid in killed.values():
            os.kill(pid, signal.SIGKILL)
        t_kill = time.monotonic()
        recorded = _interactions(_events(log_dir, ""))
        res = user.next("result", 90)
    finally:
        user.close()
    print(f"\n[resume] killed after {t_kill - t0:.1f} s, the goal ended "
          f"{time.monotonic() - t_kill:.1f} s later: {res['message']}")
    assert STATUS[res["status"]] == "aborted" and not res["success"], res
    first = _interactions(_events(log_dir, ""))
    assert 1 <= len(recorded) <= len(first) == res["interactions_used"] < 3
    assert first[:len(recorded)] == recorded
    # bringup restarted both, said so, and they come back up
    wait_until(lambda: s.respawns == {"inference": 1, "executor": 1}, 60.0,
               "both nodes respawned", poll=0.2, detail=lambda: str(s.respawns))
    for name in killed:
        assert any(f"node {name} died (SIGKILL); restart 1 of" in x for x in out.lines)
        assert s.pid(name) != killed[name]
    s.wait_ready(90)
    t_up = time.monotonic()
    # the next call of the session (the plain service this time) continues the run
    again = _explore_service(goal, env)
    print(f"[resume] respawned and up {t_up - t_kill:.1f} s after the kill; the next call "
          f"took {time.monotonic() - t_up:.1f} s: {again['message']}")
    assert again["success"], again
    assert again["resumed_from"] == len(first) and again["interactions_used"] == 3, again
    events = _events(log_dir, "")
    inter = _interactions(events)
    assert [e["index"] for e in inter] == [1, 2, 3]  # the count on disk continues
    assert inter[:len(first)] == first  # nothing recorded is lost or rewritten
    assert [e["resumed_from"] for e in events if e["event"] == "run"] == [0, len(first)]
    updates = [e for e in events if e["event"] == "update"]
    assert updates[-1]["interactions"] == 3 and Path(updates[-1]["checkpoint"]).exists()
    assert events[-1]["event"] == "end" and events[-1]["complete"]
    # the restarted inference node restored the session (checkpoint + recorded interactions)
    assert any(x.startswith("[inference]") and "restored" in x for x in out.lines)
    assert all(s.alive().values())
