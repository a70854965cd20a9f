"""Open3D-ML's own PointPillars as a timing peer (``detector bench --peer open3d-ml``).

The peer is ``open3d._ml3d.torch.models.point_pillars.PointPillars`` (the model the paper's released code forked),
built with the architecture and grid of one of our dense configs and given **our dense model's weights** (random or
trained, whatever that model has), so both networks compute the same maps and pass the same number of boxes to NMS.
:func:`peer_state_dict` maps our parameter names onto Open3D-ML's and ``load_state_dict(strict=True)`` checks every
layer's shape: the two networks have the same layers and channels, or the peer is refused.

What is equal: point cloud range, pillar size, 32 points per pillar, 40,000 test pillars, the 8-feature PFN (64
channels), the canvas ``output_shape``, SECOND 64/128/256 x 3/5/5, FPN 128 x 3 at strides 1/2/4, the 384-channel
head with A = sizes x rotations anchors per cell (the same anchor count), ``nms_pre`` 100, score threshold, rotated
BEV NMS at IoU 0.01 (Open3D-ML hard-codes 0.01; the config's ``nms_iou`` must be 0.01). What differs, unavoidably:
Open3D-ML's code itself (its compiled voxelize / NMS ops, NCHW layout throughout, three head convs, anchors generated
per frame), its direction-limit offset 1 (ours 0: the same work), which points a pillar over 32 points keeps, and the
pillar of a point exactly on a pillar boundary (its voxelize computes in float32, ours in float64). The
anchor sizes are passed as ours, ``[l, w, h]``: Open3D-ML reads a size as the (x, y, z) extents at rotation 0, which
is what l, w, h are in our convention, so every anchor is the same rectangle as ours (for the chair this is the
reference config's own list; for the car the reference lists ``[w, l, h]``, the same set over the two rotations).

Stages timed as the paper's components, with Open3D-ML's own calls (as the released code stamps them, plus an
explicit ``batch_size`` read as it does): To Device ``torch.from_numpy``; Feature Extract ``voxelize`` +
``voxel_encoder``; Feature Net ``middle_encoder`` (its scatter); Backbone ``backbone`` + ``neck``; Head ``bbox_head``;
BBox Extract ``bbox_head.get_bboxes`` (top-k, decode, NMS, direction fix; without the conversion to ``BEVBox3D``
objects, which our post-processing has no counterpart of).

Open3D-ML's ``open3d._ml3d.torch`` package imports its training pipelines on import, and they import
``tensorboard``, which this project does not install. The model needs none of that: :func:`open3d_ml_pointpillars`
imports the model module with those two package initialisers skipped (the modules themselves are Open3D-ML's,
unchanged). The compiled ops (``open3d_torch_ops.so``) load with torch 2.13, the version open3d-cpu 0.20 was built
for; Open3D refuses any other torch minor version at import.
"""

from __future__ import annotations

import importlib
import os
import sys
import time
import types
import warnings

import numpy as np
import torch
from torch import nn

from detector.bench.timing import stamps_to_ms
from detector.config import ModelConfig
from detector.models import PointPillars
from mpchair.core.errors import InputError

#: The peer row's name, and the peers ``run_bench(peer=...)`` knows (this module imports Open3D-ML only when used).
PEER_NAME = "open3d-ml"
PEERS: tuple[str, ...] = (PEER_NAME,)
#: Open3D-ML's multiclass_nms hard-codes this BEV IoU threshold.
OPEN3D_ML_NMS_IOU = 0.01


def open3d_ml_pointpillars() -> type:
    """Open3D-ML's ``PointPillars`` class; :class:`InputError` (one line) if Open3D-ML cannot be imported.

    Imports ``open3d._ml3d.torch.models.point_pillars`` without running the ``open3d._ml3d.torch`` and
    ``open3d._ml3d.torch.models`` package initialisers (they import every pipeline and model, and the pipelines need
    tensorboard); the two placeholders are removed again afterwards, so a later ordinary import is unaffected.
    """
    try:
        import open3d._ml3d as ml3d
        import open3d.ml.torch  # noqa: F401  (loads open3d_torch_ops.so, checks the torch version)
    except Exception as e:  # ImportError, or Open3D's RuntimeError on a torch version mismatch
        raise InputError(f"--peer open3d-ml needs Open3D-ML (the open3d extra: pip install open3d-cpu): {e}") from e
    name = "open3d._ml3d.torch.models.point_pillars"
    module = sys.modules.get(name)
    if module is None:
        root = os.path.dirname(ml3d.__file__)
        placed = []
        for pkg in ("open3d._ml3d.torch", "open3d._ml3d.torch.models"):
            if pkg not in sys.modules:
                stub = types.ModuleType(pkg)
                stub.__path__ = [os.path.join(root, *pkg.split(".")[2:])]
                sys.modules[pkg] = stub
                placed.append(pkg)
        try:
            module = importlib.import_module(name)
        except Exception as e:
            raise InputError(f"--peer open3d-ml: cannot import Open3D-ML's PointPillars: {e}") from e
        finally:
            for pkg in placed:
                sys.modules.pop(pkg, None)
    return module.PointPillars


