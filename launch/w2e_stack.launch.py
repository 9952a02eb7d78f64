"""Launch the w2e node stack on a full ROS 2 install: ``ros2 launch w2e_ros w2e_stack.launch.py``.

The same nodes, names and parameter file as ``w2e bringup`` (which is what runs where
``ros2 launch`` is not installable). Arguments::

    namespace:=<ns>          namespace of every node (default: none)
    params_file:=<yaml>      default: share/w2e_ros/config/w2e_stack.yaml
    use_sim:=true|false      start the sim bridge (false: real camera + robot adapters)
    nodes:=a,b,c             subset of sim_bridge,arm_adapter,segmentation,inference,executor,
                             planner (default: all but arm_adapter, which starts by default
                             when the sim bridge's robot is panda, live on its arm_base_pose)
    respawn:=true|false      start a node again when it dies (as w2e bringup --respawn;
                             launch_ros waits respawn_delay:=<s> each time, with no limit)
    rviz:=true|false         also start rviz2 with share/w2e_ros/config/w2e.rviz (its topics
                             are the un-namespaced ones; default false)

Each node gets its own section of the YAML as a parameter dictionary, so the plain
``node_name:`` keys work under any namespace (what nav2 does with RewrittenYaml). As with
``w2e bringup``, the nodes that carry camera clouds (LARGE_MESSAGE_NODES) load the Fast DDS
profile for large messages (share/w2e_ros/config/fastdds_large_messages.xml, shared memory)
and the control nodes fastdds_control.xml (UDP only: a respawned node is heard again), unless
the shell names a profile of its own (FASTRTPS_/FASTDDS_DEFAULT_PROFILES_FILE). Unlike
``w2e bringup``, launch_ros gives a respawned shared-memory node no fresh participant id.
"""

import os
import tempfile
from pathlib import Path

import yaml
from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription
from w2e_ros.ros.transport import PROFILE_VARS, node_transport_env

# short name -> (console script in setup.py, ROS node name = section of the YAML), start order
NODES = {
    "sim_bridge": ("sim_bridge_node", "sim_bridge"),
    "arm_adapter": ("arm_adapter_node", "arm_adapter"),
    "segmentation": ("segmentation_node", "segmentation"),
    "inference": ("inference_node", "inference_node"),
    "executor": ("executor_node", "executor"),
    "planner": ("planner_node", "planner_node"),
}
LARGE_MESSAGE_NODES = ("sim_bridge", "segmentation")  # as NodeSpec.large_messages in bringup


def _nodes(context, *args, **kwargs):
    namespace = LaunchConfiguration("namespace").perform(context)
    params_file = LaunchConfiguration("params_file").perform(context)
    use_sim = LaunchConfiguration("use_sim").perform(context).lower() in ("true", "1", "yes")
    respawn = LaunchConfiguration("respawn").perform(context).lower() in ("true", "1", "yes")
    respawn_delay = float(LaunchConfiguration("respawn_delay").perform(context))
    wanted = [n.strip() for n in LaunchConfiguration("nodes").perform(context).split(",")
              if n.strip()]
    unknown = [n for n in wanted if n not in NODES]
    if unknown:
        raise RuntimeError(f"unknown nodes {unknown}; the stack has {list(NODES)}")
    with open(params_file) as f:
        params = yaml.safe_load(f) or {}
    shared = params.get("/**", {}).get("ros__parameters", {})
    bridge = dict(shared, **params.get("sim_bridge", {}).get("ros__parameters", {}))
    sim_panda = use_sim and bridge.get("robot", "flying") == "panda"
    actions = []
    for name, (executable, node_name) in NODES.items():
        if wanted and name not in wanted:
            continue
        if name == "sim_bridge" and not use_sim:
            continue
        if name == "arm_adapter" and not wanted and not sim_panda:
            continue
        section = dict(shared)
        section.update(params.get(node_name, {}).get("ros__parameters", {}))
        if name == "arm_adapter" and sim_panda:  # live on the simulated arm (as w2e bringup)
            # its arm_base_pose is the bridge's: the file's /** section sets both
            section.update(dry_run=False, gripper_interface="gripper_command",
                           gripper_action="franka_gripper/gripper_action", gripper_topic="",
                           gripper_max_effort=100.0)
        actions.append(Node(
            package="w2e_ros",
            executable=executable,
            name=node_name,
            namespace=namespace,
            parameters=[section],
            output="screen",
            emulate_tty=True,
            respawn=respawn,
            respawn_delay=respawn_delay,
            additional_env=_transport_env(name),
        ))
    if LaunchConfiguration("rviz").perform(context).lower() in ("true", "1", "yes"):
        layout = os.path.join(get_package_share_directory("w2e_ros"), "config", "w2e.rviz")
        actions.append(Node(package="rviz2", executable="rviz2", name="rviz2",
                            arguments=["-d", layout], output="screen"))
    return actions


def _transport_env(name: str) -> dict[str, str]:
    """The Fast DDS variables of one node (w2e_ros.ros.transport.node_transport_env, as in
    ``w2e bringup``): the shell's own profile where it names one (the shipped large-message
    profile, which the venv's activate script sets, is none), else shared memory for the cloud
    nodes and UDP only for the others, with LOCALHOST discovery written into the profile."""
    out = Path(tempfile.mkdtemp(prefix="w2e_launch_"))
    env = node_transport_env(dict(os.environ), name in LARGE_MESSAGE_NODES, out)
    keys = (*PROFILE_VARS, "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY")
    return {k: env.get(k, "") for k in keys if k in env or k in os.environ}


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(
        get_package_share_directory("w2e_ros"), "config", "w2e_stack.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of every node"),
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="parameter file of the whole stack"),
        DeclareLaunchArgument("use_sim", default_value="true",
                              description="start the SAPIEN sim bridge as camera and robot"),
        DeclareLaunchArgument("nodes", default_value="",
                              description="comma-separated subset of nodes (default: all)"),
        DeclareLaunchArgument("respawn", default_value="false",
                              description="start a node again when its process dies"),
        DeclareLaunchArgument("respawn_delay", default_value="1.0",
                              description="seconds before a node is started again"),
        DeclareLaunchArgument("rviz", default_value="false",
                              description="also start rviz2 with config/w2e.rviz"),
        OpaqueFunction(function=_nodes),
    ])
