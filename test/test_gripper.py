"""The hand as franka_ros2 drives it (w2e_ros.ros.gripper, the bridge's franka_gripper actions).

The bridge with ``robot: panda`` runs as its own process and serves
``franka_gripper/gripper_action`` (control_msgs/GripperCommand), ``franka_gripper/move`` and
``franka_gripper/grasp`` (franka_msgs) on the simulated hand. From this process, with plain
rclpy: each action moves the simulated fingers (seen on ``joint_states``) and its result says
what the simulation did; then the arm adapter, live, as its own process with
``gripper_interface`` gripper_command or franka, closes and opens the hand between the pieces
of a FollowWaypoints goal.
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
from control_msgs.action import GripperCommand
from control_msgs.msg import GripperCommand as Command
from franka_msgs.action import Grasp, Move
from franka_msgs.msg import GraspEpsilon
from rclpy.action import ActionClient
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from w2e_msgs.action import FollowWaypoints
from waits import wait_until

from w2e_ros.core.robot import kinematics as kin
from w2e_ros.ros.conversions import to_pose
from w2e_ros.ros.processes import (
    clean_shm_at_exit,
    pick_domain_id,
    ros_env,
    stop_process,
)
from w2e_ros.ros.qos import RELIABLE_QOS
from w2e_ros.ros.waypoints import GRIPPER_CLOSE, GRIPPER_KEEP, GRIPPER_OPEN

clean_shm_at_exit()
pytestmark = pytest.mark.slow
FINGERS = ("panda_finger_joint1", "panda_finger_joint2")


class Cell:
    """The bridge (robot panda) as a process; this process a plain rclpy client of it."""

    def __init__(self, tmp) -> None:
        self.domain = pick_domain_id()
        self.env = ros_env(domain_id=self.domain, log_dir=tmp / "ros_log")
        self.log = tmp / "sim_bridge.log"
        self.bridge = subprocess.Popen(
            [sys.executable, "-m", "sim_bridge.bridge_node", "--ros-args",
             "-p", "robot:=panda", "-p", "initial_scene:=['cabinet:0']",
             "-p", "publish_rate_hz:=0.0"],
            env=self.env, start_new_session=True, stdout=self.log.open("w"),
            stderr=subprocess.STDOUT)
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=self.domain)
        self.node = Node("gripper_test", context=self.ctx)
        self.states: list[JointState] = []
        self.clients: dict[str, ActionClient] = {}
        self.node.create_subscription(JointState, "joint_states", self.states.append,
                                      RELIABLE_QOS)
        self.exe = MultiThreadedExecutor(num_threads=2, context=self.ctx)
        self.exe.add_node(self.node)
        threading.Thread(target=self.exe.spin, daemon=True).start()
        self.wait(lambda: self.states, 120.0, "the simulated arm's joint_states")

    def wait(self, pred, timeout: float, what: str) -> None:
        wait_until(pred, timeout, what, poll=0.05, detail=self.output)

    def output(self) -> str:
        return self.log.read_text()[-3000:]

    def fingers(self) -> np.ndarray:
        msg = self.states[-1]
        pos = dict(zip(msg.name, msg.position, strict=False))
        return np.array([pos[n] for n in FINGERS])

    def call(self, action_type, name: str, goal, timeout: float = 30.0):
        if name not in self.clients:  # kept: destroying one under the spinning executor fails
            self.clients[name] = ActionClient(self.node, action_type, name)
        client = self.clients[name]
        assert client.wait_for_server(timeout_sec=30.0), f"no {name}\n{self.output()}"
        sent = client.send_goal_async(goal)
        self.wait(sent.done, timeout, f"{name} accepting the goal")
        assert sent.result().accepted
        done = sent.result().get_result_async()
        self.wait(done.done, timeout, f"{name}'s result")
        return done.result()

    def close(self) -> None:
        self.exe.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)
        stop_process(self.bridge)


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    c = Cell(tmp_path_factory.mktemp("gripper"))
    yield c
    c.close()


def test_bridge_serves_the_franka_gripper_actions_from_the_simulation(cell):
    from action_msgs.msg import GoalStatus

    # GripperCommand as franka_gripper: position is one finger's travel
    done = cell.call(GripperCommand, "franka_gripper/gripper_action",
                     GripperCommand.Goal(command=Command(position=0.02, max_effort=30.0)))
    r = done.result
    assert done.status == GoalStatus.STATUS_SUCCEEDED
    assert r.reached_goal and not r.stalled
    assert r.position == pytest.approx(0.02, abs=0.001) and 0.0 <= r.effort <= 30.0
    cell.wait(lambda: np.abs(cell.fingers() - 0.02).max() < 0.001, 30.0, "fingers at 2 cm")

    # franka Move opens to a width (both fingers), at its speed
    t0 = time.monotonic()
    done = cell.call(Move, "franka_gripper/move", Move.Goal(width=0.08, speed=0.05))
    assert done.result.success and done.result.error == "", done.result.error
    assert time.monotonic() - t0 > 0.7  # 4 cm of width at 5 cm/s: the simulation never runs
    # ahead of real time, so this lower bound holds on any machine
    cell.wait(lambda: cell.fingers().min() > 0.039, 30.0, "the hand open")

    # a grasp of a 3 cm part with nothing between the fingers: they close to 0, outside
    # epsilon, and franka's rule says the grasp failed (aborted, with the reason)
    done = cell.call(Grasp, "franka_gripper/grasp", Grasp.Goal(
        width=0.03, epsilon=GraspEpsilon(inner=0.005, outer=0.005), speed=0.1, force=20.0))
    assert done.status == GoalStatus.STATUS_ABORTED and not done.result.success
    assert "grasp failed: width outside [0.0250, 0.0350] m" in done.result.error
    assert cell.fingers().max() < 0.002
    # a width the hand does not have is refused without moving
    done = cell.call(Move, "franka_gripper/move", Move.Goal(width=0.1, speed=0.1))
    assert not done.result.success and "outside the hand's [0, 0.08] m" in done.result.error
    assert cell.fingers().max() < 0.002


def _hand_goal(base: np.ndarray) -> FollowWaypoints.Goal:
    """Three wrist poses 2 cm apart, up from the ready pose's hand, in free space: the hand
    opened first, closed at the second pose and opened at the third."""
    W = base @ kin.fk(kin.Q_READY)
    poses = [W[:3, 3] + np.array([0.0, 0.0, 0.02 * k]) for k in range(3)]
    goal = FollowWaypoints.Goal(waypoints=[to_pose(p, W[:3, :3]) for p in poses],
                                gripper=[GRIPPER_KEEP, GRIPPER_CLOSE, GRIPPER_OPEN],
                                initial_gripper=GRIPPER_OPEN)
    goal.header.frame_id = "world"
    return goal


@pytest.mark.parametrize("interface", ["gripper_command", "franka"])
def test_adapter_closes_and_opens_the_simulated_hand_through_the_action(cell, tmp_path,
                                                                        interface):
    log = tmp_path / "arm_adapter.log"
    adapter = subprocess.Popen(
        [sys.executable, "-m", "w2e_ros.nodes.arm_adapter_node", "--ros-args",
         "-p", "dry_run:=false", "-p", f"gripper_interface:={interface}",
         "-p", "velocity_scale:=1.0"],
        env=cell.env, start_new_session=True, stdout=log.open("w"), stderr=subprocess.STDOUT)
    try:
        client = ActionClient(cell.node, FollowWaypoints, "follow_waypoints")
        assert client.wait_for_server(timeout_sec=30.0), log.read_text()
        seen: list[float] = []  # the fingers' opening while the goal runs
        cell.node.create_subscription(
            JointState, "joint_states",
            lambda m: seen.append(min(p for n, p in zip(m.name, m.position, strict=False)
                                      if n in FINGERS)), RELIABLE_QOS)
        sent = client.send_goal_async(_hand_goal(kin.pose_matrix(kin.DEFAULT_BASE_POSE)))
        cell.wait(sent.done, 30.0, "follow_waypoints accepting")
        assert sent.result().accepted
        done = sent.result().get_result_async()
        cell.wait(done.done, 90.0, "the adapter's result")
        res = done.result().result
        text = log.read_text()
        assert res.valid and res.reached, f"{res.message}\n{text[-3000:]}"
        # the simulated hand closed and opened again, driven through the action
        assert min(seen) < 0.002 and seen[-1] > 0.038, (min(seen), seen[-1])
        name = ("franka_gripper/gripper_action" if interface == "gripper_command"
                else "franka_gripper/grasp")
        assert f"hand closed: {name}" in text, text[-3000:]
        assert "hand opened:" in text
        if interface == "gripper_command":
            # the closing result reports the fingers shut (within the 2 mm above; under load
            # the last reading may be a tenth of a millimetre off zero)
            closed = re.search(r"hand closed: [^\n]*position (\d+\.\d+) m", text)
            assert closed and float(closed.group(1)) < 0.002, text[-3000:]
    finally:
        stop_process(adapter)
