"""Pillar Feature Net: decorate each point, one PointNet layer, max over the pillar (second half of "Feature Extract").

Decorations per point (reference / Open3D-ML ``PillarFeatureNet``): the raw features (x, y, z[, r]), then
``x - x_mean, y - y_mean, z - z_mean`` (mean over the pillar's real points), then ``x - x_c, y - y_c`` with the pillar
centre ``x_c = ix * vx + vx / 2 + x_min`` (same for y). That is 8 features for xyz input and 9 for xyzr (OpenPCDet's
extra ``z - z_c`` is not used). Padded slots are zeroed *after* decoration, then Linear(F → 64, no bias),
BatchNorm1d(eps 1e-3, momentum 0.01), ReLU and a max over the slots; padded slots take part in the BN statistics and
in the max (as zeros after the linear layer), exactly as the reference.

Three forms of the forward pass:

* :meth:`PillarFeatureNet.forward_torch`: the layers above in torch on the padded ``(P, T, F)`` block, the reference;
  eval-mode calls outside the fused path (GPUs, autocast, autograd on) and distributed training use it.
* :meth:`PillarFeatureNet.forward_compact` (what :meth:`~PillarFeatureNet.forward` runs in training): the same layers
  on the real points only (padded slots enter BatchNorm's statistics and the max in closed form), differentiable;
  equal to ``forward_torch`` in float64 to 1e-9, ~4x faster at fp32 on a CPU training batch.
* :meth:`PillarFeatureNet.forward_fused` (what :meth:`~PillarFeatureNet.forward` runs for fp32 inference on the CPU:
  eval mode, autograd off): one compiled pass per pillar (``_fused_eval``, numba) over its *real* points only. In eval
  mode BatchNorm is the per-channel affine map ``y * alpha + beta`` of the running statistics, so every padded slot
  (zero after decoration, zero after the bias-free linear layer) comes out as the same ``relu(beta)``; the max over
  the slots is then the max of the real points' values and, if the pillar has a padded slot, ``relu(beta)``. That
  skips the ~85 % of the block that is padding and never materialises the ``(P, T, 64)`` activations. It computes
  in the order torch's CPU kernels use (decorations as in :meth:`~PillarFeatureNet.decorate`, the pillar mean as
  ``torch.sum``'s four interleaved partial sums, the linear layer and BN with fused multiply-adds as MKL's GEMM and
  the BN kernel do), so on the CPUs measured its output equals ``forward_torch`` bit for bit; where a library
  accumulates differently they differ by fp32 rounding only (tested to 1e-5; ``tools/bench_feature_extract.py``
  prints the bitwise fraction).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn
from torch.autograd.function import once_differentiable

from mpchair.core.jit import njit_cached

BN_EPS = 1e-3  # reference BatchNorm eps and momentum (Open3D-ML / mmdet3d SECOND settings)
BN_MOMENTUM = 0.01


@njit_cached(contract=True)
def _fused_eval(
    pillars: np.ndarray,
    num_points: np.ndarray,
    centres: np.ndarray,
    weight_t: np.ndarray,
    bn_weight: np.ndarray,
    bn_bias: np.ndarray,
    running_mean: np.ndarray,
    running_var: np.ndarray,
    eps: np.float32,
) -> np.ndarray:
    """Eval-mode pillar net, float32: pillars (P, T, C) with C 3 or 4, num_points (P,), centres (P, 2) [x_c, y_c]
    (m), weight_t (C + 5, O) = linear weight transposed, BN parameters and running stats (O,) → features (P, O)."""
    n_pillars, t, c = pillars.shape
    n_out = weight_t.shape[1]
    # BN in eval mode as torch's CPU kernel evaluates it: alpha = weight / sqrt(var + eps), beta = bias - mean * alpha
    alpha = np.empty(n_out, dtype=np.float32)
    beta = np.empty(n_out, dtype=np.float32)
    pad = np.empty(n_out, dtype=np.float32)
    for o in range(n_out):
        alpha[o] = (np.float32(1) / np.sqrt(running_var[o] + eps)) * bn_weight[o]
        beta[o] = bn_bias[o] - running_mean[o] * alpha[o]
        pad[o] = max(beta[o], np.float32(0))  # a padded slot: relu(0 * alpha + beta)
    # rows of the transposed weight, in the decorated features' order: x, y, z, [r,] x - x_m, y - y_m, z - z_m,
    # x - x_c, y - y_c. Without reflectance its row is zeros and its value 0: adding 0 * 0 leaves a sum unchanged
    w_x, w_y, w_z = weight_t[0], weight_t[1], weight_t[2]
    w_r = weight_t[3] if c == 4 else np.zeros(n_out, dtype=np.float32)
    w_xm, w_ym, w_zm, w_xc, w_yc = weight_t[c], weight_t[c + 1], weight_t[c + 2], weight_t[c + 3], weight_t[c + 4]
    out = np.empty((n_pillars, n_out), dtype=np.float32)
    part = np.empty((4, 3), dtype=np.float32)
    t4 = t - t % 4
    for p in range(n_pillars):
        n = num_points[p]
        # pillar mean of x, y, z: torch.sum over the T slots keeps four partial sums (slot k into k % 4, slots past
        # the last multiple of 4 into the first), added in order at the end; padded slots add zeros, so skip them
        part[:] = 0
        for k in range(min(n, t4)):
            for j in range(3):
                part[k % 4, j] += pillars[p, k, j]
        for k in range(t4, n):
            for j in range(3):
                part[0, j] += pillars[p, k, j]
        count = np.float32(max(n, 1))
        x_m = (((part[0, 0] + part[1, 0]) + part[2, 0]) + part[3, 0]) / count
        y_m = (((part[0, 1] + part[1, 1]) + part[2, 1]) + part[3, 1]) / count
        z_m = (((part[0, 2] + part[1, 2]) + part[2, 2]) + part[3, 2]) / count
        best = out[p]
        # ReLU outputs are >= 0, so starting the max at 0 (a full pillar) or at relu(beta) (one with a padded slot)
        # gives the reference's max over all T slots
        for o in range(n_out):
            best[o] = pad[o] if n < t else np.float32(0)
        for k in range(n):
            x, y, z = pillars[p, k, 0], pillars[p, k, 1], pillars[p, k, 2]
            r = pillars[p, k, 3] if c == 4 else np.float32(0)
            dxm, dym, dzm = x - x_m, y - y_m, z - z_m
            dxc, dyc = x - centres[p, 0], y - centres[p, 1]
            for o in range(n_out):
                # the GEMM's sum: one multiply-add per feature in order. "0 +" starts it from a sum (MKL: 0 + x*w),
                # so that the compiler has exactly one way to fuse each step (two products would give it a choice)
                acc = np.float32(0) + x * w_x[o]
                acc = acc + y * w_y[o]
                acc = acc + z * w_z[o]
                acc = acc + r * w_r[o]
                acc = acc + dxm * w_xm[o]
                acc = acc + dym * w_ym[o]
                acc = acc + dzm * w_zm[o]
                acc = acc + dxc * w_xc[o]
                acc = acc + dyc * w_yc[o]
                v = acc * alpha[o] + beta[o]
                b = best[o]
                best[o] = v if (v > b or v != v) else b  # a NaN wins, as in torch's max
    return out


@njit_cached
def _segment_max(y: np.ndarray, offsets: np.ndarray, pad: np.ndarray, has_pad: np.ndarray) -> tuple[np.ndarray,
                                                                                                      np.ndarray]:
    """Per pillar p and channel c, the max of rows ``offsets[p]:offsets[p + 1]`` of ``y`` (N, C) (the pillar's real
    points, ReLU outputs >= 0) and, where ``has_pad[p]``, of ``pad[c]`` (its padded slots' value) → (out (P, C), winner
    (P, C): the row that gave the max, -1 for the padding, -2 for none (an empty pillar: 0)). The first of tied rows
    wins and a real point beats a tied padded slot: the slot order of the reference's ``max(dim=1)``; a NaN wins."""
    n_pillars, n_ch = offsets.shape[0] - 1, y.shape[1]
    out = np.zeros((n_pillars, n_ch), dtype=y.dtype)
    winner = np.full((n_pillars, n_ch), -2, dtype=np.int64)
    for p in range(n_pillars):
        best, who = out[p], winner[p]
        for n in range(offsets[p], offsets[p + 1]):
            for c in range(n_ch):
                v = y[n, c]
                if who[c] == -2 or v > best[c] or (v != v and best[c] == best[c]):
                    best[c] = v
                    who[c] = n
        if has_pad[p]:
            for c in range(n_ch):
                if who[c] == -2 or pad[c] > best[c]:
                    best[c] = pad[c]
                    who[c] = -1
    return out, winner


