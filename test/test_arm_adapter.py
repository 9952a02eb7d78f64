"""The arm adapter as its own process, seen from this one with plain rclpy: a primitive's
waypoints in, a Panda JointTrajectory out on the controller's topic (live) or only on
planned_trajectory / planned_path (dry run); an unreachable goal refused before anything is
published.

Live mode needs a joint trajectory controller; none runs here, so this process stands in for
its two ends that the adapter touches: it publishes ``joint_states`` and, when a trajectory
arrives on the controller topic, reports the arm at that trajectory's last point (the hand is
not driven: ``gripper_action:=''``); or, standing in for contact, part of the way there and
no farther; or it runs no controller at all.
"""

from __future__ import annotations

import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rclpy
from nav_msgs.msg import Path
from rclpy.action import ActionClient
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory
from w2e_msgs.action import FollowWaypoints
from waits import result_of, wait_until

from w2e_ros.core.robot import kinematics as kin
from w2e_ros.core.robot.primitives import Action
from w2e_ros.ros.conversions import to_pose
from w2e_ros.ros.processes import (
    clean_shm_at_exit,
    pick_domain_id,
    ros_env,
    shm_files,
    stop_process,
)
from w2e_ros.ros.qos import LATCHED_QOS
from w2e_ros.ros.waypoints import plan_waypoints

clean_shm_at_exit(shm_files())
pytestmark = pytest.mark.slow

REACHABLE = Action(np.array([0.6, 0.0, 0.5]), np.array([1.0, 0.0, 0.0]),
                   np.array([0.0, 0.0, 1.0]), "pull")  # a drawer front 0.6 m ahead
FAR = Action(np.array([1.6, 0.0, 0.5]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]),
             "pull")


BASE_AT_ORIGIN = "arm_base_pose:=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]"  # the actions' frame


def goal_of(action: Action) -> FollowWaypoints.Goal:
    plan = plan_waypoints(action)
    goal = FollowWaypoints.Goal(waypoints=[to_pose(p, plan.rotation) for p in plan.positions],
                                gripper=list(plan.gripper), initial_gripper=plan.initial_gripper)
    goal.header.frame_id = "world"
    return goal


class Robot:
    """The adapter process and, here, a client with the controller's two ends."""

    def __init__(self, tmp, *params: str, block_piece: int | None = None,
                 controller: bool = True, states: bool = True) -> None:
        """``block_piece``: that trajectory (0: the first) takes the arm half way and stops
        there, as a part that does not give stops it; ``controller``: False, none listens;
        ``states``: False, no joint_states are published (no arm)."""
        domain = pick_domain_id()
        self.started = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "w2e_ros.nodes.arm_adapter_node", "--ros-args",
             *[a for p in (BASE_AT_ORIGIN, *params) for a in ("-p", p)]],
            env=ros_env(domain_id=domain, log_dir=tmp / "ros_log"), start_new_session=True,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = Node("fake_controller", context=self.ctx)
        self.commanded: list[JointTrajectory] = []
        self.planned: list[JointTrajectory] = []
        self.paths: list[Path] = []
        self.q = kin.Q_READY.copy()
        self.block_piece = block_piece
        self.blocked = False
        self.blocked_at: float | None = None  # when the blocked piece was commanded
        if controller:
            self.node.create_subscription(JointTrajectory,
                                          "panda_arm_controller/joint_trajectory",
                                          self._on_command, 10)
        self.node.create_subscription(JointTrajectory, "planned_trajectory",
                                      self.planned.append, LATCHED_QOS)
        self.node.create_subscription(Path, "planned_path", self.paths.append, LATCHED_QOS)
        self.states = self.node.create_publisher(JointState, "joint_states", 10)
        if states:
            self.node.create_timer(0.05, self._publish_state)
        self.client = ActionClient(self.node, FollowWaypoints, "follow_waypoints")
        self.exe = MultiThreadedExecutor(num_threads=2, context=self.ctx)
        self.exe.add_node(self.node)
        self.thread = threading.Thread(target=self.exe.spin, daemon=True)
        self.thread.start()
        assert self.client.wait_for_server(timeout_sec=30.0), self.output()

    def _on_command(self, msg: JointTrajectory) -> None:
        self.commanded.append(msg)
        end = np.array(msg.points[-1].positions)
        if len(self.commanded) - 1 == self.block_piece:
            self.q, self.blocked = self.q + 0.5 * (end - self.q), True  # stopped half way
            self.blocked_at = time.monotonic()
        elif not self.blocked:
            self.q = end  # the controller got there

    def _publish_state(self) -> None:
        self.states.publish(JointState(name=list(kin.PANDA_JOINTS),
                                       position=[float(x) for x in self.q]))

    def follow(self, action: Action, timeout: float = 60.0) -> FollowWaypoints.Result:
        sent = self.client.send_goal_async(goal_of(action))
        end = time.monotonic() + timeout
        wait_until(sent.done, timeout, "the goal's acceptance", detail=self.output)
        res = sent.result().get_result_async()
        wait_until(res.done, max(end - time.monotonic(), 0.0), "the goal's result",
                   detail=self.output)
        return res.result().result

    def output(self) -> str:
        stop_process(self.proc)
        return self.proc.stdout.read() if self.proc.stdout else ""

    def close(self) -> None:
        self.exe.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
        stop_process(self.proc)


