"""The sim bridge and the gripper executor as separate processes, driven over ROS.

A client loads a cabinet with a drawer, sends ExecuteInteraction (a pull on the drawer
handle) to the executor, which drives the bridge's follow_waypoints; the drawer must really
open (outcome, the bridge's joint states, and the camera cloud agree).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from rclpy.action import ActionClient
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState, PointCloud2
from visualization_msgs.msg import MarkerArray
from w2e_msgs.action import ExecuteInteraction, FollowWaypoints
from w2e_msgs.msg import Interaction, SceneObject, SegmentedObjects
from w2e_msgs.srv import LoadScene
from waits import result_of, wait_until

from sim_bridge.objects import make_object
from sim_bridge.world import ObjectWorld
from w2e_ros.bringup import Stack
from w2e_ros.core.robot.primitives import Action
from w2e_ros.ros.conversions import action_to_interaction, from_pose, to_pose
from w2e_ros.ros.pointcloud import cloud_to_arrays
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env
from w2e_ros.ros.qos import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS

pytestmark = pytest.mark.slow
clean_shm_at_exit()


def _cabinet_with_drawer() -> tuple[int, int]:
    """(instance, joint index) of the first cabinet with a drawer."""
    for i in range(50):
        for k, name in enumerate(make_object("cabinet", i).joint_names):
            if "drawer" in name:
                return i, k
    raise LookupError("no cabinet with a drawer")


class _Client:
    """A test-side node with its own context, spun by hand."""

    def __init__(self, domain_id: int) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = Node("test_client", context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)

    def wait(self, pred, timeout: float, what: str) -> None:
        wait_until(pred, timeout, what, executor=self.ex, poll=0.05)

    def result(self, future, timeout: float, what: str):
        return result_of(future, timeout, what, executor=self.ex, poll=0.05)

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    domain = pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=tmp_path_factory.mktemp("ros_log"))
    with Stack(nodes=["sim_bridge", "segmentation", "executor"], env=env,
               ready_timeout=90.0) as s:
        client = _Client(domain)
        try:
            yield s, client
        finally:
            client.close()


def _load(client: _Client, entries: list[SceneObject]) -> LoadScene.Response:
    cli = client.node.create_client(LoadScene, "load_scene")
    client.wait(cli.service_is_ready, 30.0, "load_scene")
    resp = client.result(cli.call_async(LoadScene.Request(objects=entries, clear=True)), 60.0,
                         "load_scene response")
    client.node.destroy_client(cli)
    return resp


def _handle_pull(resp: LoadScene.Response, instance: int, joint: int) -> Action:
    """The front-most point of the drawer, seen by a camera on the bridge's placement."""
    position, R = from_pose(resp.loaded[0].pose)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, position
    model = make_object("cabinet", instance)
    world = ObjectWorld(model, [pose])
    q = np.asarray(resp.loaded[0].start_state)
    obs = world.observe(q)
    link = model.movable_joints[joint].child
    pts = obs.points[obs.link_ids == link]
    p = pts[np.argmax(pts[:, 0])].astype(float)
    return Action(p, np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), "pull")