@njit_cached
def _segment_max_backward(grad: np.ndarray, winner: np.ndarray, n_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_segment_max`'s gradient: grad (P, C) → (rows (N, C): each pillar-channel's gradient on its winning row,
    pad (C,): the sum over the pillars whose padding won)."""
    n_pillars, n_ch = grad.shape
    g_rows = np.zeros((n_rows, n_ch), dtype=grad.dtype)
    g_pad = np.zeros(n_ch, dtype=grad.dtype)
    for p in range(n_pillars):
        for c in range(n_ch):
            w = winner[p, c]
            if w >= 0:
                g_rows[w, c] = grad[p, c]
            elif w == -1:
                g_pad[c] += grad[p, c]
    return g_rows, g_pad


class SegmentMax(torch.autograd.Function):
    """``max(rows of each pillar, pad where the pillar has a padded slot)`` per channel (:func:`_segment_max`), CPU,
    with a backward that hands each max's gradient to its one winning row (or to ``pad``). Torch's
    ``scatter_reduce(amax)`` + ``maximum`` did the same with tie-splitting backwards over eq masks: 9.3 ms of a CPU
    training step (forward + backward, torch.profiler on ``mpchair_sparse_cpu.yaml`` batches, 2 threads, 2026-12-06),
    2.4 ms here."""

    @staticmethod
    def forward(ctx: Any, y: torch.Tensor, pad: torch.Tensor, offsets: torch.Tensor,
                has_pad: torch.Tensor) -> torch.Tensor:
        out, winner = _segment_max(y.detach().contiguous().numpy(), offsets.numpy(), pad.detach().contiguous().numpy(),
                                   has_pad.numpy())
        ctx.winner, ctx.rows = winner, y.shape[0]
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, None, None]:
        g_rows, g_pad = _segment_max_backward(grad.contiguous().numpy(), ctx.winner, ctx.rows)
        return torch.from_numpy(g_rows), torch.from_numpy(g_pad), None, None


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

    def centres(self, coords: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """(P, 3) [b, iy, ix] → pillar centres ``(x_c (P,), y_c (P,))`` (sensor frame, m) in ``dtype``."""
        xc = coords[:, 2].to(dtype) * self.vx + self.x_offset
        yc = coords[:, 1].to(dtype) * self.vy + self.y_offset
        return xc, yc

    def decorate(self, pillars: torch.Tensor, num_points: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """(P, T, C) pillars, (P,) counts, (P, 3) [b, iy, ix] → (P, T, C + 5) decorated features, padded slots 0."""
        p, t, c = pillars.shape
        if c != self.in_channels:
            raise ValueError(f"PillarFeatureNet: expected {self.in_channels} point features, got {c}")
        n = num_points.to(pillars.dtype).clamp(min=1).view(p, 1, 1)
        # Padded slots are zero, so the plain sum over slots is the sum over real points.
        mean = pillars[:, :, :3].sum(dim=1, keepdim=True) / n
        f_cluster = pillars[:, :, :3] - mean
        xc, yc = self.centres(coords, pillars.dtype)
        f_center = torch.stack([pillars[:, :, 0] - xc[:, None], pillars[:, :, 1] - yc[:, None]], dim=2)
        feats = torch.cat([pillars, f_cluster, f_center], dim=2)
        mask = torch.arange(t, device=pillars.device)[None, :] < num_points[:, None]
        return feats * mask.unsqueeze(2).to(feats.dtype)

    def fused_applies(self, pillars: torch.Tensor) -> bool:
        """Whether :meth:`forward` takes the compiled eval path: eval mode, autograd and autocast off, float32 on the
        CPU (anything else, training included, runs :meth:`forward_torch`)."""
        return (
            not self.training
            and not torch.is_grad_enabled()
            and pillars.device.type == "cpu"
            and not torch.is_autocast_enabled("cpu")
            and pillars.dtype == self.linear.weight.dtype == torch.float32
            and self.norm.track_running_stats  # eval BN normalises with the running statistics
            and self.in_channels in (3, 4)
        )

    def compact_applies(self) -> bool:
        """Whether :meth:`forward` takes the real-points training path (:meth:`forward_compact`): training mode with
        batch statistics of the plain ``BatchNorm1d`` (a BN converted for distributed training, whose statistics
        span the ranks, runs :meth:`forward_torch`)."""
        bn = self.norm
        return self.training and type(bn) is nn.BatchNorm1d and bn.affine and bn.momentum is not None

    def forward(self, pillars: torch.Tensor, num_points: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """pillars (P, T, C), num_points (P,), coords (P, 3) int64 [b, iy, ix] → features (P, out_channels)."""
        if pillars.shape[0] == 0:
            return pillars.new_zeros((0, self.out_channels))
        if self.fused_applies(pillars):
            return self.forward_fused(pillars, num_points, coords)
        if self.compact_applies():
            return self.forward_compact(pillars, num_points, coords)
        return self.forward_torch(pillars, num_points, coords)

    def forward_compact(self, pillars: torch.Tensor, num_points: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """The training forward on the real points only, differentiable; the same values and gradients as
        :meth:`forward_torch` in training mode (up to float rounding and the split of a gradient between exactly
        tied maxima), and the same running-statistics update.

        Why it is exact: a padded slot is zero after decoration, so zero after the bias-free linear layer. BatchNorm's
        batch statistics over all P*T slots are then those of the real points' rows plus (P*T - N) zeros, every
        padded slot normalises to the same ``relu(-mean * a + b)`` per channel, and the max over a pillar's slots is
        the max over its real points and, if it has a padded slot, that value. The (P, T, 64) activations the
        reference builds (~85 % padding on these scans) are never made: on the CPU configs' training batches they
        were most of the pillar net's time, and the pillar net most of a sparse training step (docs/sparse.md).
        """
        p, t, c = pillars.shape
        if c != self.in_channels:
            raise ValueError(f"PillarFeatureNet: expected {self.in_channels} point features, got {c}")
        bn = self.norm
        mask = torch.arange(t, device=pillars.device)[None, :] < num_points[:, None]  # (P, T) real slots
        pid, slot = mask.nonzero(as_tuple=True)  # pillar-major: each pillar's points in slot order
        pts = pillars[pid, slot]  # (N, C)
        n = num_points.to(pillars.dtype).clamp(min=1)
        mean = pillars[:, :, :3].sum(dim=1) / n[:, None]  # padded slots are zero: the sum over real points
        xc, yc = self.centres(coords, pillars.dtype)
        centre = torch.stack([xc, yc], dim=1)
        feats = torch.cat([pts, pts[:, :3] - mean[pid], pts[:, :2] - centre[pid]], dim=1)  # decorate's order
        x = self.linear(feats)  # (N, 64)
        low = x.dtype  # the reference's output dtype (bf16 under autocast: its BN keeps the linear layer's dtype)
        if low in (torch.bfloat16, torch.float16):
            x = x.float()  # fp32 statistics
        total = p * t
        batch_mean = x.sum(dim=0) / total
        # biased variance over all P*T slots, two-pass: the real rows' squared deviations plus the zeros'
        var = ((x - batch_mean).square().sum(dim=0) + (total - x.shape[0]) * batch_mean.square()) / total
        scale = torch.rsqrt(var + bn.eps) * bn.weight
        shift = bn.bias - batch_mean * scale
        y = torch.relu(x * scale + shift)
        has_pad = num_points < t
        if y.device.type == "cpu":  # one compiled pass, each max's gradient to its winner (SegmentMax)
            counts = num_points.clamp(max=t)
            offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
            out = SegmentMax.apply(y, torch.relu(shift), offsets, has_pad)
        else:
            out = y.new_zeros((p, y.shape[1]))  # ReLU outputs are >= 0: a max starting at 0 is the max over the rows
            out = out.scatter_reduce(0, pid[:, None].expand_as(y), y, reduce="amax", include_self=True)
            out = torch.where(has_pad[:, None], torch.maximum(out, torch.relu(shift)[None, :]), out)
        if bn.track_running_stats:
            with torch.no_grad():
                bn.num_batches_tracked.add_(1)
                m = bn.momentum
                bn.running_mean.mul_(1 - m).add_(batch_mean.detach() * m)
                bn.running_var.mul_(1 - m).add_(var.detach() * (total / max(total - 1, 1)) * m)
        return out.to(low)

    @torch.no_grad()
    def forward_fused(self, pillars: torch.Tensor, num_points: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """The eval-mode forward as one compiled pass over the real points (module docstring); float32, CPU, no
        autograd. Same arguments and result as :meth:`forward_torch` in eval mode."""
        if pillars.shape[2] != self.in_channels:
            raise ValueError(f"PillarFeatureNet: expected {self.in_channels} point features, got {pillars.shape[2]}")
        xc, yc = self.centres(coords, torch.float32)
        bn = self.norm
        out = _fused_eval(
            pillars.detach().contiguous().numpy(),
            num_points.contiguous().numpy(),
            torch.stack([xc, yc], dim=1).numpy(),
            self.linear.weight.detach().t().contiguous().numpy(),
            bn.weight.detach().numpy(),
            bn.bias.detach().numpy(),
            bn.running_mean.numpy(),
            bn.running_var.numpy(),
            np.float32(bn.eps),
        )
        return torch.from_numpy(out)

    def forward_torch(self, pillars: torch.Tensor, num_points: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """The layers in torch on the padded block (P, T, F): any mode, device and dtype, differentiable."""
        if pillars.shape[0] == 0:
            return pillars.new_zeros((0, self.out_channels))
        p, t, _ = pillars.shape
        x = self.linear(self.decorate(pillars, num_points, coords))  # (P, T, 64)
        # BatchNorm1d over channels with P*T samples: the same statistics as the reference's BN on the permuted
        # (P, 64, T) tensor, computed on a contiguous (P*T, 64) view (the permuted layout is a slow path on CPU).
        x = torch.relu(self.norm(x.reshape(p * t, -1))).view(p, t, -1)
        return x.max(dim=1).values
