"""The simulated Franka Panda (sim_bridge.panda): its URDF agrees with the core's kinematics,
a primitive planned by IK and executed on the arm moves a drawer, an unreachable one is refused
before anything is built, and through the stack (bridge with robot panda, the arm adapter live,
the executor) a pull sent from a separate process opens a drawer.
"""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy

from sim_bridge import panda as sim_panda
from sim_bridge.objects import make_object
from sim_bridge.physics import make_scene
from sim_bridge.world import ObjectWorld
from w2e_ros.core.robot import kinematics as kin
from w2e_ros.core.robot.primitives import Action

FK_TOLERANCE_M = 1e-5  # float32 physics poses against float64 DH
FK_TOLERANCE_RAD = 1e-5


def _drawer_cabinet() -> tuple[int, int]:
    """(instance, joint index) of the first cabinet with a drawer."""
    for i in range(50):
        for k, name in enumerate(make_object("cabinet", i).joint_names):
            if "drawer" in name:
                return i, k
    raise LookupError("no cabinet with a drawer")


def _drawer_front(world: ObjectWorld, q: np.ndarray, joint: int) -> np.ndarray:
    """The drawer's front-most point as the camera sees it (the handle side faces +x)."""
    obs = world.observe(q)
    pts = obs.points[obs.link_ids == world.models[0].movable_joints[joint].child]
    return pts[np.argmax(pts[:, 0])].astype(float)


def _rot_angle(R: np.ndarray) -> float:
    """The angle of a rotation matrix near identity (from its skew part: arccos of the trace
    loses float32's precision there)."""
    return float(np.arcsin(min(1.0, np.linalg.norm(R - R.T) / (2 * np.sqrt(2)))))


def test_urdf_hand_pose_matches_the_dh_model():
    """panda_hand of the URDF (SAPIEN's link pose) is kinematics.fk's wrist with no offset."""
    rng = np.random.default_rng(7)
    base = np.array([0.3, -0.2, 0.1, 0.0, 0.0, np.sin(0.4), np.cos(0.4)])
    scene = make_scene(1.0 / 240.0)
    arm = sim_panda.build_panda(scene, base)
    B = kin.pose_matrix(base)
    qs = np.concatenate([kin.Q_READY[None], kin.random_configurations(30, rng)])
    pos_err, rot_err = [], []
    for q in qs:
        arm.set_state(q, 0.04)
        T, F = arm.hand_pose(), B @ kin.fk(q)
        pos_err.append(np.linalg.norm(T[:3, 3] - F[:3, 3]))
        rot_err.append(_rot_angle(T[:3, :3].T @ F[:3, :3]))
    assert max(pos_err) < FK_TOLERANCE_M, max(pos_err)
    assert max(rot_err) < FK_TOLERANCE_RAD, max(rot_err)
    # and the check can fail: a joint off by 0.01 rad is seen
    arm.set_state(qs[1] + np.array([0, 0, 0, 0.01, 0, 0, 0]), 0.04)
    assert np.linalg.norm(arm.hand_pose()[:3, 3] - (B @ kin.fk(qs[1]))[:3, 3]) > 1e-3


def test_joint_names_and_limits_are_the_cores():
    scene = make_scene(1.0 / 240.0)
    arm = sim_panda.build_panda(scene, None)
    limits = np.asarray(arm.articulation.get_qlimits(), float)[arm.index[:7]]
    assert [j.name for j in arm.arm] == list(kin.PANDA_JOINTS)
    np.testing.assert_allclose(limits[:, 0], kin.Q_MIN, atol=1e-4)
    np.testing.assert_allclose(limits[:, 1], kin.Q_MAX, atol=1e-4)


@pytest.fixture(scope="module")
def drawer():
    instance, joint = _drawer_cabinet()
    model = make_object("cabinet", instance)
    world = ObjectWorld(model)
    return world, joint, sim_panda.base_in_front(world.center())


def test_arm_pull_opens_a_closed_drawer(drawer):
    world, joint, base = drawer
    q = world.joint_limits[:, 0].copy()
    point = _drawer_front(world, q, joint)
    action = Action(point, np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), "pull")
    trial = sim_panda.run_arm_trial(world, q, action, base)
    r = trial.result
    print(f"\n[panda pull] motion {r.motion[joint]:+.4f} m in {trial.duration:.1f} s, tracking "
          f"{trial.tracking_error:.4f} rad / {1000 * trial.wrist_error:.1f} mm")
    assert trial.planned and r.valid and r.success, r.reason
    assert r.target_joint == joint and r.motion[joint] > 0.01
    assert r.contact_displacement[0] > 0.01  # towards the arm, along the pull
    assert trial.wrist_error < 0.01  # the arm followed the plan within 1 cm
    # the same pull on the flying gripper agrees
    assert world.run_trial(q, action).success


