"""Camera cloud -> one down-sampled cloud with normals per object, ids stable across frames.

Plain Python (numpy, Open3D, SciPy; no rclpy) so it is unit-testable; the segmentation node
wraps it. Steps: drop non-finite points, crop to the workspace box, remove the table plane
(RANSAC, Open3D ``segment_plane``) and everything below it, cluster the rest (DBSCAN on a
voxel-down-sampled copy; every raw point joins the cluster of its nearest voxel point),
keep clusters large enough, farthest-point-sample each to N points, and give each the id
of the previous frame's object whose centroid is nearest (within ``match_distance``).

When the cloud carries ground-truth labels (the simulator's ``object_id`` field) and
``use_labels`` is on, the labels replace plane removal and clustering, and the ids are the
scene's object ids (0 = table).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from w2e_ros.core.robot.pointcloud import fps_indices


@dataclass
class SegmenterConfig:
    """Tuning of :class:`Segmenter` (the node reads it from its parameters)."""

    workspace_min: list[float] = field(default_factory=lambda: [-3.0, -3.0, -0.5])
    workspace_max: list[float] = field(default_factory=lambda: [3.0, 3.0, 3.0])
    voxel_size: float = 0.01  # m; 0 = cluster the raw points
    plane_distance: float = 0.01  # RANSAC inlier distance (m)
    plane_min_fraction: float = 0.05  # the table must hold at least this share of the points
    plane_max_tilt_deg: float = 30.0  # the table's normal is within this of +z (world frame)
    cluster_eps: float = 0.05  # DBSCAN neighbourhood (m)
    cluster_min_points: int = 10  # DBSCAN core point threshold (on the voxel cloud)
    min_object_points: int = 200  # smaller clusters (raw points) are noise
    num_points: int = 2048  # farthest-point samples per object
    match_distance: float = 0.2  # centroid distance that keeps an id across frames (m)
    use_labels: bool = True
    normal_radius: float = 0.03  # normal estimation radius when the cloud has none (m)


@dataclass
class Segment:
    """One object of one frame."""

    id: int
    points: np.ndarray  # (num_points, 3) float32
    normals: np.ndarray  # (num_points, 3) float32, unit
    centroid: np.ndarray  # (3,) mean of the raw points
    extent: np.ndarray  # (3,) axis-aligned size of the raw points
    num_raw_points: int
    movable: np.ndarray | None = None  # (num_points,) bool, from the cloud's movable field


class Segmenter:
    """Stateful (the tracks) segmentation of successive camera clouds."""

    def __init__(self, config: SegmenterConfig | None = None) -> None:
        self.config = config or SegmenterConfig()
        self._tracks: dict[int, np.ndarray] = {}  # id -> last centroid
        self._next_id = 1

    def reset(self) -> None:
        """Forget the tracked objects (ids start again at 1)."""
        self._tracks.clear()
        self._next_id = 1

    def segment(self, points: np.ndarray, normals: np.ndarray | None = None,
                labels: np.ndarray | None = None,
                movable: np.ndarray | None = None) -> list[Segment]:
        """Segment one frame; raises ValueError for arrays of the wrong shape. ``movable``
        (per point, the simulator's ground truth) is carried into each segment's samples."""
        c = self.config
        points = np.asarray(points, dtype=np.float32)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got {points.shape}")
        if normals is not None:
            normals = np.asarray(normals, dtype=np.float32)
            if normals.shape != points.shape:
                raise ValueError(f"normals {normals.shape} do not match points {points.shape}")
        if labels is not None:
            labels = np.asarray(labels).reshape(-1)
            if len(labels) != len(points):
                raise ValueError(f"{len(labels)} labels for {len(points)} points")
        if movable is not None:
            movable = np.asarray(movable).reshape(-1).astype(bool)
            if len(movable) != len(points):
                raise ValueError(f"{len(movable)} movable flags for {len(points)} points")

        keep = np.isfinite(points).all(axis=1)
        if normals is not None:
            keep &= np.isfinite(normals).all(axis=1)
        lo, hi = np.asarray(c.workspace_min, np.float32), np.asarray(c.workspace_max, np.float32)
        keep &= ((points >= lo) & (points <= hi)).all(axis=1)
        points = points[keep]
        normals = normals[keep] if normals is not None else None
        labels = labels[keep] if labels is not None else None
        movable = movable[keep] if movable is not None else None
        if len(points) == 0:
            return []

        if labels is not None and c.use_labels:
            groups = [(int(k), np.flatnonzero(labels == k)) for k in np.unique(labels) if k > 0]
        else:
            groups = [(-1, idx) for idx in self._clusters(points)]
        segments = []
        for label, idx in groups:
            if len(idx) < c.min_object_points:
                continue
            segments.append(self._make_segment(
                label, points[idx], normals[idx] if normals is not None else None,
                movable[idx] if movable is not None else None))
        if labels is None or not c.use_labels:
            self._assign_ids(segments)
        return sorted(segments, key=lambda s: s.id)

    # -- steps ----------------------------------------------------------------------------
    def _clusters(self, points: np.ndarray) -> list[np.ndarray]:
        """Indices of each object cluster after removing the table plane."""
        import open3d as o3d
        from scipy.spatial import cKDTree

        c = self.config
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
        rest = np.arange(len(points))
        if len(points) >= 3:
            model, inliers = pcd.segment_plane(c.plane_distance, 3, 200)
            normal = np.asarray(model[:3], float)
            normal /= max(np.linalg.norm(normal), 1e-12)
            d = model[3] / max(np.linalg.norm(model[:3]), 1e-12)
            if normal[2] < 0:
                normal, d = -normal, -d
            tilt = np.degrees(np.arccos(np.clip(normal[2], -1.0, 1.0)))
            if len(inliers) >= c.plane_min_fraction * len(points) and tilt <= c.plane_max_tilt_deg:
                height = points @ normal + d  # signed distance above the table
                rest = np.flatnonzero(height > c.plane_distance)
        if len(rest) == 0:
            return []
        sub = points[rest]
        if c.voxel_size > 0:
            vpcd = o3d.geometry.PointCloud(
                o3d.utility.Vector3dVector(sub.astype(np.float64))).voxel_down_sample(c.voxel_size)
            vpts = np.asarray(vpcd.points)
        else:
            vpts = sub.astype(np.float64)
        vpcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(vpts))
        vlab = np.asarray(vpcd.cluster_dbscan(c.cluster_eps, c.cluster_min_points))
        _, nearest = cKDTree(vpts).query(sub, k=1)
        lab = vlab[nearest]
        return [rest[lab == k] for k in range(int(lab.max()) + 1)] if len(lab) else []

    def _make_segment(self, label: int, pts: np.ndarray, nrm: np.ndarray | None,
                      movable: np.ndarray | None = None) -> Segment:
        c = self.config
        centroid = pts.mean(axis=0).astype(np.float64)
        extent = (pts.max(axis=0) - pts.min(axis=0)).astype(np.float64)
        idx = fps_indices(pts, c.num_points, seed=len(pts))
        sp = pts[idx]
        sn = self._estimate_normals(pts)[idx] if nrm is None else nrm[idx]
        sn = sn / np.maximum(np.linalg.norm(sn, axis=1, keepdims=True), 1e-12)
        return Segment(id=label, points=sp.astype(np.float32), normals=sn.astype(np.float32),
                       centroid=centroid, extent=extent, num_raw_points=len(pts),
                       movable=movable[idx] if movable is not None else None)

    def _estimate_normals(self, pts: np.ndarray) -> np.ndarray:
        """Normals for a cloud without them, oriented away from the cluster's centre."""
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(self.config.normal_radius, 30))
        n = np.asarray(pcd.normals)
        out = pts - pts.mean(axis=0)
        n[np.sum(n * out, axis=1) < 0] *= -1
        return n.astype(np.float32)

    def _assign_ids(self, segments: list[Segment]) -> None:
        """Match segments to the previous frame's tracks by centroid (optimal assignment)."""
        from scipy.optimize import linear_sum_assignment

        ids = list(self._tracks)
        if segments and ids:
            prev = np.stack([self._tracks[i] for i in ids])
            cur = np.stack([s.centroid for s in segments])
            cost = np.linalg.norm(cur[:, None] - prev[None], axis=2)
            rows, cols = linear_sum_assignment(cost)
            for r, col in zip(rows, cols, strict=True):
                if cost[r, col] <= self.config.match_distance:
                    segments[r].id = ids[col]
        for s in segments:
            if s.id < 0:
                s.id = self._next_id
                self._next_id += 1
        # objects out of view keep their track (an object hidden for a frame keeps its id)
        for s in segments:
            self._tracks[s.id] = s.centroid