def check_trajectory(msg: JointTrajectory) -> np.ndarray:
    """The Panda's joints, strictly increasing times, positions within Franka's limits."""
    assert list(msg.joint_names) == list(kin.PANDA_JOINTS)
    t = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points])
    assert len(t) >= 1 and np.all(np.diff(t) > 0)
    q = np.array([p.positions for p in msg.points])
    assert q.shape == (len(t), 7)
    assert np.all(q >= kin.Q_MIN) and np.all(q <= kin.Q_MAX)
    return q


def test_live_mode_sends_the_panda_trajectory_in_pieces_and_refuses_the_unreachable(tmp_path):
    robot = Robot(tmp_path, "dry_run:=false", "gripper_action:=''", "velocity_scale:=1.0",
                  "cartesian_speed:=0.5", "settle_s:=5.0")
    try:
        res = robot.follow(REACHABLE)
        assert res.reached and res.valid, (res.message, robot.output())
        # a pull: to the handle, (grasp), back: two pieces cut where the hand closes
        assert len(robot.commanded) == 2
        pieces = [check_trajectory(m) for m in robot.commanded]
        T = kin.fk(np.concatenate(pieces))
        wp = plan_waypoints(REACHABLE).positions
        np.testing.assert_allclose(T[len(pieces[0]) - 1, :3, 3], wp[1], atol=1e-3)  # at grasp
        np.testing.assert_allclose(T[-1, :3, 3], wp[-1], atol=1e-3)
        # every step after the free move is small: the arm follows the straight line
        q = np.concatenate(pieces)
        assert np.abs(np.diff(q[1:], axis=0)).max() <= kin.DEFAULT_PLAN.max_joint_step
        wait_until(lambda: robot.planned and robot.paths, 30.0, "the latched plan and path")
        assert len(robot.paths[-1].poses) == len(robot.planned[-1].points)

        n = len(robot.commanded)
        res = robot.follow(FAR)
        assert not res.valid and not res.reached
        assert res.message.startswith("unreachable") and "reach" in res.message
        assert len(robot.commanded) == n  # nothing moved
    finally:
        robot.close()


def test_an_arm_blocked_after_the_grasp_is_a_failed_trial_and_holds_where_it_stopped(tmp_path):
    """Issue 28, defect 5: a blocked move was refused as "is ... a running joint trajectory
    controller?" right after the controller had run the previous piece. The arm moved and
    was stopped: a trial that failed (valid, not reached), the cause named, the arm held."""
    settle_s = 60.0
    robot = Robot(tmp_path, "dry_run:=false", "gripper_action:=''", "velocity_scale:=1.0",
                  "cartesian_speed:=0.5", f"settle_s:={settle_s}", block_piece=1)
    try:
        res = robot.follow(REACHABLE, timeout=2 * settle_s + 30)
        since_block = time.monotonic() - robot.blocked_at  # printed, not asserted
        print(f"\n[arm_adapter] answered {since_block:.1f} s after the block: {res.message}")
        assert res.valid and not res.reached, (res.message, robot.output())
        assert res.message.startswith("blocked after waypoint ")
        assert "of the primitive: the arm stopped, " in res.message
        assert "contact" in res.message and "controller" not in res.message
        assert len(robot.commanded) == 3  # the pieces to the handle and back, then the hold
        hold = robot.commanded[-1]
        assert len(hold.points) == 1
        np.testing.assert_allclose(hold.points[0].positions, robot.q, atol=1e-9)
        # seen when the arm stopped (STALL_S of no motion: "the arm stopped" above), not
        # settle_s after the plan's end ("was still short of the plan 60.0 s after its end")
        assert "after its end" not in res.message
    finally:
        robot.close()


