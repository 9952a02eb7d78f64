"""Segmentation: the raw camera cloud in, one down-sampled cloud per object out.

Subscribes to ``camera/points`` (sensor_msgs/PointCloud2, sensor-data QoS) and publishes
w2e_msgs/SegmentedObjects on ``objects`` (reliable, transient local: a planner that starts
later still gets the latest objects). The work is done by the ROS-free
:class:`w2e_ros.ros.segmentation.Segmenter`, in the robot frame ``frame_id``.

A cloud in another frame (a real camera's optical frame: organised, NaN where the depth is
missing, packed ``rgb``) is moved into ``frame_id`` first, by the robot's TF tree (``/tf``,
``/tf_static``, at the cloud's stamp: :mod:`w2e_ros.ros.tf`) or by the static ``camera_pose``
(:mod:`w2e_ros.ros.transforms`); its invalid points are dropped, its colours ignored. A malformed
cloud (no x/y/z, truncated data, ...) or one without a transform is logged with the reason and
skipped; the node keeps running.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from w2e_msgs.msg import SegmentedObject, SegmentedObjects

from w2e_ros.ros.conversions import to_point, to_vector3
from w2e_ros.ros.params import declare_typed_parameters, describe, param
from w2e_ros.ros.pointcloud import (
    MOVABLE_FIELD,
    CloudFormatError,
    arrays_to_cloud,
    cloud_to_arrays,
)
from w2e_ros.ros.qos import LATCHED_QOS, SENSOR_QOS
from w2e_ros.ros.segmentation import Segmenter, SegmenterConfig
from w2e_ros.ros.spin import run_node
from w2e_ros.ros.tf import TfLookup
from w2e_ros.ros.transforms import TRANSFORM_SOURCES, CameraFrames, parse_camera_pose

LABEL_FIELD = "object_id"


@dataclass
class SegmentationSettings:
    """Parameters of the segmentation node (config/w2e_stack.yaml, section segmentation)."""

    frame_id: str = param("world", "robot frame: clouds are moved into it, segmented and "
                          "published in it ('': any cloud as it is, no transform)")
    transform_source: str = param(
        "auto", "camera-to-frame_id transform: tf (the robot's TF tree on /tf and /tf_static at "
        "the cloud's stamp; no transform: the cloud is skipped, the missing edge named), static "
        "(camera_pose only, TF not listened to), auto (TF, camera_pose when TF has none)")
    camera_pose: list[float] = param(
        [], "static pose of the camera's cloud frame in frame_id, x y z qx qy qz qw as "
        "static_transform_publisher takes it ([]: none)")
    camera_frame: str = param(
        "", "the cloud frame camera_pose is for, e.g. camera_color_optical_frame ('': any "
        "frame other than frame_id)")
    tf_timeout_s: float = param(0.2, "how long one TF lookup may wait for transforms not yet "
                                "received (s)", min=0.0)
    tf_tolerance_s: float = param(
        0.1, "a cloud stamped outside a moving TF edge's history by at most this takes the "
        "edge's nearest transform (s; inside it, transforms are interpolated)", min=0.0)
    tf_cache_s: float = param(10.0, "history kept per moving TF edge (s)", min=0.1)
    use_labels: bool = param(True, "use the cloud's object_id field when it has one")
    forward_movable: bool = param(
        True, "carry the cloud's movable field (the simulator's ground-truth movable parts) "
        "into the object clouds, so exploration and manipulate act on movable parts as the "
        "reference does in simulation; a real camera's cloud has no such field")
    workspace_min: list[float] = param([-3.0, -3.0, -0.5], "workspace box, lower corner (m)")
    workspace_max: list[float] = param([3.0, 3.0, 3.0], "workspace box, upper corner (m)")
    plane_distance: float = param(0.01, "RANSAC inlier distance of the table plane (m)",
                                  min=0.0)
    plane_min_fraction: float = param(0.05, "share of points the table plane must hold",
                                      min=0.0, max=1.0)
    cluster_eps: float = param(0.05, "DBSCAN neighbourhood (m)", min=0.0)
    cluster_min_points: int = param(10, "DBSCAN core-point threshold", min=1)
    min_object_points: int = param(200, "clusters with fewer raw points are noise", min=1)
    num_points: int = param(2048, "farthest-point samples per object", min=1)
    match_distance: float = param(0.2, "centroid distance that keeps an id across frames (m)",
                                  min=0.0)
    voxel_size: float = param(0.01, "voxel size before clustering (m; 0: off)", min=0.0)
    max_points: int = param(
        2_000_000, "clouds with more points are dropped with an error (an Azure Kinect frame "
        "has at most 1,048,576; a larger cloud is a driver fault that would stall the node)",
        min=1)


class SegmentationNode(Node):
    """Turns camera clouds into SegmentedObjects with stable ids."""

    def __init__(self, **node_kwargs) -> None:
        """``node_kwargs`` go to Node (context, parameter_overrides: tests)."""
        super().__init__("segmentation", **node_kwargs)
        s = declare_typed_parameters(self, SegmentationSettings)
        self.settings = s
        self.dropped = 0  # malformed or unusable camera clouds skipped since start
        self.get_logger().info(f"settings: {describe(s)}")
        if len(s.workspace_min) != 3 or len(s.workspace_max) != 3:
            raise ValueError("workspace_min and workspace_max need 3 values each")
        self.frames = self._camera_frames(s)
        self.segmenter = Segmenter(SegmenterConfig(
            workspace_min=s.workspace_min, workspace_max=s.workspace_max,
            voxel_size=s.voxel_size, plane_distance=s.plane_distance,
            plane_min_fraction=s.plane_min_fraction, cluster_eps=s.cluster_eps,
            cluster_min_points=s.cluster_min_points, min_object_points=s.min_object_points,
            num_points=s.num_points, match_distance=s.match_distance, use_labels=s.use_labels))
        self._pub = self.create_publisher(SegmentedObjects, "objects", LATCHED_QOS)
        # clouds one at a time (the segmenter tracks ids); a TF lookup waiting in this callback
        # lets the listener's reentrant callbacks run on the executor's other thread
        self.create_subscription(PointCloud2, "camera/points", self._on_cloud, SENSOR_QOS,
                                 callback_group=MutuallyExclusiveCallbackGroup())

    def _camera_frames(self, s: SegmentationSettings) -> CameraFrames:
        """The transform rule of the settings; ValueError for a bad pose or source."""
        if s.transform_source not in TRANSFORM_SOURCES:
            raise ValueError(f"transform_source must be one of {TRANSFORM_SOURCES}, got "
                             f"{s.transform_source!r}")
        static = parse_camera_pose(s.camera_pose)
        use_tf = bool(s.frame_id) and s.transform_source in ("tf", "auto")
        lookup = (TfLookup(self, s.frame_id, s.tf_timeout_s, s.tf_tolerance_s, s.tf_cache_s)
                  if use_tf else None)
        log = self.get_logger()
        where = ("TF (/tf, /tf_static)" + (", camera_pose as the fallback"
                                          if static and s.transform_source == "auto" else "")
                 if lookup else "camera_pose" if static else "none: clouds must be in frame_id")
        log.info(f"clouds in other frames than {s.frame_id!r}: transform from {where}"
                 if s.frame_id else "frame_id is '': clouds are segmented in their own frame")
        return CameraFrames(s.frame_id, s.transform_source if lookup else "static", static,
                            s.camera_frame, lookup,
                            warn=lambda m: log.warning(m, throttle_duration_sec=10.0),
                            knows=lookup.knows if lookup else None)

    def process(self, msg: PointCloud2) -> SegmentedObjects:
        """Segment one cloud message; raises CloudFormatError / ValueError for a bad one
        (FrameError, a CloudFormatError, when there is no transform into frame_id)."""
        if msg.width * msg.height > self.settings.max_points:
            raise CloudFormatError(f"{msg.width} x {msg.height} points is more than max_points "
                                   f"{self.settings.max_points}")
        names = {f.name for f in msg.fields}
        wanted = tuple(f for f, on in ((LABEL_FIELD, self.settings.use_labels),
                                       (MOVABLE_FIELD, self.settings.forward_movable))
                       if on and f in names)
        arr = cloud_to_arrays(msg, fields=wanted, drop_nonfinite=True)
        to_robot = self.frames.transform_for(msg.header.frame_id, msg.header.stamp)
        header = msg.header
        if to_robot is not None:
            arr.points = to_robot.apply(arr.points)
            arr.normals = to_robot.rotate(arr.normals) if arr.normals is not None else None
            header = Header(stamp=msg.header.stamp, frame_id=self.settings.frame_id)
        labels = arr.fields.get(LABEL_FIELD)
        segments = self.segmenter.segment(arr.points, arr.normals, labels,
                                          arr.fields.get(MOVABLE_FIELD))
        out = SegmentedObjects(header=header)
        for seg in segments:
            out.objects.append(SegmentedObject(
                id=int(seg.id),
                cloud=arrays_to_cloud(
                    seg.points, seg.normals, header=header,
                    fields=None if seg.movable is None else {
                        MOVABLE_FIELD: seg.movable.astype(np.uint8)}),
                centroid=to_point(seg.centroid),
                extent=to_vector3(seg.extent),
                num_raw_points=int(seg.num_raw_points)))
        return out

    def destroy_node(self) -> None:
        """Say at shutdown how many camera clouds were skipped (the errors are throttled)."""
        if self.dropped:
            self.get_logger().info(f"{self.dropped} camera cloud(s) skipped in all")
        super().destroy_node()

    def _on_cloud(self, msg: PointCloud2) -> None:
        t0 = time.perf_counter()
        try:
            out = self.process(msg)
        except (CloudFormatError, ValueError) as err:
            self.dropped += 1
            self.get_logger().error(f"skipping camera cloud ({self.dropped} dropped so far): "
                                    f"{err}", throttle_duration_sec=5.0)
            return
        self._pub.publish(out)
        self.get_logger().debug(
            f"{len(out.objects)} objects from {msg.width * msg.height} points in "
            f"{(time.perf_counter() - t0) * 1e3:.0f} ms")


def main(args: list[str] | None = None) -> None:
    """Run the segmentation node."""
    run_node(SegmentationNode, args, threads=2)


if __name__ == "__main__":
    main()
