"""Point cloud helpers shared by the collector, the offline world and the segmentation node."""

from __future__ import annotations

import numpy as np

from w2e_ros.core.robot.fps import load_fpsample


def fps_indices(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Indices of ``n`` furthest-point samples of (P, 3) points (bucket FPS, ms not 100 ms;
    the torch loop where ``fpsample`` cannot be imported: other samples for the same seed,
    as their first points differ, see :mod:`w2e_ros.core.robot.fps`).

    Clouds with fewer than ``n`` points are padded by repeating points, so every stored cloud
    has exactly ``n`` rows; deterministic for a given seed.
    """
    points = np.ascontiguousarray(points, dtype=np.float32)
    p = len(points)
    if p == 0:
        raise ValueError("cannot sample an empty point cloud")
    if p <= n:
        rng = np.random.default_rng(seed)
        extra = rng.integers(0, p, size=n - p)
        return np.concatenate([np.arange(p), extra]).astype(np.int64)
    start = int(np.random.default_rng(seed).integers(0, p))
    fpsample = load_fpsample()
    if fpsample is None:
        import torch

        from w2e_ros.core.robot.fps import farthest_point_sample_torch

        return farthest_point_sample_torch(torch.from_numpy(points)[None], n, start)[0].numpy()
    height = 7 if p > 4096 else 5
    idx = fpsample.bucket_fps_kdline_sampling(points, n, h=height, start_idx=start)
    return np.asarray(idx, dtype=np.int64)


def check_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> None:
    """Reject clouds the model cannot use, with a message that says why."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"point cloud must be (N, 3), got {points.shape}")
    if len(points) < 16:
        raise ValueError(f"point cloud has {len(points)} points; at least 16 are needed")
    if not np.isfinite(points).all():
        raise ValueError("point cloud contains NaN or infinite coordinates")
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != points.shape:
            raise ValueError(f"normals {normals.shape} do not match points {points.shape}")
        if not np.isfinite(normals).all():
            raise ValueError("normals contain NaN or infinite values")


def protrusion(points: np.ndarray, normals: np.ndarray, k: int = 32) -> np.ndarray:
    """(N,) how far each point stands out of its neighbourhood along its own normal.

    Handles, knobs, levers and free edges stand out; flat boards do not. The collector uses it
    to propose contacts where a gripper can actually grasp something.
    """
    from scipy.spatial import cKDTree

    k = min(k, len(points))
    _, nb = cKDTree(points).query(points, k=k)
    centre = np.median(points[nb], axis=1)
    return np.einsum("ij,ij->i", points - centre, normals).astype(np.float32)
