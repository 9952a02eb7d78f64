"""PointNet++ SSG segmentation encoder: per-point features for a partial point cloud.

Layers as small modules over the plain functions of ``pointnet2_geometry``; sizes come from
``ModelConfig``. ReLUs are not in-place (in-place slowed backward by ~30 %).
"""

from __future__ import annotations

import torch
from torch import nn

from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.pointnet2_geometry import (
    group_knn,
    sample_and_group,
    sample_and_group_all,
    three_interpolate,
)


def _norm(kind: str, c: int, groups: int, dims: int) -> nn.Module:
    """GroupNorm keeps every cloud's features independent of the other clouds in a batch:
    no train / eval gap on 1-cloud fine-tuning batches, and no path by which the batch
    statistics of C_sim clouds reach the affordance loss of C_aff clouds. BatchNorm is the
    reference's choice, kept as an option."""
    if kind == "group":
        return nn.GroupNorm(min(groups, c), c)
    if kind == "batch":
        return nn.BatchNorm2d(c) if dims == 2 else nn.BatchNorm1d(c)
    raise ValueError(f"unknown norm {kind!r} (group | batch)")


def _mlp(c_in: int, widths: tuple[int, ...], cfg: ModelConfig, dims: int) -> nn.Sequential:
    conv = nn.Conv2d if dims == 2 else nn.Conv1d
    layers: list[nn.Module] = []
    for c in widths:
        layers += [conv(c_in, c, 1, bias=False), _norm(cfg.norm, c, cfg.norm_groups, dims),
                   nn.ReLU()]
        c_in = c
    return nn.Sequential(*layers)


class SetAbstraction(nn.Module):
    """Sample centroids, group neighbours, shared MLP, max-pool over each neighbourhood."""

    def __init__(self, npoint: int | None, radius: float, nsample: int, c_in: int,
                 mlp: tuple[int, ...], cfg: ModelConfig) -> None:
        super().__init__()
        self.npoint, self.radius, self.nsample = npoint, radius, nsample
        self.mlp = _mlp(c_in + 3, mlp, cfg, dims=2)

    def forward(self, xyz: torch.Tensor,
                feats: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """xyz (B, N, 3), feats (B, N, C) -> new_xyz (B, S, 3), new_feats (B, S, C')."""
        if self.npoint is None:
            new_xyz, grouped = sample_and_group_all(xyz, feats)
        else:
            new_xyz, grouped = sample_and_group(self.npoint, self.radius, self.nsample, xyz,
                                                feats)
        x = self.mlp(grouped.permute(0, 3, 1, 2))  # (B, C', S, K)
        return new_xyz, x.amax(dim=-1).transpose(1, 2)


class FeaturePropagation(nn.Module):
    """Interpolate coarse features onto finer points, concatenate skip features, MLP."""

    def __init__(self, c_in: int, mlp: tuple[int, ...], cfg: ModelConfig) -> None:
        super().__init__()
        self.mlp = _mlp(c_in, mlp, cfg, dims=1)

    def forward(self, xyz1: torch.Tensor, xyz2: torch.Tensor, feats1: torch.Tensor | None,
                feats2: torch.Tensor) -> torch.Tensor:
        """fine (B, N, 3) [+ (B, N, C1)], coarse (B, S, 3) + (B, S, C2) -> (B, N, C')."""
        x = three_interpolate(xyz1, xyz2, feats2)  # (B, N, C2)
        if feats1 is not None:
            x = torch.cat([x, feats1], dim=-1)
        return self.mlp(x.transpose(1, 2)).transpose(1, 2)


class PointNet2Encoder(nn.Module):
    """(B, N, 3) cloud -> (B, N, feat_dim) per-point features."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        # xyz_features: every point carries its (centred) coordinates as input features, as
        # the reference feeds its cloud twice: the first level then sees absolute positions
        # besides the offsets, and the last propagation layer the query point's own position
        # local_k: every point also carries a descriptor of its k nearest input points (a
        # PointNet over their offsets): the first level's centroids are ~2 point spacings
        # apart, so without it a contact's feature is only interpolated between them
        self.local = _mlp(3, cfg.local_mlp, cfg, dims=2) if cfg.local_k else None
        c0 = (3 if cfg.xyz_features else 0) + (cfg.local_mlp[-1] if cfg.local_k else 0)
        sa, c = [], c0
        for npoint, radius, nsample, mlp in zip(cfg.sa_npoint, cfg.sa_radius, cfg.sa_nsample,
                                                cfg.sa_mlp, strict=True):
            sa.append(SetAbstraction(npoint, radius, nsample, c, mlp, cfg))
            c = mlp[-1]
        self.sa = nn.ModuleList(sa)
        # skip widths from the deepest level back to the input (which has none)
        skips = [m[-1] for m in cfg.sa_mlp[:-1]][::-1] + [c0]
        fp, c = [], cfg.sa_mlp[-1][-1]
        for skip, mlp in zip(skips, cfg.fp_mlp, strict=True):
            fp.append(FeaturePropagation(c + skip, mlp, cfg))
            c = mlp[-1]
        self.fp = nn.ModuleList(fp)
        self.out = _mlp(c, (cfg.feat_dim,), cfg, dims=1)
        if cfg.feat_activation == "none":  # the ReLU has no weights: checkpoints load either way
            self.out = self.out[:-1]

    def abstract(self, xyz: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor | None]]:
        """The set-abstraction levels: points (B, N_l, 3) and features (B, N_l, C_l) per level,
        the input first (no features). All the geometry (sampling, grouping) happens here."""
        xyzs: list[torch.Tensor] = [xyz]
        feats: list[torch.Tensor | None] = [self._point_features(xyz)]
        for layer in self.sa:
            new_xyz, new_feats = layer(xyzs[-1], feats[-1])
            xyzs.append(new_xyz)
            feats.append(new_feats)
        return xyzs, feats

    def _point_features(self, xyz: torch.Tensor) -> torch.Tensor | None:
        """Input features of every point (B, N, C0): coordinates and / or the local
        descriptor, as the config asks; None for the plain encoder."""
        parts = []
        if self.cfg.xyz_features:
            parts.append(xyz)
        if self.local is not None:
            grouped = group_knn(self.cfg.local_k, xyz)  # (B, N, k, 3)
            parts.append(self.local(grouped.permute(0, 3, 1, 2)).amax(dim=-1).transpose(1, 2))
        return torch.cat(parts, dim=-1) if parts else None

    def propagate(self, xyzs: list[torch.Tensor],
                  feats: list[torch.Tensor | None]) -> torch.Tensor:
        """Feature propagation from the deepest level back to the input points: (B, N, F).
        Split from ``abstract`` so fine-tuning can train these layers on cached levels."""
        x = feats[-1]
        for i, layer in enumerate(self.fp):
            fine = len(self.sa) - 1 - i  # level receiving the features
            x = layer(xyzs[fine], xyzs[fine + 1], feats[fine], x)
        return self.out(x.transpose(1, 2)).transpose(1, 2)  # (B, N, feat_dim)

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        return self.propagate(*self.abstract(xyz))
