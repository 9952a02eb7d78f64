"""w2e_msgs is built and usable across processes: a service, an action and a PointCloud2 topic.

The server half runs in a child process (this file run as a script), the client half in the
test process, on a private ROS domain kept on localhost.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from rclpy.action import ActionClient, ActionServer
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from w2e_msgs.action import ExecuteInteraction
from w2e_msgs.msg import AffordanceMap, Interaction, InteractionOutcome
from w2e_msgs.srv import PredictMaps
from waits import wait_until

from w2e_ros.ros.pointcloud import arrays_to_cloud, cloud_to_arrays
from w2e_ros.ros.processes import (
    clean_shm,
    clean_shm_at_exit,
    pick_domain_id,
    ros_env,
    shm_files,
    stop_process,
)
from w2e_ros.ros.qos import SENSOR_QOS

N_POINTS = 10_000
_SHM_BEFORE = shm_files()
if __name__ != "__main__":
    clean_shm_at_exit(_SHM_BEFORE)  # this process's own participant files, once it exits


def test_every_interface_imports_and_has_its_fields():
    from w2e_msgs.action import FollowWaypoints
    from w2e_msgs.msg import ExplorationProgress, SceneObject, SegmentedObject, SegmentedObjects
    from w2e_msgs.srv import Explore, LoadScene, Manipulate, UpdateModel

    assert SegmentedObjects().objects == [] and SegmentedObject().id == 0
    assert {"object_id", "point", "up", "forward", "primitive"} <= set(
        Interaction.get_fields_and_field_types())
    assert {"valid", "success", "motion", "moved_part", "joint_index", "reason"} <= set(
        InteractionOutcome.get_fields_and_field_types())
    assert {"best_actions", "best_scores", "mean_similarity", "cloud"} <= set(
        AffordanceMap.get_fields_and_field_types())
    assert {"step", "budget", "category", "interaction", "outcome", "mean_similarity"} <= set(
        ExplorationProgress.get_fields_and_field_types())
    assert {"category", "object_ids", "instances", "primitive", "budget", "similarity_bar"} <= set(
        Explore.Request.get_fields_and_field_types())
    assert {"success", "interactions_used", "final_mean_similarity", "successes", "message"} <= set(
        Explore.Response.get_fields_and_field_types())
    assert {"outcomes", "success", "message"} <= set(
        Manipulate.Response.get_fields_and_field_types())
    assert {"loss", "checkpoint_path"} <= set(UpdateModel.Response.get_fields_and_field_types())
    assert {"waypoints", "gripper"} <= set(FollowWaypoints.Goal.get_fields_and_field_types())
    assert {"reached", "contacts", "joints_before", "joints_after"} <= set(
        FollowWaypoints.Result.get_fields_and_field_types())
    assert FollowWaypoints.Goal.GRIPPER_CLOSE == 2
    assert "object_ids" in LoadScene.Response.get_fields_and_field_types()
    assert SceneObject().category == ""
    # the explore action: the service's request as its goal, its response as its result
    from w2e_msgs.action import Explore as ExploreAction

    assert ExploreAction.Goal.get_fields_and_field_types() == \
        Explore.Request.get_fields_and_field_types()
    assert ExploreAction.Result.get_fields_and_field_types() == \
        Explore.Response.get_fields_and_field_types()
    assert ExploreAction.Feedback.get_fields_and_field_types() == {
        "progress": "w2e_msgs/ExplorationProgress"}
    assert {"checkpoint_name", "restore"} <= set(UpdateModel.Request.get_fields_and_field_types())


# --- the server half (a child process) -------------------------------------------------------

class _InterfaceServer(Node):
    """Answers PredictMaps, executes a fake ExecuteInteraction, streams a 10k-point cloud."""

    def __init__(self) -> None:
        super().__init__("iface_server")
        rng = np.random.default_rng(0)
        self._points = rng.normal(size=(N_POINTS, 3)).astype(np.float32)
        self._normals = self._points / np.linalg.norm(self._points, axis=1, keepdims=True)
        self.create_service(PredictMaps, "predict_maps", self._predict)
        self._action = ActionServer(self, ExecuteInteraction, "execute_interaction", self._execute)
        self._pub = self.create_publisher(PointCloud2, "camera/points", SENSOR_QOS)
        self.create_timer(0.1, self._publish)

    def _publish(self) -> None:
        msg = arrays_to_cloud(self._points, self._normals, frame_id="world",
                              stamp=self.get_clock().now().to_msg())
        self._pub.publish(msg)

    def _predict(self, req: PredictMaps.Request, resp: PredictMaps.Response):
        for i, cloud in enumerate(req.clouds):
            arr = cloud_to_arrays(cloud)
            score = np.linalg.norm(arr.points, axis=1).astype(np.float32)
            m = AffordanceMap(object_id=req.object_ids[i] if req.object_ids else i,
                              primitive=req.primitive)
            m.cloud = arrays_to_cloud(arr.points, arr.normals, {"affordance": score})
            m.mean_similarity = float(score.mean())
            resp.maps.append(m)
        resp.success = True
        resp.message = f"{len(resp.maps)} maps"
        return resp

    def _execute(self, goal_handle):
        for phase in ("approach", "contact", "pull"):
            fb = ExecuteInteraction.Feedback(phase=phase)
            goal_handle.publish_feedback(fb)
            time.sleep(0.02)
        goal_handle.succeed()
        req = goal_handle.request.interaction
        return ExecuteInteraction.Result(outcome=InteractionOutcome(
            valid=True, success=True, motion=req.point.x, reason="", joint_index=0,
            moved_part=f"echo-{req.primitive}"))


def _serve() -> None:
    rclpy.init()
    node = _InterfaceServer()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


# --- the client half (this process) ----------------------------------------------------------

@pytest.fixture
def server(tmp_path):
    env = ros_env(domain_id=pick_domain_id(), log_dir=tmp_path / "ros_log")
    shm_before = shm_files()
    proc = subprocess.Popen([sys.executable, __file__], env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE",
                                            "ROS_LOG_DIR")}
    for k in saved:
        os.environ[k] = env[k]
    try:
        yield proc
    finally:
        stop_process(proc)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        clean_shm(shm_before)


def _wait(pred, timeout: float, executor, what: str) -> None:
    wait_until(pred, timeout, what, executor=executor, poll=0.05)


def test_service_action_and_cloud_between_two_processes(server):
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node("iface_client", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        latencies: list[float] = []
        received: list[PointCloud2] = []

        def on_cloud(msg: PointCloud2) -> None:
            now = node.get_clock().now().nanoseconds
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            latencies.append((now - stamp) / 1e6)
            received.append(msg)

        node.create_subscription(PointCloud2, "camera/points", on_cloud, SENSOR_QOS)
        cli = node.create_client(PredictMaps, "predict_maps")
        act = ActionClient(node, ExecuteInteraction, "execute_interaction")
        _wait(lambda: server.poll() is None and cli.service_is_ready()
              and act.server_is_ready(), 30.0, ex, "the server process")

        # topic: 10k points with normals at 10 Hz, decoded intact
        _wait(lambda: len(received) >= 12, 20.0, ex, "camera clouds")
        arr = cloud_to_arrays(received[-1], require_normals=True)
        assert arr.points.shape == (N_POINTS, 3) and arr.frame_id == "world"
        assert np.allclose(np.linalg.norm(arr.normals, axis=1), 1.0, atol=1e-5)
        cloud_ms = float(np.median(latencies[2:]))

        # service: round trip of a 2k-point cloud -> affordance map
        pts = np.random.default_rng(1).uniform(-1, 1, (2048, 3)).astype(np.float32)
        req = PredictMaps.Request(clouds=[arrays_to_cloud(pts, pts)], object_ids=[7],
                                  primitive="pull", num_directions=8)
        rtts = []
        for _ in range(10):
            t0 = time.perf_counter()
            fut = cli.call_async(req)
            _wait(fut.done, 30.0, ex, "predict_maps")
            rtts.append((time.perf_counter() - t0) * 1e3)
        resp = fut.result()
        assert resp.success and len(resp.maps) == 1 and resp.maps[0].object_id == 7
        out = cloud_to_arrays(resp.maps[0].cloud, fields=("affordance",))
        assert np.allclose(out.fields["affordance"], np.linalg.norm(pts, axis=1), atol=1e-6)

        # action: goal -> feedback phases -> result
        phases: list[str] = []
        goal = ExecuteInteraction.Goal(interaction=Interaction(object_id=3, primitive="pull"))
        goal.interaction.point.x = 0.25
        send = act.send_goal_async(goal, feedback_callback=lambda fb: phases.append(
            fb.feedback.phase))
        _wait(send.done, 30.0, ex, "goal acceptance")
        assert send.result().accepted
        res_fut = send.result().get_result_async()
        _wait(res_fut.done, 30.0, ex, "action result")
        outcome = res_fut.result().result.outcome
        assert outcome.success and outcome.motion == pytest.approx(0.25)
        assert outcome.moved_part == "echo-pull"
        assert phases == ["approach", "contact", "pull"]
        print(f"\n[interfaces] cloud 10k pts latency median {cloud_ms:.1f} ms; "
              f"predict_maps (2k pts) round trip median {np.median(rtts):.1f} ms")
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


if __name__ == "__main__":
    _serve()