def test_arm_push_closes_a_half_open_drawer(drawer):
    world, joint, base = drawer
    q = world.joint_limits[:, 0].copy()
    q[joint] = world.joint_limits[joint].mean()
    point = _drawer_front(world, q, joint)
    action = Action(point, np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), "push")
    r = sim_panda.run_arm_trial(world, q, action, base).result
    assert r.valid and r.success, r.reason
    assert r.motion[joint] < -0.01


def test_unreachable_action_is_reported_before_anything_is_built(drawer, monkeypatch):
    world, joint, base = drawer
    q = world.joint_limits[:, 0].copy()
    point = _drawer_front(world, q, joint) - np.array([1.5, 0.0, 0.0])  # behind the cabinet

    def no_scene(*_a, **_k):
        raise AssertionError("a scene was built for an unreachable action")

    monkeypatch.setattr(sim_panda, "make_scene", no_scene)
    action = Action(point, np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), "pull")
    trial = sim_panda.run_arm_trial(world, q, action, base)
    assert not trial.planned and not trial.result.valid and not trial.result.success
    assert trial.result.reason.startswith("unreachable: ")
    assert np.all(trial.result.motion == 0)


def test_live_arm_follows_a_trajectory_and_closes_the_fingers(drawer):
    """What the bridge's controller topics drive: a trajectory from the current state, then
    the hand."""
    world, _, base = drawer
    q = world.joint_limits[:, 0].copy()
    live = sim_panda.LiveArm(world, q, base)
    goal = kin.Q_READY + np.array([0.3, -0.2, 0.1, 0.2, 0.0, 0.1, -0.3])
    duration = live.command_arm(np.array([1.0, 2.0]), np.stack([
        (kin.Q_READY + goal) / 2, goal]))
    assert duration == pytest.approx(2.0)
    assert live.busy()
    live.step(int(2.5 / live.timestep))
    assert np.abs(live.panda.q() - goal).max() < 0.01
    live.command_fingers(np.array([0.5]), np.array([0.0]))
    live.step(int(1.0 / live.timestep))
    assert live.panda.finger_positions().max() < 0.002
    assert not live.busy()


# -- through the stack ------------------------------------------------------------------------


