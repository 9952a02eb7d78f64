"""Farthest point sampling: the ``fpsample`` package on the CPU, plain torch otherwise.

``fpsample``'s bucket FPS (a kd-tree over the cloud) takes 0.6 ms for 512 of 2,048 points
where the torch loop takes ~15 ms on one thread, so it stays the CPU default. The torch loop
serves CUDA tensors (no copy to the host and back inside the model) and every machine where
``fpsample`` cannot be imported (no wheel for the GPU machine's Python 3.12).

Both are exact FPS: each new sample is the point farthest from those chosen so far. They
differ in two ways, both measured in ``test_fps_torch.py``:

* ``fpsample.bucket_fps_kdline_sampling`` (1.0.2) does not start at ``start_idx``: its first
  sample is the point at that position of its kd-tree's own order (which depends on ``h``).
  From its first sample on, its indices are exactly those of this loop started there.
* Two points exactly as far (a pixel grid on a flat face gives such ties) are taken in a
  different order: this loop takes the lower index, as ``torch.argmax`` does.
"""

from __future__ import annotations

from functools import cache
from types import ModuleType

import torch


@cache
def load_fpsample() -> ModuleType | None:
    """The ``fpsample`` module, or None where it cannot be imported (checked once)."""
    try:
        import fpsample
    except ImportError:
        return None
    return fpsample


def farthest_point_sample_torch(xyz: torch.Tensor, npoint: int,
                                start: int | torch.Tensor = 0) -> torch.Tensor:
    """(B, N, 3) -> (B, npoint) long indices of exact FPS from point ``start`` (an int or
    (B,) indices), on ``xyz``'s device. Distances in float32 as ``(dx*dx + dy*dy) + dz*dz``,
    the order ``fpsample`` sums in, so the same cloud gives the same indices."""
    B, N, _ = xyz.shape
    pts = xyz.detach().float()
    dev = pts.device
    idx = torch.empty(B, npoint, dtype=torch.long, device=dev)
    nearest = torch.full((B, N), float("inf"), device=dev)  # to the samples so far
    far = torch.as_tensor(start, dtype=torch.long, device=dev).expand(B).clone()
    rows = torch.arange(B, device=dev)
    for i in range(npoint):
        idx[:, i] = far
        sq = (pts - pts[rows, far].unsqueeze(1)).square()  # (B, N, 3)
        nearest = torch.minimum(nearest, sq[..., 0] + sq[..., 1] + sq[..., 2])
        far = nearest.argmax(1)  # the first of equally far points
    return idx
