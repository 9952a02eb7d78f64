"""Segmentation: the raw camera cloud in, one down-sampled cloud per object out.

Subscribes to ``camera/points`` (sensor_msgs/PointCloud2, sensor-data QoS) and publishes
w2e_msgs/SegmentedObjects on ``objects`` (reliable, transient local: a planner that starts
later still gets the latest objects). The work is done by the ROS-free
:class:`w2e_ros.ros.segmentation.Segmenter`. A malformed cloud (no x/y/z, truncated data,
NaNs only, ...) is logged with the reason and skipped; the node keeps running.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from w2e_msgs.msg import SegmentedObject, SegmentedObjects

from w2e_ros.ros.conversions import to_point, to_vector3
from w2e_ros.ros.params import declare_typed_parameters, describe, param
from w2e_ros.ros.pointcloud import CloudFormatError, arrays_to_cloud, cloud_to_arrays
from w2e_ros.ros.qos import LATCHED_QOS, SENSOR_QOS
from w2e_ros.ros.segmentation import Segmenter, SegmenterConfig
from w2e_ros.ros.spin import run_node

LABEL_FIELD = "object_id"


@dataclass
class SegmentationSettings:
    """Parameters of the segmentation node (config/w2e_stack.yaml, section segmentation)."""

    frame_id: str = param("world", "expected frame of the camera cloud ('' accepts any)")
    use_labels: bool = param(True, "use the cloud's object_id field when it has one")
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


class SegmentationNode(Node):
    """Turns camera clouds into SegmentedObjects with stable ids."""

    def __init__(self, **node_kwargs) -> None:
        """``node_kwargs`` go to Node (context, parameter_overrides: tests)."""
        super().__init__("segmentation", **node_kwargs)
        s = declare_typed_parameters(self, SegmentationSettings)
        self.settings = s
        self.get_logger().info(f"settings: {describe(s)}")
        if len(s.workspace_min) != 3 or len(s.workspace_max) != 3:
            raise ValueError("workspace_min and workspace_max need 3 values each")
        self.segmenter = Segmenter(SegmenterConfig(
            workspace_min=s.workspace_min, workspace_max=s.workspace_max,
            voxel_size=s.voxel_size, plane_distance=s.plane_distance,
            plane_min_fraction=s.plane_min_fraction, cluster_eps=s.cluster_eps,
            cluster_min_points=s.cluster_min_points, min_object_points=s.min_object_points,
            num_points=s.num_points, match_distance=s.match_distance, use_labels=s.use_labels))
        self._pub = self.create_publisher(SegmentedObjects, "objects", LATCHED_QOS)
        self.create_subscription(PointCloud2, "camera/points", self._on_cloud, SENSOR_QOS)

    def process(self, msg: PointCloud2) -> SegmentedObjects:
        """Segment one cloud message; raises CloudFormatError / ValueError for a bad one."""
        if self.settings.frame_id and msg.header.frame_id not in ("", self.settings.frame_id):
            raise CloudFormatError(f"cloud is in frame {msg.header.frame_id!r}, expected "
                                   f"{self.settings.frame_id!r} (no TF lookup here)")
        arr = cloud_to_arrays(msg)
        labels = arr.fields.get(LABEL_FIELD) if self.settings.use_labels else None
        segments = self.segmenter.segment(arr.points, arr.normals, labels)
        out = SegmentedObjects(header=msg.header)
        for seg in segments:
            out.objects.append(SegmentedObject(
                id=int(seg.id),
                cloud=arrays_to_cloud(seg.points, seg.normals, header=msg.header),
                centroid=to_point(seg.centroid),
                extent=to_vector3(seg.extent),
                num_raw_points=int(seg.num_raw_points)))
        return out

    def _on_cloud(self, msg: PointCloud2) -> None:
        t0 = time.perf_counter()
        try:
            out = self.process(msg)
        except (CloudFormatError, ValueError) as err:
            self.get_logger().error(f"skipping malformed camera cloud: {err}",
                                    throttle_duration_sec=5.0)
            return
        self._pub.publish(out)
        self.get_logger().debug(
            f"{len(out.objects)} objects from {msg.width * msg.height} points in "
            f"{(time.perf_counter() - t0) * 1e3:.0f} ms")


def main(args: list[str] | None = None) -> None:
    """Run the segmentation node."""
    run_node(SegmentationNode, args, threads=1)


if __name__ == "__main__":
    main()
