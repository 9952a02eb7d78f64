"""The Panda's base has one source (issue 28, defect 8): ``arm_base_pose``, set once in
config/w2e_stack.yaml's ``/**`` section, is where the bridge's simulated arm stands, what the
arm adapter plans from and what the planner checks reach from; it no longer depends on which
object the bridge loads first (it was 0.95 m in front of the first object's centre there, and
the origin in the planner and the adapter unless each was set by hand)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from rclpy.parameter import Parameter
from w2e_msgs.msg import SceneObject

from w2e_ros.bringup import default_params, node_parameters
from w2e_ros.core.robot import kinematics as kin
from w2e_ros.nodes.arm_adapter_node import ArmAdapterNode
from w2e_ros.nodes.planner_node import PlannerNode
from w2e_ros.ros.processes import pick_domain_id, ros_env

STACK_ARGS = ["--ros-args", "--params-file", str(default_params())]


def test_the_stack_file_sets_the_base_once_for_the_three_nodes():
    values = {node: node_parameters(default_params(), node)["arm_base_pose"]
              for node in ("sim_bridge", "planner_node", "arm_adapter")}
    assert all(v == list(kin.DEFAULT_BASE_POSE) for v in values.values()), values


def test_bridge_planner_and_adapter_agree_on_the_base(ros_context, tmp_path):
    from sim_bridge.bridge_node import SimBridgeNode

    nodes = [
        SimBridgeNode(context=ros_context, cli_args=STACK_ARGS, parameter_overrides=[
            Parameter("initial_scene", value=["cabinet:0"])]),
        PlannerNode(context=ros_context, cli_args=STACK_ARGS, parameter_overrides=[
            Parameter("arm", value="panda"),
            Parameter("exploration_log_dir", value=str(tmp_path))]),
        ArmAdapterNode(context=ros_context, cli_args=STACK_ARGS),
    ]
    try:
        bridge, planner, adapter = nodes
        want = kin.pose_matrix(kin.DEFAULT_BASE_POSE)
        np.testing.assert_allclose(bridge.arm_base(), want)
        np.testing.assert_allclose(kin.pose_matrix(planner.arm.base_pose), want)
        np.testing.assert_allclose(adapter.base, want)
    finally:
        for node in nodes:
            node.destroy_node()


def test_the_simulated_arm_stands_where_the_parameter_says_whichever_object_loads_first(
        ros_context):
    from sim_bridge.bridge_node import SimBridgeNode

    base = [0.9, 0.1, 0.05, 0.0, 0.0, 1.0, 0.0]
    bridge = SimBridgeNode(context=ros_context, parameter_overrides=[
        Parameter("robot", value="panda"),
        Parameter("arm_base_pose", value=base), Parameter("publish_rate_hz", value=0.0)])
    try:
        seen = []
        for order in (("cabinet", 0, "door", 30), ("door", 30, "cabinet", 0)):
            entries = [SceneObject(category=order[0], instance=order[1]),
                       SceneObject(category=order[2], instance=order[3])]
            ok, _, _, msg = bridge.load(entries, clear=True)
            assert ok, msg
            seen.append(bridge._live.base_pose.copy())
        np.testing.assert_allclose(seen[0], seen[1])
        np.testing.assert_allclose(seen[0], kin.pose_matrix(base))
    finally:
        bridge.destroy_node()


def test_a_command_line_override_still_beats_the_stack_file(tmp_path):
    """rcl puts ``-p`` into the /** section: the file's /** must come after the nodes'
    sections, or their values would win over every ``-p`` (measured: the executor kept
    outcome_source joints under ``-p outcome_source:=clouds``)."""
    proc = subprocess.run(  # the file says 0.3; 2.0 is out of range: the node stops
        [sys.executable, "-m", "w2e_ros.nodes.arm_adapter_node", *STACK_ARGS,
         "-p", "velocity_scale:=2.0"],
        env=ros_env(domain_id=pick_domain_id(), log_dir=tmp_path / "ros_log"),
        capture_output=True, text=True, timeout=60)
    out = proc.stdout + proc.stderr
    assert "velocity_scale" in out and proc.returncode == 2, out  # -p reached the node
