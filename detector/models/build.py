"""The one builder: :class:`ModelConfig` → :class:`PointPillars`, following the fixed stage order.

Each stage's output width is passed to the next (pillar net 64 → backbone → neck sum(neck_channels) → head), like
OpenPCDet's ``module_topology``/``num_bev_features``, without a registry: the backbone variant and the head variant
are ``Literal`` config fields, each chosen by one ``match`` here.
"""

from __future__ import annotations

from detector.config import ModelConfig, check_model_config
from detector.models.anchors import generate_anchors
from detector.models.backbone import SecondBackbone
from detector.models.head import AnchorHead, SparseExactHead
from detector.models.neck import SecondFPN
from detector.models.pillar_net import PillarFeatureNet
from detector.models.pointpillars import PointPillars
from detector.models.sparse_backbone import SparseBackboneNeck


def head_stride(cfg: ModelConfig) -> int:
    """Pseudo-image cells per head-map cell: ``layer_strides[0] / upsample_strides[0]``."""
    return cfg.layer_strides[0] // cfg.upsample_strides[0]


def head_feature_size(cfg: ModelConfig) -> tuple[int, int]:
    """(H, W) of the neck/head map: the pseudo-image at :func:`head_stride`."""
    s = head_stride(cfg)
    return cfg.output_shape[0] // s, cfg.output_shape[1] // s


def anchor_cells(cfg: ModelConfig) -> tuple[float, float, float, float] | None:
    """``(x_origin, y_origin, cell_x, cell_y)`` (m, sensor frame) of the head map's cells for ``cells`` anchor
    placement, None for ``range`` (:mod:`detector.models.anchors`)."""
    if cfg.anchor_centres == "range":
        return None
    s = head_stride(cfg)
    return (cfg.point_cloud_range[0], cfg.point_cloud_range[1], cfg.voxel_size[0] * s, cfg.voxel_size[1] * s)


def build_model(cfg: ModelConfig) -> PointPillars:
    """Build the dense or sparse PointPillars described by ``cfg`` (validated first; bad values → InputError).

    The sparse variants use ``detector.models.sparse_backbone.SparseBackboneNeck`` (backbone and neck in one module):
    ``sparse`` (3 sparse blocks), ``sparse1_dense23`` / ``sparse12_dense3`` (1 / 2 sparse blocks, then the dense
    SECOND blocks and ConvTranspose2d levels), ``sparse_wide`` (first SubM of every block 9x9, the paper's text) and
    ``sparse_wide_down`` (9x9 stride-2 down-conv of every block, the released code's Sparse+WideConv).
    """
    check_model_config(cfg)
    pfn = PillarFeatureNet(
        in_channels=cfg.in_channels,
        out_channels=cfg.pfn_channels,
        voxel_size=cfg.voxel_size,
        point_cloud_range=cfg.point_cloud_range,
    )
    neck = None
    match cfg.backbone:
        case "dense":
            backbone = SecondBackbone(
                in_channels=cfg.pfn_channels,
                layer_channels=cfg.layer_channels,
                layer_nums=cfg.layer_nums,
                layer_strides=cfg.layer_strides,
            )
            neck = SecondFPN(
                in_channels=cfg.layer_channels, out_channels=cfg.neck_channels, upsample_strides=cfg.upsample_strides
            )
        case "sparse":
            backbone = _sparse_backbone(cfg, sparse_blocks=3, first_subm_kernel=3)
        case "sparse1_dense23":
            backbone = _sparse_backbone(cfg, sparse_blocks=1, first_subm_kernel=3)
        case "sparse12_dense3":
            backbone = _sparse_backbone(cfg, sparse_blocks=2, first_subm_kernel=3)
        case "sparse_wide":
            backbone = _sparse_backbone(cfg, sparse_blocks=3, first_subm_kernel=9)
        case "sparse_wide_down":
            backbone = _sparse_backbone(cfg, sparse_blocks=3, first_subm_kernel=3, down_kernel=9)
    num_anchors = len(cfg.anchor_sizes) * len(cfg.anchor_rotations)
    head_kwargs = dict(in_channels=sum(cfg.neck_channels), num_anchors=num_anchors, num_classes=cfg.num_classes)
    match cfg.head:
        case "dense":
            head = AnchorHead(**head_kwargs)
        case "sparse_exact":
            head = SparseExactHead(**head_kwargs)
    anchors = generate_anchors(
        feature_size=head_feature_size(cfg),
        anchor_range=cfg.anchor_range,
        sizes=cfg.anchor_sizes,
        rotations=cfg.anchor_rotations,
        cells=anchor_cells(cfg),
    )
    return PointPillars(
        point_cloud_range=cfg.point_cloud_range,
        voxel_size=cfg.voxel_size,
        output_shape=cfg.output_shape,
        max_points_per_pillar=cfg.max_points_per_pillar,
        max_pillars_train=cfg.max_pillars_train,
        max_pillars_test=cfg.max_pillars_test,
        pillar_encoder=pfn,
        backbone=backbone,
        neck=neck,
        sparse_input=cfg.backbone != "dense",
        anchor_head=head,
        anchors=anchors,
        num_classes=cfg.num_classes,
        pos_iou_thr=cfg.pos_iou_thr,
        neg_iou_thr=cfg.neg_iou_thr,
        dir_offset=cfg.dir_offset,
        dir_limit_offset=cfg.dir_limit_offset,
        loss_params=dict(
            focal_alpha=cfg.focal_alpha,
            focal_gamma=cfg.focal_gamma,
            cls_weight=cfg.cls_weight,
            smooth_l1_beta=cfg.smooth_l1_beta,
            reg_weight=cfg.reg_weight,
            dir_weight=cfg.dir_weight,
        ),
        nms_pre=cfg.nms_pre,
        score_thr=cfg.score_thr,
        nms_iou=cfg.nms_iou,
    )


def _sparse_backbone(
    cfg: ModelConfig, *, sparse_blocks: int, first_subm_kernel: int, down_kernel: int = 2
) -> SparseBackboneNeck:
    """The sparse backbone + neck module (one module: its neck reads the sparse blocks' active sites)."""
    return SparseBackboneNeck(
        in_channels=cfg.pfn_channels,
        layer_channels=cfg.layer_channels,
        layer_nums=cfg.layer_nums,
        out_channels=cfg.neck_channels,
        upsample_strides=cfg.upsample_strides,
        sparse_blocks=sparse_blocks,
        first_subm_kernel=first_subm_kernel,
        down_kernel=down_kernel,
        downsample=cfg.downsample,
    )