def peer_kwargs(m: ModelConfig) -> dict:
    """Open3D-ML ``PointPillars`` constructor arguments with the architecture and grid of our dense config ``m``."""
    if m.backbone != "dense":
        raise InputError(f"--peer open3d-ml mirrors a dense model; the first --config has backbone {m.backbone!r}")
    if m.nms_iou != OPEN3D_ML_NMS_IOU:
        raise InputError(f"--peer open3d-ml: Open3D-ML's NMS IoU is fixed at {OPEN3D_ML_NMS_IOU}, the config has "
                         f"nms_iou {m.nms_iou}")
    return dict(
        name="PointPillars",
        device="cpu",
        point_cloud_range=list(m.point_cloud_range),
        classes=[f"class{k}" for k in range(m.num_classes)],
        voxelize=dict(max_num_points=m.max_points_per_pillar, voxel_size=list(m.voxel_size),
                      max_voxels=[m.max_pillars_train, m.max_pillars_test]),
        voxel_encoder=dict(in_channels=m.in_channels, feat_channels=[m.pfn_channels], voxel_size=list(m.voxel_size)),
        scatter=dict(in_channels=m.pfn_channels, output_shape=list(m.output_shape)),
        backbone=dict(in_channels=m.pfn_channels, out_channels=list(m.layer_channels), layer_nums=list(m.layer_nums),
                      layer_strides=list(m.layer_strides)),
        neck=dict(in_channels=list(m.layer_channels), out_channels=list(m.neck_channels),
                  upsample_strides=list(m.upsample_strides), use_conv_for_no_stride=False),
        head=dict(in_channels=sum(m.neck_channels), feat_channels=sum(m.neck_channels), nms_pre=m.nms_pre,
                  score_thr=m.score_thr, dir_offset=m.dir_offset, ranges=[list(m.anchor_range)],
                  sizes=[list(s) for s in m.anchor_sizes], rotations=list(m.anchor_rotations),
                  iou_thr=[[m.neg_iou_thr, m.pos_iou_thr]] * m.num_classes),
        augment={},
    )


def peer_state_dict(ours: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Our dense model's ``state_dict`` under Open3D-ML's parameter names (the same tensors)."""
    renames = (("pillar_encoder.", "voxel_encoder.pfn_layers.0."), ("anchor_head.conv_dir.", "bbox_head.conv_dir_cls."),
               ("anchor_head.", "bbox_head."))
    out = {}
    for key, value in ours.items():
        for a, b in renames:
            if key.startswith(a):
                key = b + key[len(a):]
                break
        out[key] = value
    return out


def build_peer(cfg: ModelConfig, ours: PointPillars) -> nn.Module:
    """Open3D-ML's PointPillars with ``cfg``'s architecture and grid and the weights of our dense model ``ours``, in
    eval mode on the CPU. Raises :class:`InputError` if Open3D-ML is missing or the architectures differ."""
    cls = open3d_ml_pointpillars()
    with torch.random.fork_rng(devices=[]):  # its constructor draws random weights; ours replace them
        peer = cls(**peer_kwargs(cfg))
    try:
        peer.load_state_dict(peer_state_dict(ours.state_dict()), strict=True)
    except RuntimeError as e:
        raise InputError(f"--peer open3d-ml: Open3D-ML's PointPillars differs from {cfg.backbone!r}: {e}") from e
    return peer.eval()


@torch.no_grad()
def time_peer_frame(peer: nn.Module, points: np.ndarray) -> tuple[dict[str, float], int]:
    """One frame through the peer's stages with a stamp after each (CPU): ``({component: ms}, detections)``, the
    components of :data:`detector.bench.timing.COMPONENTS`."""
    stamps = [time.perf_counter()]
    pts = torch.from_numpy(points)
    stamps.append(time.perf_counter())
    voxels, num_points, coors = peer.voxelize([pts])
    features = peer.voxel_encoder(voxels, num_points, coors)
    batch_size = int(coors[-1, 0].item()) + 1 if coors.shape[0] else 1
    stamps.append(time.perf_counter())
    x = peer.middle_encoder(features, coors, batch_size)
    stamps.append(time.perf_counter())
    x = peer.neck(peer.backbone(x))
    stamps.append(time.perf_counter())
    outs = peer.bbox_head(x)
    stamps.append(time.perf_counter())
    with warnings.catch_warnings():  # its anchor generator calls torch.meshgrid without indexing= (a UserWarning)
        warnings.simplefilter("ignore", UserWarning)
        boxes, _, _ = peer.bbox_head.get_bboxes(*outs)
    stamps.append(time.perf_counter())
    return stamps_to_ms(stamps), int(sum(int(b.shape[0]) for b in boxes))
