"""Real camera clouds: organised, in the camera's optical frame, with NaN holes and packed rgb.

The simulator's camera sees two cabinets on a table; the same hits are published the way the
Azure Kinect and RealSense drivers do (an H x W grid in the optical frame, z forward, x
right, y down, NaN where the depth is missing, x y z + packed float32 rgb in PCL's 32-byte
point layout), built here with plain sensor_msgs. The segmentation node, given the camera's
pose (static_transform_publisher's x y z qx qy qz qw) or reading it from the robot's TF tree
(published by a separate process, a static chain with a moving joint, at the cloud's stamp),
must give the objects the world-frame cloud of the same hits gives.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from scenes import two_cabinets_on_a_table
from sensor_msgs.msg import PointCloud2, PointField

from w2e_ros.ros.conversions import quaternion_from_matrix
from w2e_ros.ros.pointcloud import CloudFormatError, arrays_to_cloud, cloud_to_arrays
from w2e_ros.ros.transforms import (
    CameraFrames,
    FrameError,
    RigidTransform,
    parse_camera_pose,
)

OPTICAL_FRAME = "camera_color_optical_frame"
# optical axes (x right, y down, z forward) in the simulator camera's (x forward, y left, z up)
OPTICAL_IN_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
WORKSPACE = {"workspace_min": [-5.0, -5.0, -1.0], "workspace_max": [5.0, 10.0, 5.0]}
# more samples than an object has points (4-6 k here): the object cloud is then every raw
# point of the segment in cloud order (padded by repeats), so it can be compared point by
# point; farthest-point sampling proper breaks near-ties differently under float32 rounding
ALL_POINTS = 8192


class Scene:
    """The camera's hits on two cabinets and a table, in the world and in the optical frame."""

    def __init__(self, width: int = 448, height: int = 448, missing: float = 0.03) -> None:
        from sim_bridge.camera import CameraSettings

        settings = CameraSettings(width=width, height=height)
        obs, camera_pose = two_cabinets_on_a_table(settings)

        # the optical frame's pose in the world: what the user measures and gives the node
        self.rotation = camera_pose[:3, :3] @ OPTICAL_IN_CAMERA
        self.translation = camera_pose[:3, 3].copy()
        optical = (obs.points.astype(np.float64) - self.translation) @ self.rotation
        # pixel of each hit (pinhole of the simulated camera; hits come in row-major order)
        f = (height / 2) / np.tan(np.radians(settings.fov_deg) / 2)
        u = np.rint(f * optical[:, 0] / optical[:, 2] + width / 2 - 0.5).astype(np.int64)
        v = np.rint(f * optical[:, 1] / optical[:, 2] + height / 2 - 0.5).astype(np.int64)
        pixel = v * width + u
        assert (np.diff(pixel) > 0).all(), "one hit per pixel, in row-major order"
        # missing depth on the objects too, as a real sensor has (dark or shiny spots)
        valid = np.random.default_rng(0).random(len(pixel)) >= missing

        self.width, self.height = width, height
        self.pixel = pixel[valid]
        self.optical = optical[valid].astype(np.float32)  # (N, 3)
        self.world = obs.points[valid]  # (N, 3), the same hits in the same (pixel) order
        self.object_ids = obs.object_ids[valid].astype(np.int32) + 1  # as the bridge: table 0

    def camera_pose(self) -> list[float]:
        """x y z qx qy qz qw of the optical frame in the world."""
        return [*map(float, self.translation), *map(float, quaternion_from_matrix(self.rotation))]

    def organised_cloud(self, labels: bool = False, frame_id: str = OPTICAL_FRAME
                        ) -> PointCloud2:
        """H x W, NaN where there is no depth, x y z _ rgb _ (+ object_id) float32 fields."""
        names = ["x", "y", "z", "rgb"] + (["object_id"] if labels else [])
        offsets = [0, 4, 8, 16] + ([20] if labels else [])
        formats = ["<f4"] * 4 + (["<i4"] if labels else [])
        dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                          "itemsize": 32})
        grid = np.zeros(self.height * self.width, dtype=dtype)
        for c in ("x", "y", "z"):
            grid[c] = np.nan
        for i, c in enumerate(("x", "y", "z")):
            grid[c][self.pixel] = self.optical[:, i]
        colour = np.array([[200, 180, 150], [40, 90, 200], [200, 60, 40]], np.uint32)
        c = colour[np.clip(self.object_ids, 0, 2)]
        grid["rgb"][self.pixel] = ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).view(np.float32)
        if labels:
            grid["object_id"][self.pixel] = self.object_ids
        msg = PointCloud2(height=self.height, width=self.width, point_step=32,
                          row_step=32 * self.width, is_bigendian=False, is_dense=False)
        msg.header.frame_id = frame_id
        msg.header.stamp.sec = 1700000000
        types = {"<f4": PointField.FLOAT32, "<i4": PointField.INT32}
        msg.fields = [PointField(name=n, offset=o, datatype=types[f], count=1)
                      for n, o, f in zip(names, offsets, formats, strict=True)]
        msg.data = grid.tobytes()
        return msg

    def world_cloud(self, labels: bool = False) -> PointCloud2:
        """Today's input: the same hits, unorganised, in the world frame."""
        fields = {"object_id": self.object_ids} if labels else None
        return arrays_to_cloud(self.world, fields=fields, frame_id="world")


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene()


