"""``--respawn`` no longer hides a dead node (issue 28, defect 2), driven as a user would: the
whole stack from ``w2e bringup``'s Stack with respawn and the planner's default timeouts
(service 120 s, execute 60 s), a plain rclpy action client in another process, SIGKILL of a
node mid-explore. The respawned node takes the same name; the explore used to wait its whole
timeout (119.7 s for the inference node, 57 s for the executor). Now it ends soon after the
kill (within 10 s here; printed, not asserted: a loaded machine's discovery sets it), naming the
node ("restarted" / "is gone", which only the peer check says), and the session's next call
resumes (test_resume.py checks the resume).

The models have random weights (as in test_resume.py): this checks the plumbing.
"""

from __future__ import annotations

import os
import signal
import time

import pytest
from scenes import Tee
from test_resume import CATEGORY, PRIMITIVE, STATUS, ActionUser
from waits import wait_until

from w2e_ros.bringup import Stack, random_model_args
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env

pytestmark = pytest.mark.slow
clean_shm_at_exit()

@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("respawn")
    env = ros_env(domain_id=pick_domain_id(), log_dir=tmp / "ros_log")
    extra = {
        "inference": [*random_model_args(tmp), "-p", "finetune_steps:=2"],
        # the default service / execute timeouts (120 s / 60 s): the kill must be seen anyway
        "planner": ["-p", "points_per_object:=64",
                    "-p", f"exploration_log_dir:={tmp / 'exploration'}"],
    }
    out = Tee()
    with Stack(env=env, output=out, ready_timeout=150.0, extra_args=extra, respawn=True,
               respawn_delay=0.5) as s:
        yield s, env, out


@pytest.mark.parametrize("victim, server", [("inference", "inference_node"),
                                            ("executor", "executor")])
def test_a_node_killed_and_respawned_mid_explore_ends_the_explore_naming_it(
        stack, victim, server):
    s, env, out = stack
    s.wait_ready(120)
    goal = dict(category=CATEGORY, instances=[32], primitive=PRIMITIVE, budget=4,
                similarity_bar=1.0, session=f"kill_{victim}")
    user = ActionUser(goal, env)
    try:
        assert user.next("goal", 60)["accepted"]
        assert user.next("feedback", 90)["step"] == 1
        before = s.respawns.get(victim, 0)
        pid = s.pid(victim)
        os.kill(pid, signal.SIGKILL)
        t_kill = time.monotonic()
        res = user.next("result", 100)  # the timeouts it must not wait: 120 s / 60 s
        took = time.monotonic() - t_kill
    finally:
        user.close()
    print(f"\n[respawn] {victim} killed; the explore ended {took:.1f} s later: "
          f"{res['message']}")
    assert STATUS[res["status"]] == "aborted" and not res["success"], res
    assert f"{server} restarted" in res["message"] or f"{server} is gone" in res["message"]
    assert "the next explore of this session continues" in res["message"]
    wait_until(lambda: s.respawns.get(victim, 0) > before, 60.0, f"{victim} respawned",
               poll=0.2)
    assert s.respawns.get(victim, 0) == before + 1 and s.pid(victim) != pid
