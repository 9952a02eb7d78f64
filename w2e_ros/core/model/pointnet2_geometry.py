"""PointNet++ geometry as plain functions: sampling, grouping, interpolation.

Chosen for a 2-core CPU: furthest point sampling runs as bucket FPS in the
``fpsample`` package on the CPU (ms instead of a 100 ms torch loop; the torch loop of
:mod:`w2e_ros.core.robot.fps` on CUDA or without ``fpsample``), squared distances are one matrix
product, and the ball query keeps the ``nsample`` NEAREST points inside the radius (a top-k
instead of a full sort; the reference keeps the first ``nsample`` by index, a random subset of
the ball). Nothing here has parameters or gradients of its own except through the gathered
coordinates.
"""

from __future__ import annotations

import numpy as np
import torch

from w2e_ros.core.robot.fps import farthest_point_sample_torch, load_fpsample


def square_distance(src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
    """(B, S, 3), (B, N, 3) -> (B, S, N) squared distances, as one matmul."""
    d = -2.0 * torch.bmm(src, dst.transpose(1, 2))
    d = d + (src * src).sum(-1, keepdim=True) + (dst * dst).sum(-1).unsqueeze(1)
    return d.clamp_min(0.0)


def index_points(points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """(B, N, C) gathered at (B, ...) indices -> (B, ..., C)."""
    B = points.shape[0]
    batch = torch.arange(B, device=points.device).view(B, *([1] * (idx.dim() - 1)))
    return points[batch, idx]


def _fps_height(n: int) -> int:
    # fpsample's advice: small clouds h=3, medium 5-7; measured best for 2k / 10k points
    return 3 if n <= 2048 else (5 if n <= 8192 else 7)


def farthest_point_sample(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
    """(B, N, 3) -> (B, npoint) long indices, deterministic: bucket FPS (``fpsample``) for CPU
    tensors, the torch loop from point 0 for CUDA tensors or without ``fpsample``. The two
    start at different points (see :mod:`w2e_ros.core.robot.fps`), so their centroids differ."""
    B, N, _ = xyz.shape
    if npoint >= N:
        return torch.arange(N, device=xyz.device).repeat(B, 1)[:, :npoint]
    fpsample = load_fpsample()
    if xyz.is_cuda or fpsample is None:
        return farthest_point_sample_torch(xyz, npoint)
    pts = xyz.detach().to("cpu", torch.float32).numpy()
    h = _fps_height(N)
    out = np.stack([
        np.asarray(fpsample.bucket_fps_kdline_sampling(pts[b], npoint, h=h, start_idx=0))
        for b in range(B)
    ])
    return torch.from_numpy(out.astype(np.int64)).to(xyz.device)


def query_ball_point(radius: float, nsample: int, xyz: torch.Tensor,
                     new_xyz: torch.Tensor) -> torch.Tensor:
    """Nearest ``nsample`` of ``xyz`` (B, N, 3) within ``radius`` of each ``new_xyz`` (B, S, 3).

    Returns (B, S, nsample) indices; slots with no point inside the ball repeat the nearest
    one (the centroid itself when it is one of ``xyz``), as the reference pads with the first.
    """
    k = min(nsample, xyz.shape[1])
    d = square_distance(new_xyz, xyz)  # (B, S, N)
    dist, idx = torch.topk(d, k, dim=-1, largest=False, sorted=True)  # (B, S, k)
    outside = dist > radius * radius
    idx = torch.where(outside, idx[:, :, :1].expand_as(idx), idx)
    if k < nsample:  # fewer points than neighbours asked for: pad with the nearest
        idx = torch.cat([idx, idx[:, :, :1].expand(-1, -1, nsample - k)], dim=-1)
    return idx


def sample_and_group(npoint: int, radius: float, nsample: int, xyz: torch.Tensor,
                     feats: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Centroids and their local neighbourhoods for one set-abstraction level.

    xyz (B, N, 3), feats (B, N, C) or None -> new_xyz (B, S, 3),
    grouped (B, S, nsample, 3 + C): neighbour offsets from the centroid, then features.
    """
    fps_idx = farthest_point_sample(xyz, npoint)  # (B, S)
    new_xyz = index_points(xyz, fps_idx)  # (B, S, 3)
    idx = query_ball_point(radius, nsample, xyz, new_xyz)  # (B, S, K)
    grouped = index_points(xyz, idx) - new_xyz.unsqueeze(2)  # (B, S, K, 3)
    if feats is not None:
        grouped = torch.cat([grouped, index_points(feats, idx)], dim=-1)
    return new_xyz, grouped


def group_knn(k: int, xyz: torch.Tensor) -> torch.Tensor:
    """Every point's ``k`` nearest neighbours (itself first) as offsets from it:
    (B, N, 3) -> (B, N, k, 3). The full-resolution neighbourhood a contact point sits in."""
    k = min(k, xyz.shape[1])
    if xyz.device.type == "cpu":  # a k-d tree: ~2 ms a cloud where the (N, N) top-k took 90
        from scipy.spatial import cKDTree

        pts = xyz.detach().numpy()
        idx = torch.from_numpy(np.stack([cKDTree(p).query(p, k)[1].reshape(len(p), k)
                                         for p in pts]).astype(np.int64))
    else:
        idx = torch.topk(square_distance(xyz, xyz), k, dim=-1, largest=False, sorted=True)[1]
    return index_points(xyz, idx) - xyz.unsqueeze(2)


def sample_and_group_all(xyz: torch.Tensor,
                         feats: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """One group holding every point, centred at the origin: (B, 1, 3), (B, 1, N, 3 + C)."""
    B, _, _ = xyz.shape
    new_xyz = torch.zeros(B, 1, 3, device=xyz.device, dtype=xyz.dtype)
    grouped = xyz.unsqueeze(1)
    if feats is not None:
        grouped = torch.cat([grouped, feats.unsqueeze(1)], dim=-1)
    return new_xyz, grouped


def three_interpolate(xyz1: torch.Tensor, xyz2: torch.Tensor,
                      feats2: torch.Tensor) -> torch.Tensor:
    """Inverse-distance interpolation of ``feats2`` (B, S, C) at ``xyz2`` (B, S, 3) onto the
    points ``xyz1`` (B, N, 3) from their 3 nearest neighbours -> (B, N, C)."""
    S = xyz2.shape[1]
    if S == 1:
        return feats2.expand(-1, xyz1.shape[1], -1)
    k = min(3, S)
    d = square_distance(xyz1, xyz2)  # (B, N, S)
    dist, idx = torch.topk(d, k, dim=-1, largest=False)  # (B, N, k)
    w = 1.0 / (dist + 1e-8)
    w = w / w.sum(-1, keepdim=True)
    return (index_points(feats2, idx) * w.unsqueeze(-1)).sum(2)