@pytest.fixture
def context(ros_context):
    return ros_context


def _node(context, **params):
    from w2e_ros.nodes.segmentation_node import SegmentationNode

    values = {**WORKSPACE, **params}
    return SegmentationNode(context=context, parameter_overrides=[
        Parameter(k, value=v) for k, v in values.items()])


def _assert_same_objects(got, want) -> None:
    assert got.header.frame_id == want.header.frame_id == "world"
    assert [o.id for o in got.objects] == [o.id for o in want.objects]
    for g, w in zip(got.objects, want.objects, strict=True):
        assert g.num_raw_points == w.num_raw_points < ALL_POINTS
        gc, wc = cloud_to_arrays(g.cloud), cloud_to_arrays(w.cloud)
        assert gc.frame_id == "world"
        np.testing.assert_allclose(gc.points, wc.points, atol=1e-4, rtol=0)
        for v in ("centroid", "extent"):
            a, b = getattr(g, v), getattr(w, v)
            np.testing.assert_allclose([a.x, a.y, a.z], [b.x, b.y, b.z], atol=1e-4)
        # estimated normals (the camera gives none) agree up to the odd neighbourhood
        agree = np.abs(np.sum(gc.normals * wc.normals, axis=1)) > 0.999
        assert agree.mean() > 0.99


@pytest.mark.slow
def test_optical_frame_organised_cloud_segments_as_the_world_frame_cloud(scene, context):
    """No labels (a real camera's cloud): table plane + DBSCAN in the robot frame."""
    ref = _node(context, use_labels=False, num_points=ALL_POINTS).process(scene.world_cloud())
    assert len(ref.objects) == 2
    msg = scene.organised_cloud()
    assert (msg.height, msg.width) == (448, 448) and not msg.is_dense
    node = _node(context, use_labels=False, num_points=ALL_POINTS,
                 camera_pose=scene.camera_pose(), camera_frame=OPTICAL_FRAME)
    out = node.process(msg)
    _assert_same_objects(out, ref)
    assert out.header.stamp.sec == 1700000000  # the camera's stamp is kept
    # the cloud as it came, without the transform, would not even show the table as level
    assert len(_node(context, frame_id="", use_labels=False).process(msg).objects) != 2
    node.destroy_node()


@pytest.mark.slow
def test_optical_frame_cloud_with_labels_gives_the_scene_ids(scene, context):
    ref = _node(context, num_points=ALL_POINTS).process(scene.world_cloud(labels=True))
    out = _node(context, num_points=ALL_POINTS, camera_pose=scene.camera_pose()).process(
        scene.organised_cloud(labels=True))
    assert [o.id for o in out.objects] == [1, 2]  # object ids 0 = table, 1, 2 = cabinets
    _assert_same_objects(out, ref)


def test_static_pose_matches_static_transform_publishers_convention():
    # a camera 1 m up, looking straight down: optical z = world -z, optical x = world x
    pose = parse_camera_pose([0.5, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0])  # 180 deg about x
    np.testing.assert_allclose(pose.apply(np.array([[0.0, 0.0, 1.0], [0.1, 0.2, 0.5]])),
                               [[0.5, 0.0, 0.0], [0.6, -0.2, 0.5]], atol=1e-6)
    np.testing.assert_allclose(pose.rotate(np.array([[0.0, 0.0, -1.0]])), [[0.0, 0.0, 1.0]],
                               atol=1e-6)
    assert parse_camera_pose([]) is None
    # an unnormalised quaternion is normalised, as static_transform_publisher does
    np.testing.assert_allclose(parse_camera_pose([0, 0, 0, 0, 0, 0, 2.0]).rotation, np.eye(3))


@pytest.mark.parametrize(("params", "match"), [
    ({"camera_pose": [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0]}, "zero norm"),
    ({"camera_pose": [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]}, "needs 7 values"),
    ({"camera_pose": [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]}, "needs 7 values"),
    ({"camera_pose": [0.0, 0.0, float("nan"), 0.0, 0.0, 0.0, 1.0]}, "finite"),
    ({"transform_source": "tf2"}, "transform_source must be one of"),
])
def test_a_malformed_transform_parameter_stops_the_node_at_startup(context, params, match):
    with pytest.raises(ValueError, match=match):
        _node(context, **params)