@pytest.mark.slow
def test_pull_through_the_stack_with_the_simulated_panda_opens_a_drawer(tmp_path):
    """bridge (robot panda) + segmentation + executor (outcome from clouds, as on a real arm)
    + the arm adapter live; a plain rclpy client loads a closed drawer cabinet and sends the
    pull: the drawer opens in the simulated world."""
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from scenes import Tee
    from sensor_msgs.msg import JointState
    from w2e_msgs.action import ExecuteInteraction
    from w2e_msgs.msg import SceneObject, SegmentedObjects
    from w2e_msgs.srv import LoadScene
    from waits import result_of, wait_until

    from w2e_ros.bringup import Stack
    from w2e_ros.ros.conversions import action_to_interaction, from_pose
    from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env, stop_process
    from w2e_ros.ros.qos import LATCHED_QOS, RELIABLE_QOS

    clean_shm_at_exit()
    instance, joint = _drawer_cabinet()
    model = make_object("cabinet", instance)
    closed = [float(lo) for lo, _ in model.joint_limits]
    pose = np.eye(4)  # placed at the identity below (use_pose), not laid out
    world = ObjectWorld(model, [pose])
    base = sim_panda.base_in_front(world.center())
    base_arg = "[" + ", ".join(f"{v:.6f}" for v in base) + "]"
    domain = pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=tmp_path / "ros_log")
    out = Tee()
    adapter_log = tmp_path / "arm_adapter.log"
    adapter = subprocess.Popen(
        [sys.executable, "-m", "w2e_ros.nodes.arm_adapter_node", "--ros-args",
         "-p", "dry_run:=false", "-p", f"arm_base_pose:={base_arg}",
         "-p", "gripper_interface:=gripper_command", "-p", "gripper_max_effort:=100.0"],
        env=env, start_new_session=True, stdout=adapter_log.open("w"),
        stderr=subprocess.STDOUT)
    extra = {"sim_bridge": ["-p", "robot:=panda", "-p", f"arm_base_pose:={base_arg}",
                            "-p", "initial_scene:=[]"],
             "executor": ["-p", "outcome_source:=clouds"]}
    ctx = rclpy.Context()
    try:
        with Stack(nodes=["sim_bridge", "segmentation", "executor"], env=env, output=out,
                   ready_timeout=90.0, extra_args=extra):
            rclpy.init(context=ctx, domain_id=domain)
            node = Node("panda_client", context=ctx)
            ex = SingleThreadedExecutor(context=ctx)
            ex.add_node(node)

            def wait(pred, timeout: float, what: str) -> None:
                wait_until(pred, timeout, what, executor=ex, poll=0.05)

            def result(future, timeout: float, what: str):
                return result_of(future, timeout, what, executor=ex, poll=0.05)

            cli = node.create_client(LoadScene, "load_scene")
            wait(cli.service_is_ready, 30.0, "load_scene")
            resp = result(cli.call_async(LoadScene.Request(objects=[SceneObject(
                category="cabinet", instance=instance, start_state=closed, use_pose=True)],
                clear=True)),
                60.0, "load_scene")
            assert resp.success, resp.message
            (obj_id,) = resp.object_ids
            position, _ = from_pose(resp.loaded[0].pose)
            np.testing.assert_allclose(position, pose[:3, 3], atol=1e-6)  # the layout assumed

            objects, arm_states, obj_states = [], [], []
            node.create_subscription(SegmentedObjects, "objects", objects.append, LATCHED_QOS)
            node.create_subscription(JointState, "joint_states", arm_states.append,
                                     RELIABLE_QOS)
            node.create_subscription(JointState, "object_joint_states", obj_states.append,
                                     RELIABLE_QOS)
            wait(lambda: objects and [o.id for o in objects[-1].objects] == [obj_id], 30.0,
                 "the cabinet in objects")
            wait(lambda: arm_states, 10.0, "the simulated arm's joint_states")
            assert list(arm_states[-1].name[:7]) == list(kin.PANDA_JOINTS)
            np.testing.assert_allclose(arm_states[-1].position[:7], kin.Q_READY, atol=0.02)

            act = ActionClient(node, ExecuteInteraction, "execute_interaction")
            wait(act.server_is_ready, 30.0, "execute_interaction")
            point = _drawer_front(world, np.asarray(closed), joint)
            pull = Action(point, np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), "pull")
            handle = result(act.send_goal_async(ExecuteInteraction.Goal(
                interaction=action_to_interaction(pull, obj_id))), 30.0, "acceptance")
            assert handle.accepted
            t0 = time.monotonic()
            outcome = result(handle.get_result_async(), 120.0, "the outcome").result.outcome
            print(f"\n[panda stack] pull in {time.monotonic() - t0:.1f} s: valid="
                  f"{outcome.valid} success={outcome.success} {outcome.reason}")
            # the simulated world's drawer opened (ground truth, not the executor's judgement)
            wait(lambda: obj_states and obj_states[-1].position[joint] > closed[joint] + 0.01,
                 10.0, "the open drawer in object_joint_states")
            assert obj_states[-1].name[joint].startswith(f"{obj_id}/")
            assert outcome.valid and outcome.success, outcome.reason
            # the arm moved: its hand is away from the ready pose
            assert np.abs(np.asarray(arm_states[-1].position[:7]) - kin.Q_READY).max() > 0.1

            # right after the pull, a push into the drawer closed again (issue 28, defect 5):
            # the closed drawer stops the arm; a trial that failed, its cause said, where it
            # was refused as "is panda_arm_controller/joint_trajectory a running controller?"
            resp = result(cli.call_async(LoadScene.Request(objects=[SceneObject(
                category="cabinet", instance=instance, start_state=closed, use_pose=True)],
                clear=True)), 60.0, "load_scene")
            assert resp.success, resp.message
            (obj_id,) = resp.object_ids
            wait(lambda: objects and [o.id for o in objects[-1].objects] == [obj_id], 30.0,
                 "the reloaded cabinet in objects")
            # aimed 5 cm inside the drawer's front: a push into a fingertip's depth (1 cm) past
            # the surface is stopped well within goal_tolerance; this one 6 cm short
            push = Action(point - np.array([0.05, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]),
                          np.array([0.0, 1.0, 0.0]), "push")
            handle = result(act.send_goal_async(ExecuteInteraction.Goal(
                interaction=action_to_interaction(push, obj_id))), 30.0, "acceptance")
            assert handle.accepted
            t0 = time.monotonic()
            outcome = result(handle.get_result_async(), 120.0, "the outcome").result.outcome
            print(f"[panda stack] push into the closed drawer in {time.monotonic() - t0:.1f} s: "
                  f"valid={outcome.valid} success={outcome.success} {outcome.reason}")
            assert outcome.valid and not outcome.success, outcome.reason
            assert "robot: blocked after waypoint" in outcome.reason, outcome.reason
            assert "joint trajectory controller" not in outcome.reason
            ex.shutdown()
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
        stop_process(adapter)
        print("[arm_adapter]", adapter_log.read_text()[-3000:])
