"""The PointPillars assembly: stage methods that are exactly the paper's timing components.

| stage (paper timer) | method | output |
|---|---|---|
| Feature Extract | :meth:`PointPillars.voxelize` + :meth:`PointPillars.pillar_net` | features (P, 64), coords (P, 3) |
| Feature Net | :meth:`PointPillars.feature_net` | dense canvas (B, 64, ny, nx) or ``detector.sparse.SparseTensor`` |
| Backbone | :meth:`PointPillars.backbone_neck` | (B, 384, ny/2, nx/2) map and active mask (B, ny/2, nx/2) or None |
| Head | :meth:`PointPillars.head` | :class:`HeadOutput` cls / reg / dir, (B, H, W, C) |
| BBox Extract | :meth:`PointPillars.postprocess` | per sample :class:`Detections` (sensor frame) |

``forward(points_list)`` chains the first four stages and returns the head maps (training); :meth:`loss` assigns
targets and computes the losses; :meth:`predict` runs all five stages. Build instances with
:func:`detector.models.build.build_model`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Literal

import torch
from torch import nn

from detector.models.assign import Targets, assign_targets
from detector.models.head import AnchorHead, HeadOutput
from detector.models.losses import Losses, compute_loss
from detector.models.pillar_net import PillarFeatureNet
from detector.models.postprocess import Detections, postprocess
from detector.models.scatter import canvas_channels_last, scatter_to_canvas
from detector.models.voxelizer import Voxels, voxelize
from detector.sparse.workspace import Workspace, inference_workspace


def native_bf16() -> bool:
    """Whether this CPU computes bfloat16 natively (AVX512-BF16 or AMX), the condition for ``precision="bf16"`` to
    pay off (as training's ``auto`` precision decides from /proc/cpuinfo's flags)."""
    return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())


class PointPillars(nn.Module):
    """Dense or sparse PointPillars. Sub-modules: ``pillar_encoder``, ``backbone``, ``neck`` (None for the sparse
    variants, whose backbone includes the neck), ``anchor_head``; ``anchors`` is a non-persistent buffer (H*W*A, 7).

    Geometry kwargs as :class:`detector.config.ModelConfig` (metres, sensor frame). ``sparse_input``: the
    backbone consumes a ``SparseTensor`` (no scatter) and returns ``(map, active)``; otherwise it consumes the dense
    canvas and returns a list of maps for ``neck``.

    ``workspace``: ``None`` (the default: every stage allocates its outputs) or a
    :class:`detector.sparse.workspace.Workspace`, set by a caller that streams frames (``detector bench``). Then
    inference (autograd off) reuses its buffers from frame to frame: the canvases, the sparse layers' gathers, GEMM
    outputs and site lookups, the dense neck and the head write into memory kept from the last frame, so a steady
    stream allocates nothing big and pays no page faults for it. The tensors the stages return then live in that
    memory: each is valid until the same stage runs again (clone what you keep). Training ignores it.

    ``precision``: ``"fp32"`` (default) or ``"bf16"``: inference runs Feature Net, Backbone and Head under bfloat16
    autocast, the pseudo-image (dense canvas or sparse features) in bf16 from the start; every GEMM / convolution then
    multiplies bf16 and accumulates in fp32 (oneDNN and MKL do), the sparse convs in their one-GEMM form (the
    rulebook would add its offsets' products in bf16). Fast where the CPU computes bf16 natively (AVX512-BF16 / AMX;
    :func:`native_bf16`). Feature Extract and BBox Extract stay fp32. Training ignores it (``train.precision``).
    """

    def __init__(
        self,
        *,
        point_cloud_range: tuple[float, float, float, float, float, float],
        voxel_size: tuple[float, float, float],
        output_shape: tuple[int, int],
        max_points_per_pillar: int,
        max_pillars_train: int,
        max_pillars_test: int,
        pillar_encoder: PillarFeatureNet,
        backbone: nn.Module,
        neck: nn.Module | None,
        sparse_input: bool,
        anchor_head: AnchorHead,
        anchors: torch.Tensor,
        num_classes: int,
        pos_iou_thr: float,
        neg_iou_thr: float,
        dir_offset: float,
        dir_limit_offset: float,
        loss_params: dict[str, float],
        nms_pre: int,
        score_thr: float,
        nms_iou: float,
    ) -> None:
        super().__init__()
        self.point_cloud_range = tuple(float(v) for v in point_cloud_range)
        self.voxel_size = tuple(float(v) for v in voxel_size)
        self.output_shape = (int(output_shape[0]), int(output_shape[1]))
        self.max_points_per_pillar = max_points_per_pillar
        self.max_pillars_train, self.max_pillars_test = max_pillars_train, max_pillars_test
        self.pillar_encoder = pillar_encoder
        self.backbone = backbone
        self.neck = neck
        self.sparse_input = sparse_input
        self.anchor_head = anchor_head
        self.register_buffer("anchors", anchors, persistent=False)
        self.num_classes = num_classes
        self.pos_iou_thr, self.neg_iou_thr = pos_iou_thr, neg_iou_thr
        self.dir_offset, self.dir_limit_offset = dir_offset, dir_limit_offset
        self.loss_params = dict(loss_params)
        self.nms_pre, self.score_thr, self.nms_iou = nms_pre, score_thr, nms_iou
        self.workspace: Workspace | None = None
        self.precision: Literal["fp32", "bf16"] = "fp32"

    # --- Feature Extract ---------------------------------------------------------------------------------------
    def voxelize(self, points_list: Sequence[torch.Tensor]) -> Voxels:
        """B point clouds (N_i, C) (sensor frame, m) → :class:`Voxels`; pillar cap is the train or test one by mode."""
        cap = self.max_pillars_train if self.training else self.max_pillars_test
        return voxelize(
            points_list,
            point_cloud_range=self.point_cloud_range,
            voxel_size=self.voxel_size,
            output_shape=self.output_shape,
            max_points=self.max_points_per_pillar,
            max_pillars=cap,
        )

    def pillar_net(self, voxels: Voxels) -> tuple[torch.Tensor, torch.Tensor]:
        """:class:`Voxels` → (features (P, 64), coords (P, 3) int64 [b, iy, ix])."""
        return self.pillar_encoder(voxels.pillars, voxels.num_points, voxels.coords), voxels.coords

    # --- Feature Net --------------------------------------------------------------------------------------------
    def feature_net(self, features: torch.Tensor, coords: torch.Tensor, batch_size: int):
        """Dense: scatter into one (B, 64, ny, nx) canvas. Sparse: wrap as ``SparseTensor`` (no canvas is built)."""
        ws = inference_workspace(self.workspace)
        if self._bf16():
            features = features.to(torch.bfloat16)  # the canvas / sparse features in bf16 from the start
        if self.sparse_input:
            from detector.sparse import SparseTensor

            return SparseTensor(features, coords, self.output_shape, batch_size, workspace=ws, origin=self)
        # channels-last for inference and bf16 training, NCHW for fp32 training (the faster layout of each; see
        # detector.models.scatter): at inference the dense and the sparse model hand the head the same layout
        cl = canvas_channels_last(features.device.type)
        return scatter_to_canvas(features, coords, batch_size, self.output_shape, channels_last=cl, workspace=ws,
                                 owner=self)

    # --- Backbone -------------------------------------------------------------------------------------------------
    def backbone_neck(self, x) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Canvas or SparseTensor → ((B, 384, ny/2, nx/2) map, active (B, ny/2, nx/2) bool or None)."""
        with self._autocast():
            if self.sparse_input:
                return self.backbone(x)
            return self.neck(self.backbone(x), workspace=inference_workspace(self.workspace)), None

    # --- Head -----------------------------------------------------------------------------------------------------
    def head(self, x: torch.Tensor, active: torch.Tensor | None = None) -> HeadOutput:
        """(B, 384, H, W) map (+ active mask) → :class:`HeadOutput` (B, H, W, C) maps."""
        with self._autocast():
            return self.anchor_head(x, active, workspace=inference_workspace(self.workspace))

    def _bf16(self) -> bool:
        """bf16 inference is on (``precision == "bf16"`` and autograd off)."""
        return self.precision == "bf16" and not torch.is_grad_enabled()

    def _autocast(self) -> contextlib.AbstractContextManager:
        """bfloat16 autocast on the model's device for bf16 inference, else nothing."""
        if not self._bf16():
            return contextlib.nullcontext()
        return torch.autocast(self.anchors.device.type, dtype=torch.bfloat16)

    # --- BBox Extract ---------------------------------------------------------------------------------------------
    def postprocess(self, cls: torch.Tensor, reg: torch.Tensor, dir: torch.Tensor) -> list[Detections]:
        """Head maps → per-sample :class:`Detections` (sensor frame boxes, scores, labels)."""
        return postprocess(
            cls,
            reg,
            dir,
            self.anchors,
            num_classes=self.num_classes,
            nms_pre=self.nms_pre,
            score_thr=self.score_thr,
            nms_iou=self.nms_iou,
            dir_offset=self.dir_offset,
            dir_limit_offset=self.dir_limit_offset,
        )

    # --- whole passes -----------------------------------------------------------------------------------------
    def forward(self, points_list: Sequence[torch.Tensor]) -> HeadOutput:
        """B point clouds (N_i, C) (sensor frame, m) → head maps (B, H, W, C) (the stages chained; with autograd on,
        the all-sparse model's head runs on the neck's active rows, the same maps without the canvas)."""
        voxels = self.voxelize(points_list)
        features, coords = self.pillar_net(voxels)
        x = self.feature_net(features, coords, voxels.batch_size)
        if torch.is_grad_enabled() and self.sparse_input and getattr(self.backbone, "all_sparse", False):
            # Training the all-sparse model: the head on the neck's active rows (AnchorHead.on_sites), the same maps
            # and gradients as the head on the scattered 384-channel canvas, whose zero fill, 1x1 convs and their
            # backward over every cell were most of the sparse step beyond the pillar net (docs/sparse.md).
            return self.anchor_head.on_sites(self.backbone.neck_rows(x))
        x, active = self.backbone_neck(x)
        return self.head(x, active)

    @torch.no_grad()
    def predict(self, points_list: Sequence[torch.Tensor]) -> list[Detections]:
        """All five stages (call ``eval()`` first for the test pillar cap and BN running stats)."""
        return self.postprocess(*self.forward(points_list))

    def targets(self, gt_boxes_list: Sequence[torch.Tensor], gt_labels_list: Sequence[torch.Tensor]) -> Targets:
        """GT boxes (M_b, 7) sensor frame and labels (M_b,) int64 per sample → anchor :class:`Targets`."""
        return assign_targets(
            self.anchors,
            gt_boxes_list,
            gt_labels_list,
            pos_iou_thr=self.pos_iou_thr,
            neg_iou_thr=self.neg_iou_thr,
            dir_offset=self.dir_offset,
        )

    def loss(
        self, preds: HeadOutput, gt_boxes_list: Sequence[torch.Tensor], gt_labels_list: Sequence[torch.Tensor]
    ) -> Losses:
        """Head maps + per-sample GT → :class:`Losses` (see :mod:`detector.models.losses`)."""
        return compute_loss(
            preds, self.targets(gt_boxes_list, gt_labels_list), num_classes=self.num_classes, **self.loss_params
        )