def test_an_arm_that_never_moves_is_refused_naming_the_missing_controller(tmp_path):
    robot = Robot(tmp_path, "dry_run:=false", "gripper_action:=''", "velocity_scale:=1.0",
                  "cartesian_speed:=0.5", "settle_s:=0.5", controller=False)
    try:
        res = robot.follow(REACHABLE)
        assert not res.valid and not res.reached, (res.message, robot.output())
        assert res.message.startswith("the arm did not move on joint_states")
        assert "running joint trajectory controller? (nothing subscribes to it)" in res.message
    finally:
        robot.close()


def test_dry_run_only_publishes_the_plan(tmp_path):
    robot = Robot(tmp_path)  # dry_run defaults to true
    try:
        res = robot.follow(REACHABLE)
        assert not res.valid and res.message.startswith("dry run"), res.message
        wait_until(lambda: robot.planned and robot.paths, 30.0, "the latched plan and path")
        q = check_trajectory(robot.planned[-1])
        np.testing.assert_allclose(q[0], kin.Q_READY, atol=1e-9)  # from the reported state
        path = robot.paths[-1]
        assert path.header.frame_id == "world" and len(path.poses) == len(q)
        assert robot.commanded == []
    finally:
        robot.close()


def test_executor_judging_by_joints_refuses_a_robot_side_without_object_joints():
    """An arm (the adapter, a real Panda) measures no object joints; judging "nothing moved"
    from that would label every trial a failure and teach the model so. The executor says
    which setting to change instead."""
    from rclpy.action import ActionServer
    from w2e_msgs.action import ExecuteInteraction

    from w2e_ros.nodes.executor_node import GripperExecutorNode
    from w2e_ros.ros.conversions import action_to_interaction

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id())
    arm = Node("arm_like_robot_side", context=ctx)
    followed: list[int] = []

    def follow(goal_handle):  # what the adapter answers: done, valid, no object joints
        followed.append(len(goal_handle.request.waypoints))
        goal_handle.succeed()
        return FollowWaypoints.Result(valid=True, message="")

    server = ActionServer(arm, FollowWaypoints, "follow_waypoints", follow)
    executor_node = GripperExecutorNode(context=ctx)
    client_node = Node("user", context=ctx)
    ex = MultiThreadedExecutor(num_threads=4, context=ctx)
    for n in (arm, executor_node, client_node):
        ex.add_node(n)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    try:
        client = ActionClient(client_node, ExecuteInteraction, "execute_interaction")
        assert client.wait_for_server(timeout_sec=10.0)
        act = Action(np.array([0.5, 0.0, 0.4]), np.array([-1.0, 0.0, 0.0]),
                     np.array([0.0, 0.0, 1.0]), "pull")
        sent = client.send_goal_async(ExecuteInteraction.Goal(
            interaction=action_to_interaction(act, 1)))
        result = result_of(sent, 60.0, "the goal's acceptance").get_result_async()
        outcome = result_of(result, 120.0, "the executor's outcome").result.outcome
        assert followed, "the robot side never got the trajectory"
        assert not outcome.valid and not outcome.success
        assert "outcome_source: clouds" in outcome.reason
    finally:
        ex.shutdown(timeout_sec=0.0)
        spinner.join(timeout=5.0)
        server.destroy()
        for n in (arm, executor_node, client_node):
            n.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_without_an_arm_the_first_goal_waits_out_start_up_then_goals_fail_fast(tmp_path):
    """No joint_states at all: the first goal after start-up waits out the start-up grace
    (discovery can take seconds on a loaded machine, and a goal sent at once must not be
    refused for it), later ones are refused after joint_state_timeout_s, naming the wait."""
    from w2e_ros.nodes.arm_adapter_node import STARTUP_GRACE_S

    robot = Robot(tmp_path, "dry_run:=false", "joint_state_timeout_s:=0.5", states=False)
    try:
        res = robot.follow(REACHABLE)
        first = time.monotonic() - robot.started
        assert not res.valid and "where is the arm?" in res.message, res.message
        assert first >= STARTUP_GRACE_S - 1.0, first  # the adapter started after robot.started
        res = robot.follow(REACHABLE)
        assert "where is the arm?" in res.message, res.message
        # after joint_state_timeout_s, not the start-up grace again (the wait as the message
        # gives it: a loaded machine may stretch the 0.5 s, not to the grace's 10 s)
        waited = float(re.search(r"within ([\d.]+) s", res.message)[1])
        assert 0.5 <= waited < STARTUP_GRACE_S, res.message
        assert not robot.commanded  # nothing was sent to a controller
    finally:
        robot.close()