def test_pull_on_drawer_handle_opens_it(stack):
    _, client = stack
    instance, joint = _cabinet_with_drawer()
    model = make_object("cabinet", instance)
    closed = [float(lo) for lo, _ in model.joint_limits]
    resp = _load(client, [SceneObject(category="cabinet", instance=instance, start_state=closed)])
    assert resp.success, resp.message
    (obj_id,) = resp.object_ids

    joint_states: list[JointState] = []
    clouds: list[PointCloud2] = []
    client.node.create_subscription(JointState, "object_joint_states", joint_states.append,
                                    RELIABLE_QOS)
    client.node.create_subscription(PointCloud2, "camera/points", clouds.append, SENSOR_QOS)
    def ids(msg: PointCloud2) -> set[int]:
        c = cloud_to_arrays(msg, require_normals=True, fields=("object_id",))
        return set(np.unique(c.fields["object_id"]).tolist())

    # a frame rendered just before the load may still arrive: wait for one of the new scene
    client.wait(lambda: clouds and ids(clouds[-1]) == {0, obj_id}, 30.0,
                "a camera cloud of the table + the cabinet")
    # the segmentation node sees the cabinet under its scene id
    objects: list[SegmentedObjects] = []
    client.node.create_subscription(SegmentedObjects, "objects", objects.append, LATCHED_QOS)
    client.wait(lambda: objects and [o.id for o in objects[-1].objects] == [obj_id], 30.0,
                "the cabinet in objects")
    seg = cloud_to_arrays(objects[-1].objects[0].cloud, require_normals=True)
    assert seg.points.shape == (2048, 3)
    # the simulator's movable-part truth reaches the object cloud: the drawer and door
    # fronts are marked, the cabinet's body is not
    assert 0 < np.count_nonzero(seg.fields["movable"]) < 2048

    markers: list[MarkerArray] = []  # what RViz gets: the interaction, coloured by outcome
    client.node.create_subscription(MarkerArray, "interaction_markers", markers.append,
                                    LATCHED_QOS)
    act = ActionClient(client.node, ExecuteInteraction, "execute_interaction")
    client.wait(act.server_is_ready, 30.0, "execute_interaction")
    pull = _handle_pull(resp, instance, joint)
    goal = ExecuteInteraction.Goal(interaction=action_to_interaction(pull, obj_id))
    phases: list[str] = []
    t0 = time.perf_counter()
    handle = client.result(act.send_goal_async(
        goal, feedback_callback=lambda fb: phases.append(fb.feedback.phase)), 30.0, "acceptance")
    assert handle.accepted
    outcome = client.result(handle.get_result_async(), 120.0, "the outcome").result.outcome
    elapsed = time.perf_counter() - t0
    print(f"\n[bridge+executor] pull executed in {elapsed * 1e3:.0f} ms; phases {phases}; "
          f"motion {outcome.motion:+.4f}")

    assert outcome.valid and outcome.success, outcome.reason
    assert outcome.joint_index == joint and outcome.motion > 0.01
    assert outcome.contact_displacement.x > 0.01  # the handle came towards the gripper
    assert phases[0] == "planning" and phases[-1] == "done"
    client.wait(lambda: markers and markers[-1].markers[-1].text.startswith("pull: success"),
                10.0, "the interaction's markers, green")
    contact = markers[-1].markers[2].pose.position  # DELETEALL, arrow, then the contact
    assert np.allclose([contact.x, contact.y, contact.z], pull.point, atol=1e-6)
    assert markers[-1].markers[2].color.g > 0.5 > markers[-1].markers[2].color.r
    # the bridge's object really stays open afterwards
    client.wait(lambda: joint_states and joint_states[-1].position
                and joint_states[-1].position[joint] > closed[joint] + 0.01, 10.0,
                "the open drawer in object_joint_states")
    assert joint_states[-1].name[joint].startswith(f"{obj_id}/")


def test_bad_requests_get_clear_errors_not_crashes(stack):
    s, client = stack
    resp = _load(client, [SceneObject(category="spaceship", instance=0)])
    assert not resp.success and "unknown category" in resp.message

    act = ActionClient(client.node, ExecuteInteraction, "execute_interaction")
    client.wait(act.server_is_ready, 30.0, "execute_interaction")
    bad = ExecuteInteraction.Goal(interaction=Interaction(primitive="poke"))
    handle = client.result(act.send_goal_async(bad), 30.0, "acceptance")
    outcome = client.result(handle.get_result_async(), 30.0, "result").result.outcome
    assert not outcome.valid and "unknown primitive" in outcome.reason

    # the robot side refuses a trajectory that is not a primitive
    robot = ActionClient(client.node, FollowWaypoints, "follow_waypoints")
    client.wait(robot.server_is_ready, 30.0, "follow_waypoints")
    wp = FollowWaypoints.Goal(waypoints=[to_pose([0, 0, 1.0], np.eye(3)),
                                         to_pose([0.5, 0, 1.0], np.eye(3))],
                              gripper=[0, 0], initial_gripper=FollowWaypoints.Goal.GRIPPER_CLOSE)
    handle = client.result(robot.send_goal_async(wp), 30.0, "acceptance")
    res = client.result(handle.get_result_async(), 30.0, "result").result
    assert not res.valid and "not a push primitive" in res.message
    assert all(s.alive().values())
