"""Pillar Feature Net: decorate each point, one PointNet layer, max over the pillar (second half of "Feature Extract").

Decorations per point (reference / Open3D-ML ``PillarFeatureNet``): the raw features (x, y, z[, r]), then
``x - x_mean, y - y_mean, z - z_mean`` (mean over the pillar's real points), then ``x - x_c, y - y_c`` with the pillar
centre ``x_c = ix * vx + vx / 2 + x_min`` (same for y). That is 8 features for xyz input and 9 for xyzr (OpenPCDet's
extra ``z - z_c`` is not used). Padded slots are zeroed *after* decoration, then Linear(F → 64, no bias),
BatchNorm1d(eps 1e-3, momentum 0.01), ReLU and a max over the slots; padded slots take part in the BN statistics and
in the max (as zeros after the linear layer), exactly as the reference.
"""

from __future__ import annotations

import torch
from torch import nn

BN_EPS = 1e-3  # reference BatchNorm eps and momentum (Open3D-ML / mmdet3d SECOND settings)
BN_MOMENTUM = 0.01


class PillarFeatureNet(nn.Module):
    """(P, T, C) padded pillars → (P, out_channels) pillar features.

    in_channels: C raw point features (3: xyz, 4: xyzr). voxel_size: (vx, vy, vz) metres. point_cloud_range:
    (x_min, y_min, z_min, x_max, y_max, z_max) metres, sensor frame. out_channels: feature width (64).
    """

    def __init__(
        self,
        *,
        in_channels: int,
        out_channels: int,
        voxel_size: tuple[float, float, float],
        point_cloud_range: tuple[float, float, float, float, float, float],
    ) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.vx, self.vy = float(voxel_size[0]), float(voxel_size[1])
        # Pillar centre offsets: x_c = ix * vx + (vx / 2 + x_min).
        self.x_offset = self.vx / 2 + float(point_cloud_range[0])
        self.y_offset = self.vy / 2 + float(point_cloud_range[1])
        self.num_features = in_channels + 3 + 2
        self.linear = nn.Linear(self.num_features, out_channels, bias=False)
        self.norm = nn.BatchNorm1d(out_channels, eps=BN_EPS, momentum=BN_MOMENTUM)
        self.out_channels = out_channels

    def decorate(self, pillars: torch.Tensor, num_points: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """(P, T, C) pillars, (P,) counts, (P, 3) [b, iy, ix] → (P, T, C + 5) decorated features, padded slots 0."""
        p, t, c = pillars.shape
        if c != self.in_channels:
            raise ValueError(f"PillarFeatureNet: expected {self.in_channels} point features, got {c}")
        n = num_points.to(pillars.dtype).clamp(min=1).view(p, 1, 1)
        # Padded slots are zero, so the plain sum over slots is the sum over real points.
        mean = pillars[:, :, :3].sum(dim=1, keepdim=True) / n
        f_cluster = pillars[:, :, :3] - mean
        xc = coords[:, 2].to(pillars.dtype) * self.vx + self.x_offset
        yc = coords[:, 1].to(pillars.dtype) * self.vy + self.y_offset
        f_center = torch.stack([pillars[:, :, 0] - xc[:, None], pillars[:, :, 1] - yc[:, None]], dim=2)
        feats = torch.cat([pillars, f_cluster, f_center], dim=2)
        mask = torch.arange(t, device=pillars.device)[None, :] < num_points[:, None]
        return feats * mask.unsqueeze(2).to(feats.dtype)

    def forward(self, pillars: torch.Tensor, num_points: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """pillars (P, T, C), num_points (P,), coords (P, 3) int64 [b, iy, ix] → features (P, out_channels)."""
        if pillars.shape[0] == 0:
            return pillars.new_zeros((0, self.out_channels))
        p, t, _ = pillars.shape
        x = self.linear(self.decorate(pillars, num_points, coords))  # (P, T, 64)
        # BatchNorm1d over channels with P*T samples: the same statistics as the reference's BN on the permuted
        # (P, 64, T) tensor, computed on a contiguous (P*T, 64) view (the permuted layout is a slow path on CPU).
        x = torch.relu(self.norm(x.reshape(p * t, -1))).view(p, t, -1)
        return x.max(dim=1).values