def test_clouds_without_xyz_or_without_a_transform_are_logged_and_skipped(scene, context,
                                                                           capfd):
    node = _node(context, camera_pose=scene.camera_pose(), camera_frame=OPTICAL_FRAME)
    no_xyz = scene.organised_cloud()
    no_xyz.fields = [f for f in no_xyz.fields if f.name not in ("y", "z")]
    with pytest.raises(CloudFormatError, match="no y/z field"):
        node.process(no_xyz)
    node._on_cloud(no_xyz)  # logged, not raised
    other = scene.organised_cloud(frame_id="camera_depth_optical_frame")
    with pytest.raises(FrameError, match="camera_depth_optical_frame"):
        node.process(other)
    bare = _node(context)  # no camera_pose at all
    with pytest.raises(FrameError, match="set camera_pose"):
        bare.process(scene.organised_cloud())
    err = capfd.readouterr().err
    assert "skipping camera cloud" in err and "no y/z field" in err
    # the node goes on with the next good cloud
    assert len(node.process(scene.organised_cloud(labels=True)).objects) == 2
    node.destroy_node()
    bare.destroy_node()


def test_tf_auto_falls_back_to_the_static_pose_and_tf_alone_does_not():
    static = RigidTransform.from_pose([1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    from_tf = RigidTransform.from_pose([0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    calls, warnings = [], []
    tf_up, known = True, {OPTICAL_FRAME}

    def lookup(frame, stamp, wait=True):  # stands in for TfLookup
        calls.append((frame, wait))
        if not tf_up:
            raise FrameError(f"TF: no transform from {frame!r} to 'world'")
        return from_tf

    frames = CameraFrames("world", "auto", static, OPTICAL_FRAME, lookup, warnings.append,
                          knows=known.__contains__)
    assert frames.transform_for("world") is None and frames.transform_for("") is None
    assert frames.transform_for(OPTICAL_FRAME) is from_tf
    assert calls == [(OPTICAL_FRAME, True)]
    tf_up = False
    assert frames.transform_for(OPTICAL_FRAME) is static
    assert "using the static camera_pose" in warnings[-1]
    known.clear()  # a frame TF never named: the static pose without waiting for TF
    calls.clear()
    assert frames.transform_for(OPTICAL_FRAME) is static and calls == [(OPTICAL_FRAME, False)]
    with pytest.raises(FrameError, match="TF: no transform"):  # static is for another frame
        frames.transform_for("other_frame")
    # tf: the robot's tree only, a static pose set too is not used
    strict = CameraFrames("world", "tf", static, OPTICAL_FRAME, lookup)
    with pytest.raises(FrameError, match="TF: no transform from 'camera_color_optical_frame'"):
        strict.transform_for(OPTICAL_FRAME)
    # static only: TF is never asked
    calls.clear()
    only = CameraFrames("world", "static", static, "", lookup)
    assert only.transform_for("any_camera") is static and not calls


def test_the_camera_pose_from_tf_published_by_another_process(scene, tmp_path):
    """transform_source tf: a robot_state_publisher-like process publishes world ->
    panda_link0 -> (moving joint) panda_link1 -> camera_link -> the optical frame; a cloud
    stamped between two of the moving joint's samples segments as the world-frame cloud
    (the transform taken at its stamp: the latest would be 0.3 m off); a cloud in a frame TF
    does not have is skipped with the missing frame named, and the node goes on."""
    import json
    import subprocess
    import sys
    import threading
    from pathlib import Path

    from rclpy.executors import MultiThreadedExecutor
    from scipy.spatial.transform import Rotation

    from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env, stop_process

    clean_shm_at_exit()

    def matrix(pose):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.from_quat(pose[3:]).as_matrix(), pose[:3]
        return T

    def pose(T):
        return [*map(float, T[:3, 3]), *map(float, Rotation.from_matrix(T[:3, :3]).as_quat())]

    base = [0.95, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    t0 = 1_700_000_000  # the clouds' stamp (s); the joint moves 0.3 m/s along z from t0 - 1

    def joint(t):  # panda_link0 -> panda_link1 at t s after t0
        return [0.0, 0.0, 0.333 + 0.3 * t, 0.0, 0.0, np.sin(0.2), np.cos(0.2)]

    optical = matrix(scene.camera_pose())  # what the chain must give at the cloud's stamp
    mount = np.linalg.inv(matrix(base) @ matrix(joint(0.25))) @ optical
    spec = {"static": [["world", "panda_link0", *base], ["panda_link1", "camera_link",
                                                         *pose(mount)],
                       ["camera_link", OPTICAL_FRAME, 0, 0, 0, 0, 0, 0, 1]],
            "dynamic": [["panda_link0", "panda_link1", int((t0 + t) * 1e9), *joint(t)]
                        for t in (-1.0, 0.0, 0.5, 1.0)],
            "rate_hz": 10.0}
    domain = pick_domain_id()
    proc = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("tf_tree.py")), json.dumps(spec)],
        env=ros_env(domain_id=domain, log_dir=tmp_path / "ros_log"), start_new_session=True,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    exe = MultiThreadedExecutor(num_threads=2, context=ctx)
    node = None
    try:
        assert proc.stdout.readline().strip() == "ready"
        node = _node(ctx, num_points=ALL_POINTS, transform_source="tf", tf_timeout_s=20.0,
                     camera_pose=[0.0, 0.0, 5.0, 0.0, 0.0, 0.0, 1.0])  # not used with tf
        exe.add_node(node)
        threading.Thread(target=exe.spin, daemon=True).start()
        ref = _node(ctx, num_points=ALL_POINTS).process(scene.world_cloud(labels=True))
        msg = scene.organised_cloud(labels=True)
        msg.header.stamp.sec, msg.header.stamp.nanosec = t0, 250_000_000  # between samples
        out = node.process(msg)
        assert [o.id for o in out.objects] == [1, 2]
        _assert_same_objects(out, ref)
        # the moving joint's latest sample (1 s) would put the camera 0.225 m higher
        latest = node.frames.lookup(OPTICAL_FRAME, None)
        assert latest.translation[2] == pytest.approx(optical[2, 3] + 0.225, abs=1e-6)
        # a frame the tree lacks: skipped, named, and the node goes on
        node.frames.lookup.timeout_s = 0.2  # the tree is complete: no need to wait 20 s
        other = scene.organised_cloud(labels=True, frame_id="camera_depth_optical_frame")
        with pytest.raises(FrameError, match="frame 'camera_depth_optical_frame' is not in TF"):
            node.process(other)
        node._on_cloud(other)  # logged, not raised
        assert len(node.process(msg).objects) == 2
    finally:
        exe.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        stop_process(proc)


def _ros_arg(value) -> str:
    """A parameter value as ``-p name:=value`` takes it (YAML)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list):
        return "[" + ",".join(_ros_arg(v) for v in value) + "]"
    return repr(value) if isinstance(value, float) else str(value)


@pytest.mark.slow
def test_segmentation_process_segments_a_published_optical_frame_cloud(tmp_path, context):
    """The node as its own process, the cloud from a plain rclpy publisher; its objects are
    the ones an in-process node makes of the world-frame hits."""
    import threading

    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from w2e_msgs.msg import SegmentedObjects

    from w2e_ros.bringup import Stack
    from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, ros_env
    from w2e_ros.ros.qos import LATCHED_QOS, SENSOR_QOS

    clean_shm_at_exit()
    # 128 x 96 (0.4 MB a cloud): larger best-effort clouds from a Python publisher were lost
    # here every time; coarser pixels need a wider DBSCAN neighbourhood
    small = Scene(width=128, height=96)
    params = {"use_labels": False, "cluster_eps": 0.1, "cluster_min_points": 5,
              "min_object_points": 50, "num_points": ALL_POINTS, **WORKSPACE}
    ref = _node(context, **params).process(small.world_cloud())
    assert len(ref.objects) == 2
    params.update(camera_pose=small.camera_pose(), camera_frame=OPTICAL_FRAME)
    args = [a for k, v in params.items() for a in ("-p", f"{k}:={_ros_arg(v)}")]

    domain = pick_domain_id()
    env = ros_env(domain_id=domain, log_dir=tmp_path / "ros_log")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    exe = SingleThreadedExecutor(context=ctx)
    node = Node("camera_frames_test", context=ctx)
    exe.add_node(node)
    objects: list[SegmentedObjects] = []
    node.create_subscription(SegmentedObjects, "objects", objects.append, LATCHED_QOS)
    pub = node.create_publisher(PointCloud2, "camera/points", SENSOR_QOS)
    thread = threading.Thread(target=exe.spin, daemon=True)
    thread.start()
    try:
        with Stack(nodes=["segmentation"], env=env, ready_timeout=30.0, output=None,
                   extra_args={"segmentation": args}):
            msg, end = small.organised_cloud(), time.monotonic() + 60
            while not objects and time.monotonic() < end:
                pub.publish(msg)  # best effort, as a camera: repeat until one gets through
                time.sleep(0.5)  # a camera at 2 Hz
        assert objects, "no segmented objects from the camera cloud"
        _assert_same_objects(objects[-1], ref)
    finally:
        exe.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
