"""The whole stack as separate processes (bridge, segmentation, inference, executor, planner),
driven by the Python client from the test process: explore (budget 2) and manipulate run real
trials in the simulator, and the model is really fine-tuned.

The models have random weights (saved to tmp by the core's API), so this checks the plumbing
and the learning step, not the success rate.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import torch
from rclpy.node import Node
from rclpy.time import Time
from scenes import Tee
from sensor_msgs.msg import JointState
from waits import wait_until

from sim_bridge.objects import make_object
from w2e_ros.bringup import Stack
from w2e_ros.client import W2EClient
from w2e_ros.core.model.network import W2EModel, load_model, save_model
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env
from w2e_ros.ros.qos import RELIABLE_QOS

pytestmark = pytest.mark.slow
clean_shm_at_exit()

CATEGORY = "door"  # novel for the default combination cfw
EXPLORE_INSTANCES = [30, 31]
TEST_INSTANCES = [40, 41, 42]


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("stack")
    ckpt = {}
    for i, prim in enumerate(("push", "pull")):
        torch.manual_seed(i)
        ckpt[prim] = save_model(tmp / f"{prim}.pt", W2EModel(), {"method": "w2e",
                                                                 "combo": "cfw"})
    domain = pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=tmp / "ros_log")
    out = Tee()
    extra = {
        "inference": ["-p", f"push_checkpoint:={ckpt['push']}",
                      "-p", f"pull_checkpoint:={ckpt['pull']}",
                      "-p", f"adapted_dir:={tmp / 'adapted'}", "-p", "finetune_steps:=2"],
        "planner": ["-p", "points_per_object:=128", "-p", "execute_timeout_s:=30.0",
                    "-p", "observe_timeout_s:=40.0",  # a loaded CI machine can stall frames
                    "-p", "connect_timeout_s:=3.0",
                    "-p", f"exploration_log_dir:={tmp / 'exploration'}"],
    }
    with Stack(env=env, output=out, ready_timeout=120.0, extra_args=extra) as s:
        client = W2EClient(domain_id=domain)
        try:
            assert client.wait_until_ready(30.0)
            yield s, client, ckpt, out
        finally:
            client.close()


def _joint_states(client: W2EClient) -> list[JointState]:
    got: list[JointState] = []
    node: Node = client.node
    node.create_subscription(JointState, "object_joint_states", got.append, RELIABLE_QOS)
    return got


def test_explore_runs_real_trials_and_fine_tunes_the_model(stack):
    s, client, ckpt, _ = stack
    joints = _joint_states(client)
    t0 = time.perf_counter()
    # budget 1 = one interaction per object: two doors, two interactions
    res = client.explore(CATEGORY, instances=EXPLORE_INSTANCES, primitive="pull", budget=1,
                         similarity_bar=0.99)
    print(f"\n[stack] explore budget 1: {time.perf_counter() - t0:.1f} s: {res.message}")
    assert res.success, res.message
    assert len(EXPLORE_INSTANCES) == 2
    assert res.interactions_used == 2 and len(res.steps) == 2
    n_joints = {len(make_object(CATEGORY, i).joint_names) for i in EXPLORE_INSTANCES}
    for st in res.steps:
        assert st.action.primitive == "pull" and 0.0 <= st.predicted_similarity <= 1.0
        assert np.isfinite(st.loss) and st.loss > 0
    # the simulator's objects: the bridge's joint states cover both loaded doors, and any
    # part motion reported by a step is the motion the bridge's state shows
    wait_until(lambda: joints, 60.0, "the bridge's object_joint_states")
    assert len(joints[-1].name) == sum(
        len(make_object(CATEGORY, i).joint_names) for i in EXPLORE_INSTANCES)
    assert n_joints and all(n >= 1 for n in n_joints)
    # the model changed: a checkpoint written after every update, weights differ
    path = Path(res.checkpoint_path)
    assert path.exists()
    adapted, meta = load_model(path, "cpu")
    orig, _ = load_model(ckpt["pull"], "cpu")
    assert meta["explored"] == 2 and meta["last_category"] == CATEGORY
    assert any(not torch.equal(a, b) for a, b in zip(adapted.state_dict().values(),
                                                     orig.state_dict().values(), strict=True))
    assert all(s.alive().values())


def test_manipulate_executes_the_best_action_on_unseen_instances(stack):
    """One unseen instance per call (alone in the scene, so the bridge's joint states of the
    object change by exactly what its trial did)."""
    s, client, _, _ = stack
    joints = _joint_states(client)
    moved = 0.0
    for inst in TEST_INSTANCES:
        joints.clear()
        t0 = time.perf_counter()
        res = client.manipulate(CATEGORY, instances=[inst], primitive="push",
                                 timeout=120.0)  # a trial takes seconds: not the 600 s default
        answered_ns = client.node.get_clock().now().nanoseconds
        print(f"\n[stack] manipulate {CATEGORY}/{inst}: {time.perf_counter() - t0:.1f} s: "
              f"{res.message}; motion {[round(o.motion, 4) for o in res.outcomes]}")
        assert len(res.outcomes) == 1, res.message
        (o,) = res.outcomes
        assert o.action.primitive == "push" and 0.0 <= o.predicted_affordance <= 1.0
        assert o.valid or o.reason  # the simulator says why a trial does not count
        # the trial ran in the simulator: the bridge's joint states of the object changed,
        # from the first message after loading to one published after the answer (the bridge
        # stamps them with the same system clock), by the joint motion
        oid = o.action.object_id

        def of_object(oid=oid, answered_ns=answered_ns) -> list[JointState]:
            seen = [m for m in list(joints) if any(n.startswith(f"{oid}/") for n in m.name)]
            late = seen and Time.from_msg(seen[-1].header.stamp).nanoseconds > answered_ns
            return seen if late else []

        seen = wait_until(of_object, 60.0, f"joint states of object {oid} after its trial")
        assert len(seen) >= 2, f"one message of object {oid}: {seen}"
        change = np.subtract(seen[-1].position, seen[0].position)
        np.testing.assert_allclose(change, o.joint_motion, atol=1e-3)
        moved = max(moved, float(np.max(np.abs(change))))
    print(f"[stack] largest joint change in the bridge: {moved:.4f}")
    # the maps of the loaded object come from the inference node
    objs = client.objects(timeout=15.0)
    maps = client.predict_maps(objs, primitive="push", num_directions=4)
    assert len(maps) == len(objs) and maps[0].affordance.shape == (len(objs[0].points),)


def test_bad_requests_and_a_dead_executor_give_errors_not_hangs(stack):
    s, client, _, _ = stack
    for kw, words in [(dict(category="spaceship"), "unknown category"),
                      (dict(budget=0), "budget"), (dict(primitive="poke"), "primitive")]:
        args = dict(category=CATEGORY, instances=[30], primitive="pull", budget=1) | kw
        r = client.explore(**args)
        assert not r.success and words in r.message
    # the executor dies: explore answers with an error within the timeouts
    executor = next(p for p in s.procs if p.spec.name == "executor")
    executor.popen.terminate()
    executor.popen.wait(timeout=20)
    # the planner's own error (its 30 s execute timeout or the service gone), not the
    # client's 120 s "no answer" (a StackCallError)
    r = client.explore(CATEGORY, instances=[30], primitive="pull", budget=1, timeout=120.0)
    assert not r.success and "execute_interaction" in r.message, r.message
    assert s.alive()["planner"] and s.alive()["inference"]
