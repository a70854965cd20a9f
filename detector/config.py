"""The detector's experiment configuration: one YAML file per experiment, loaded into frozen dataclasses.

The schema of the experiment YAMLs (the shipped ones in ``detector/configs/``, by name: ``--config mpchair_sparse``),
read once at the edge (``detector train/eval/bench/...``); modules below take
explicit keyword arguments. ``mpchair`` never reads this schema: ``mpchair stats --config`` takes only the pillar grid
(``model.point_cloud_range / voxel_size / output_shape``) through :func:`mpchair.geometry.geometry_from_model_yaml`,
and :func:`pseudoimage_geometry` gives the detector the same :class:`~mpchair.geometry.PseudoimageGeometry`.

The file reads top to bottom like OpenPCDet's ``pointpillar.yaml``: ``model`` (voxelizer → pillar net → backbone →
neck → anchors → head → losses → post-processing), ``data`` (classes and augmentation switches), ``train`` (optimiser
and schedule) and ``eval`` (classes and IoU thresholds). In the detector only
:func:`detector.models.build.build_model` reads ``model``; modules take explicit keyword arguments. Every length is
in metres, every angle in radians, and all boxes are ``[x, y, z_centre, l, w, h, yaw]`` in the sensor frame (x
forward, y left, z up), yaw CCW from +x.

Reference values (section 6 of ``pointpillars-reference.md``) are the defaults, so a config only has to name the
geometry; a config may also derive from another (``_BASE_CONFIG_: mpchair_sparse``) and set only what differs
(:func:`experiment_yaml`). See ``docs/model.md`` for every key.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from mpchair.core.config import (
    at_key_line,
    from_dict,
    load_derived_yaml,
    load_yaml,
    merge_config,
    package_folder,
    packaged_names,
    resolve_named_file,
)
from mpchair.core.errors import InputError
from mpchair.core.limits import machine_memory_bytes
from mpchair.geometry import PseudoimageGeometry, grid_size

Backbone = Literal["dense", "sparse", "sparse1_dense23", "sparse12_dense3", "sparse_wide", "sparse_wide_down"]
"""Middle of the network: the dense SECOND backbone + FPN, or one of the sparse variants of the paper. Sparse+WideConv
comes twice: ``sparse_wide`` as the paper's text describes it (the first SubM of every block 9x9) and
``sparse_wide_down`` as the released code builds it (a 9x9 stride-2 down-conv opening every block)."""

Downsample = Literal["floor", "reference_quirk"]
"""Sparse 2x2 stride-2 semantics: ``floor`` (paper, default) or the reference's MinkowskiEngine expand quirk."""

AnchorCentres = Literal["range", "cells"]
"""Where anchors sit on the head map: ``range``, ``linspace`` over ``anchor_range`` with the map's size, endpoints
included (the reference's ``Anchor3DRangeGenerator``; it drifts from the cells' centres by up to ±5 cm on the
288 x 144 CPU grid and up to 0.55 m on the padded 768 x 512 one); ``cells``, every cell's centre (OpenPCDet's
``align_center``), which stays right on any grid, so weights trained at one pseudo-image size transfer to another."""

Head = Literal["dense", "sparse_exact"]
"""``dense``: three 1x1 convs over the whole map. ``sparse_exact``: the same weights on active sites only, bias
elsewhere (identical output when the map is zero at inactive sites)."""

MEAN_CHAIR_LWH = (0.960005934232471, 0.6668719666706728, 0.8838318530669755)
"""Reference chair anchor [l, w, h] (m): the Matterport-Chair mean box (Open3D-ML lists it as (w, l, h))."""


@dataclass(frozen=True)
class ModelConfig:
    """Everything :func:`build_model` needs. Defaults are the reference's (Open3D-ML / SPP) values.

    Geometry: ``point_cloud_range`` ``[x_min, y_min, z_min, x_max, y_max, z_max]`` (m, sensor frame); ``voxel_size``
    ``[vx, vy, vz]`` (m; vz spans the whole z range, so pillars); ``output_shape`` ``[ny, nx]`` cells of the padded
    pseudo-image (>= the real grid, a multiple of the product of ``layer_strides``).

    Anchors: ``anchor_range`` ``[x_min, y_min, z_bottom, x_max, y_max, z_bottom]`` (anchor *bottom* z, as the
    reference); ``anchor_sizes`` ``[[l, w, h], ...]`` in OUR convention (l along the heading). Open3D-ML lists sizes
    as (w, l, h) with w the x extent at yaw 0; because the rotations {0, 1.57} cover both axis assignments, the
    reference anchor set is the same set of BEV rectangles as ours with l = the larger listed horizontal value for the
    car ([1.6, 3.9, 1.56] → l 3.9, w 1.6, h 1.56) and l = the first value for the chair ([0.960, 0.667, 0.884] →
    l 0.960, w 0.667, h 0.884).
    """

    # --- voxelizer (Feature Extract) ---
    point_cloud_range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, float, float]
    output_shape: tuple[int, int]
    in_channels: int = 3
    max_points_per_pillar: int = 32
    max_pillars_train: int = 16000
    max_pillars_test: int = 40000
    # --- pillar feature net ---
    pfn_channels: int = 64
    # --- backbone + neck ---
    backbone: Backbone = "dense"
    downsample: Downsample = "floor"
    layer_channels: tuple[int, ...] = (64, 128, 256)
    layer_nums: tuple[int, ...] = (3, 5, 5)
    layer_strides: tuple[int, ...] = (2, 2, 2)
    neck_channels: tuple[int, ...] = (128, 128, 128)
    upsample_strides: tuple[int, ...] = (1, 2, 4)
    # --- head + anchors ---
    head: Head = "dense"
    num_classes: int = 1
    anchor_range: tuple[float, float, float, float, float, float] = (0.0, -19.0, 0.0, 25.0, 19.0, 0.0)
    anchor_sizes: tuple[tuple[float, float, float], ...] = (MEAN_CHAIR_LWH,)
    anchor_rotations: tuple[float, ...] = (0.0, 1.57)
    anchor_centres: AnchorCentres = "range"
    # --- target assignment (nearest-BEV axis-aligned IoU) ---
    neg_iou_thr: float = 0.35
    pos_iou_thr: float = 0.5
    # --- losses ---
    focal_alpha: float = 0.25
    focal_gamma: float = 2.0
    cls_weight: float = 1.0
    smooth_l1_beta: float = 0.11
    reg_weight: float = 2.0
    dir_weight: float = 0.2
    dir_offset: float = 0.0
    # --- post-processing (BBox Extract) ---
    nms_pre: int = 100
    score_thr: float = 0.1
    nms_iou: float = 0.01
    dir_limit_offset: float = 0.0


@dataclass(frozen=True)
class GtSamplingConfig:
    """Ground-truth database sampling: paste up to ``sample`` database objects with >= ``min_points`` points."""

    enabled: bool = True
    min_points: int = 20
    sample: int = 10


@dataclass(frozen=True)
class DataConfig:
    """What the dataset yields and how training samples are augmented (read by ``detector.data`` / ``train``).

    ``classes``: label names trained on, in class-index order (index k ↔ head class k). ``rename``: pairs
    ``[from, to]`` applied to label names first (e.g. none for the chair set). ``fov_crop``: keep only points that
    project into the camera image (KITTI). ``range_filter``: drop GT boxes whose centre is outside the anchor x/y
    range (Open3D-ML ObjectRangeFilter). ``flip_y``: random flip of y (p 0.5); ``rotation``: uniform global yaw range
    (rad) or null; ``scaling``: uniform global scale range or null (all three off in the reference).
    """

    classes: tuple[str, ...] = ("Chair",)
    rename: tuple[tuple[str, str], ...] = ()
    fov_crop: bool = False
    gt_sampling: GtSamplingConfig = field(default_factory=GtSamplingConfig)
    point_shuffle: bool = True
    range_filter: bool = True
    flip_y: bool = False
    rotation: tuple[float, float] | None = None
    scaling: tuple[float, float] | None = None


Schedule = Literal["constant", "onecycle", "plateau"]
"""Learning-rate schedule: ``constant`` (the reference), ``onecycle`` (OpenPCDet's ``adam_onecycle``) or ``plateau``
(warm-up, constant LR, decay at a validation plateau, stop at the next: :mod:`detector.train.plateau`)."""
Precision = Literal["fp32", "bf16"]
"""Training precision: ``fp32`` (the reference) or ``bf16`` (bfloat16 autocast of the forward pass)."""


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser and schedule. Reference: AdamW lr 1e-3, betas (0.95, 0.99), wd 0.01, constant LR, batch 6.

    ``grad_clip_norm``: clip the total gradient norm to this value (``torch.nn.utils.clip_grad_norm_``) or null for no
    clipping. The reference config names ``grad_clip_norm: 2`` but never applies it (and would have clipped by
    value); we clip by norm at 10 like OpenPCDet, which only acts on rare spikes. ``samples_per_epoch``: samples drawn
    per epoch (reference 5000) or null for one pass over the split. ``shuffle``: the reference iterates in a fixed
    order every epoch (false).

    ``schedule``: ``constant`` (``lr`` throughout) or ``onecycle`` (``torch.optim.lr_scheduler.OneCycleLR`` over
    ``epochs x steps per epoch`` global steps, cosine annealing, stepped once per optimiser step): ``lr`` is then the
    peak, reached after ``pct_start`` of the steps from ``lr / div_factor``, and the last step uses
    ``lr / (div_factor * final_div_factor)``; AdamW's beta1 runs ``beta1_range[0] → beta1_range[1]`` (at the peak)
    ``→ beta1_range[0]`` and replaces ``betas[0]``. The defaults are OpenPCDet's ``adam_onecycle`` (pct_start 0.4,
    div_factor 10, final LR = initial / 1e4, moms [0.95, 0.85]). The one-cycle keys are ignored by ``constant``.
``plateau``: a linear warm-up from ``lr / div_factor`` to ``lr`` over ``warmup_epochs``, then ``lr`` until the
validation 3D AP (Overall R40, evaluated every epoch: ``eval_every`` must be 1) has not risen by ``plateau_min_delta``
points over ``plateau_patience`` epochs; each of the first ``plateau_decays`` such plateaus multiplies the LR by
``plateau_factor``, the next one stops the run; ``epochs`` is the cap (:mod:`detector.train.plateau`).

    ``precision``: ``fp32`` (the paper's), or ``bf16``: the forward pass runs under ``torch.autocast`` in bfloat16
    (convolutions and matmuls in bf16, accumulated in fp32 inside the kernels) while weights, optimiser state,
    gradients, losses and target assignment stay fp32; no loss scaling is needed (bf16 has fp32's exponent range).
    Evaluation always runs in fp32. Measured on the 2-core AVX512-BF16 CPU: 1.6x faster dense training steps, 1.2x
    sparse (docs/training.md, "Precision").
    """

    optimizer: Literal["adamw"] = "adamw"
    lr: float = 1e-3
    betas: tuple[float, float] = (0.95, 0.99)
    weight_decay: float = 0.01
    schedule: Schedule = "constant"
    pct_start: float = 0.4
    div_factor: float = 10.0
    final_div_factor: float = 1e4
    beta1_range: tuple[float, float] = (0.95, 0.85)
    batch_size: int = 6
    epochs: int = 200
    samples_per_epoch: int | None = None
    shuffle: bool = False
    grad_clip_norm: float | None = 10.0
    seed: int = 0
    num_workers: int = 0
    checkpoint_every: int = 2
    eval_every: int = 5
    precision: Precision = "fp32"
    warmup_epochs: float = 1.0
    plateau_patience: int = 5
    plateau_min_delta: float = 1.0
    plateau_decays: int = 1
    plateau_factor: float = 0.1


@dataclass(frozen=True)
class EvalConfig:
    """KITTI-protocol evaluation: ``classes`` with one IoU threshold each (BEV and 3D), result batch size.

    ``similar``: pairs ``[label, class]`` of neighbouring classes that are ignored rather than counted as false
    positives (KITTI: Van → Car).
    """

    classes: tuple[str, ...] = ("Chair",)
    iou_thresholds: tuple[float, ...] = (0.5,)
    similar: tuple[tuple[str, str], ...] = ()
    batch_size: int = 1


@dataclass(frozen=True)
class ExperimentConfig:
    """One experiment file: ``model``, ``data``, ``train``, ``eval`` (the last three default to the reference)."""

    model: ModelConfig
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


def real_grid(cfg: ModelConfig) -> tuple[int, int]:
    """The un-padded pillar grid ``(ny, nx)`` spanned by ``point_cloud_range`` / ``voxel_size`` (cells).

    Raises ValueError when the range is not a whole number of voxels (:func:`mpchair.geometry.grid_size`).
    """
    nx, ny = grid_size(cfg.point_cloud_range, cfg.voxel_size)
    return ny, nx


def pseudoimage_geometry(cfg: ModelConfig) -> PseudoimageGeometry:
    """The model's pillar grid as the shared floor names it: range and voxel (m, sensor frame) and the padded canvas
    ``(W, H)`` = ``output_shape[::-1]`` (for :func:`mpchair.geometry.frame_density`)."""
    ny, nx = cfg.output_shape
    return PseudoimageGeometry(cfg.point_cloud_range, cfg.voxel_size[:2], (nx, ny))


def check_model_config(cfg: ModelConfig, source: str = "<config>", batch_size: int = 1,
                       this_machine: bool = True) -> None:
    """Raise :class:`InputError` for values the dataclass types cannot express (ranges, divisibility, lengths), or
    (``this_machine``) for a model whose training step at ``batch_size`` cannot fit this machine's memory
    (:func:`check_memory`)."""

    def fail(msg: str) -> None:
        raise InputError(f"model.{msg}", source)

    x0, y0, z0, x1, y1, z1 = cfg.point_cloud_range
    if not (x1 > x0 and y1 > y0 and z1 > z0):
        fail(f"point_cloud_range: max must exceed min on every axis, got {list(cfg.point_cloud_range)}")
    if min(cfg.voxel_size) <= 0:
        fail(f"voxel_size: must be positive, got {list(cfg.voxel_size)}")
    if cfg.in_channels not in (3, 4):
        fail(f"in_channels: 3 (xyz) or 4 (xyzr), got {cfg.in_channels}")
    ny, nx = cfg.output_shape
    try:
        ry, rx = real_grid(cfg)
    except ValueError as e:
        raise InputError(f"model.point_cloud_range / voxel_size: {e}", source) from None
    if ny < ry or nx < rx:
        fail(f"output_shape: [{ny}, {nx}] is smaller than the real grid [{ry}, {rx}]")
    n_levels = len(cfg.layer_channels)
    if n_levels != 3 or any(
        len(t) != 3 for t in (cfg.layer_nums, cfg.layer_strides, cfg.neck_channels, cfg.upsample_strides)
    ):
        fail("layer_channels, layer_nums, layer_strides, neck_channels, upsample_strides: three levels each")
    for name in ("layer_channels", "layer_strides", "neck_channels", "upsample_strides"):
        if min(getattr(cfg, name)) < 1:
            fail(f"{name}: every value must be >= 1, got {list(getattr(cfg, name))}")
    if min(cfg.layer_nums) < 0:
        fail(f"layer_nums: every value must be >= 0, got {list(cfg.layer_nums)}")
    if cfg.pfn_channels < 1:
        fail(f"pfn_channels: must be >= 1, got {cfg.pfn_channels}")
    total = math.prod(cfg.layer_strides)
    if ny % total or nx % total:
        fail(f"output_shape: [{ny}, {nx}] must be a multiple of the total stride {total}")
    # Every neck level must land on the block-1 resolution so the three maps concatenate.
    cum = 1
    for i, (s, u) in enumerate(zip(cfg.layer_strides, cfg.upsample_strides)):
        cum *= s
        if cum // u != cfg.layer_strides[0] or cum % u:
            fail(f"upsample_strides[{i}]: {u} does not bring level {i} (stride {cum}) to stride {cfg.layer_strides[0]}")
    if cfg.backbone != "dense" and cfg.layer_strides != (2, 2, 2):
        fail(f"layer_strides: sparse backbones use 2x2 stride-2 down-convs, got {list(cfg.layer_strides)}")
    if cfg.backbone == "sparse_wide_down" and cfg.downsample != "floor":
        fail(f"downsample: {cfg.downsample!r} applies to 2x2 down-convs; sparse_wide_down's 9x9 down-conv has one "
             "output set (MinkowskiEngine's for odd kernels), use floor")
    if cfg.max_points_per_pillar < 1 or cfg.max_pillars_train < 1 or cfg.max_pillars_test < 1:
        fail("max_points_per_pillar / max_pillars_*: must be >= 1")
    if cfg.num_classes < 1:
        fail(f"num_classes: must be >= 1, got {cfg.num_classes}")
    if not cfg.anchor_sizes or not cfg.anchor_rotations:
        fail("anchor_sizes / anchor_rotations: at least one each")
    if any(min(s) <= 0 for s in cfg.anchor_sizes):
        fail("anchor_sizes: every l, w, h must be positive")
    if not 0.0 <= cfg.neg_iou_thr <= cfg.pos_iou_thr <= 1.0:
        fail(f"neg_iou_thr / pos_iou_thr: need 0 <= neg <= pos <= 1, got {cfg.neg_iou_thr}, {cfg.pos_iou_thr}")
    if cfg.nms_pre < 1:
        fail(f"nms_pre: must be >= 1, got {cfg.nms_pre}")
    if this_machine:
        check_memory(cfg, source, batch_size)


def memory_floor_bytes(cfg: ModelConfig, batch_size: int = 1) -> int:
    """A lower bound on the memory one training step of ``cfg`` needs (bytes, fp32): weights with their gradients and
    AdamW's two moments, the voxelizer's pillar buffer, and the neck's output map; a dense backbone adds the
    pseudo-image and one feature map per layer (a sparse one stores features at active sites only).

    Deliberately an under-estimate (no autograd copies, no allocator slack), so that it only refuses configs that
    cannot run at all, before anything is built or written.
    """
    c_in = 10 if cfg.in_channels == 4 else 9  # decorated point features of the pillar net
    weights = c_in * cfg.pfn_channels
    ny, nx = cfg.output_shape
    dense = cfg.backbone == "dense"
    maps = sum(cfg.neck_channels) * (ny // cfg.layer_strides[0]) * (nx // cfg.layer_strides[0])
    maps += cfg.pfn_channels * ny * nx if dense else 0
    c_prev, stride = cfg.pfn_channels, 1
    for c, n, s, u, cn in zip(cfg.layer_channels, cfg.layer_nums, cfg.layer_strides, cfg.upsample_strides,
                              cfg.neck_channels):
        stride *= s
        weights += 9 * c_prev * c + n * 9 * c * c + c * cn * u * u
        maps += (n + 1) * c * (ny // stride) * (nx // stride) if dense else 0
        c_prev = c
    pillars = max(cfg.max_pillars_train, cfg.max_pillars_test) * cfg.max_points_per_pillar * (c_in + cfg.pfn_channels)
    return 4 * (4 * weights + batch_size * (maps + pillars))


def check_memory(cfg: ModelConfig, source: str = "<config>", batch_size: int = 1) -> None:
    """:class:`InputError` when :func:`memory_floor_bytes` exceeds this machine's physical memory."""
    need, have = memory_floor_bytes(cfg, batch_size), machine_memory_bytes()
    if need > have:
        raise InputError(f"model: needs at least {need / 2**30:,.1f} GiB for one step (layer sizes, canvas, pillar "
                         f"buffer) but this machine has {have / 2**30:,.1f} GiB", source)


def check_experiment(cfg: ExperimentConfig, source: str = "<config>", this_machine: bool = True) -> None:
    """Cross-section checks: class lists agree with ``model.num_classes`` and ``eval.iou_thresholds``; the model's
    checks (:func:`check_model_config`, this machine's memory only if ``this_machine``)."""
    check_model_config(cfg.model, source, cfg.train.batch_size, this_machine)
    if len(cfg.data.classes) != cfg.model.num_classes:
        raise InputError(
            f"data.classes has {len(cfg.data.classes)} names but model.num_classes is {cfg.model.num_classes}", source
        )
    if len(cfg.eval.iou_thresholds) != len(cfg.eval.classes):
        raise InputError("eval.iou_thresholds: one threshold per eval class", source)
    unknown = [c for c in cfg.eval.classes if c not in cfg.data.classes]
    if unknown:
        raise InputError(f"eval.classes: {unknown[0]!r} is not a trained class (data.classes: "
                         f"{', '.join(cfg.data.classes)})", source)
    check_train_config(cfg.train, source)


#: Bounds that no real schedule reaches (the reference trains 200 epochs of 5,000 samples), so a typo cannot start a
#: run that never ends.
MAX_EPOCHS = 100_000
MAX_SAMPLES_PER_EPOCH = 10_000_000
MAX_WORKERS = 64


def check_train_config(cfg: TrainConfig, source: str = "<config>") -> None:
    """Raise :class:`InputError` for training values outside their range (the schedule name is checked on load)."""

    def fail(msg: str) -> None:
        raise InputError(f"train.{msg}", source)

    if cfg.batch_size < 1 or cfg.epochs < 0:
        raise InputError("train.batch_size must be >= 1 and train.epochs >= 0", source)
    if cfg.epochs > MAX_EPOCHS:
        fail(f"epochs: at most {MAX_EPOCHS:,}, got {cfg.epochs}")
    if cfg.samples_per_epoch is not None and not 1 <= cfg.samples_per_epoch <= MAX_SAMPLES_PER_EPOCH:
        fail(f"samples_per_epoch: between 1 and {MAX_SAMPLES_PER_EPOCH:,} (or null for one pass), got "
             f"{cfg.samples_per_epoch}")
    if not 0 <= cfg.seed < 2**32:
        fail(f"seed: between 0 and 2**32 - 1, got {cfg.seed}")
    if not 0 <= cfg.num_workers <= MAX_WORKERS:
        fail(f"num_workers: between 0 and {MAX_WORKERS}, got {cfg.num_workers}")
    if cfg.checkpoint_every < 0 or cfg.eval_every < 0:
        fail(f"checkpoint_every / eval_every: must be >= 0, got {cfg.checkpoint_every}, {cfg.eval_every}")
    if cfg.lr <= 0:
        fail(f"lr: must be > 0, got {cfg.lr}")
    if not 0.0 < cfg.pct_start < 1.0:
        fail(f"pct_start: must be strictly between 0 and 1, got {cfg.pct_start}")
    if cfg.div_factor < 1.0 or cfg.final_div_factor < 1.0:
        fail(f"div_factor / final_div_factor: must be >= 1 (lr is the peak), got {cfg.div_factor}, "
             f"{cfg.final_div_factor}")
    if not all(0.0 <= b < 1.0 for b in cfg.beta1_range):
        fail(f"beta1_range: both values must be in [0, 1), got {list(cfg.beta1_range)}")
    if not (math.isfinite(cfg.warmup_epochs) and 0.0 <= cfg.warmup_epochs <= MAX_EPOCHS):
        fail(f"warmup_epochs: must be >= 0, got {cfg.warmup_epochs}")
    if not 1 <= cfg.plateau_patience <= MAX_EPOCHS or not 0 <= cfg.plateau_decays <= 10:
        fail(f"plateau_patience / plateau_decays: must be >= 1 / in 0..10, got {cfg.plateau_patience}, "
             f"{cfg.plateau_decays}")
    if not (math.isfinite(cfg.plateau_min_delta) and cfg.plateau_min_delta >= 0.0):
        fail(f"plateau_min_delta: must be a finite number >= 0 (AP points), got {cfg.plateau_min_delta}")
    if not 0.0 < cfg.plateau_factor < 1.0:
        fail(f"plateau_factor: must be strictly between 0 and 1, got {cfg.plateau_factor}")
    if cfg.schedule == "plateau" and cfg.eval_every != 1:
        fail(f"eval_every: the plateau schedule evaluates after every epoch (eval_every: 1), got {cfg.eval_every}")


def experiment_from_dict(data: dict, source: str = "<config>") -> ExperimentConfig:
    """Build and check an :class:`ExperimentConfig` from a plain mapping (e.g. the copy stored in a checkpoint)."""
    cfg = from_dict(ExperimentConfig, data, source=source)
    check_experiment(cfg, source)
    return cfg


#: Folder of the shipped experiment configs (``detector/configs``, package data: also in an installed wheel).
CONFIG_DIR = package_folder("detector", "configs")


def available_configs() -> list[str]:
    """Names of the shipped experiment configs (``mpchair_sparse``, ...), sorted."""
    return packaged_names(CONFIG_DIR)


def config_file(name_or_path: str | Path) -> Path:
    """The YAML file of ``--config``: an existing file (a path wins), else a packaged config's name
    (:data:`CONFIG_DIR`)."""
    return resolve_named_file(name_or_path, CONFIG_DIR, "config")


def load_experiment(name_or_path: str | Path, overrides: Mapping | None = None) -> ExperimentConfig:
    """Load and validate an experiment: a YAML path or a packaged name, its ``_BASE_CONFIG_`` chain merged in, then
    ``overrides`` (a nested mapping like the YAML's, e.g. ``{"train": {"batch_size": 1}}``) on top.

    Bad keys / types / values, a missing base or a cycle of bases are one-line :class:`InputError` s naming the file.
    """
    path = config_file(name_or_path)
    data = experiment_yaml(path)
    if overrides:
        return experiment_from_dict(merge_config(data, overrides), source=f"{path} (with overrides)")
    try:
        return experiment_from_dict(data, source=str(path))
    except InputError as e:  # name the line of the key at fault in the file
        raise at_key_line(e, path) from None


def experiment_yaml(path: str | Path) -> dict:
    """The mapping of the experiment YAML ``path`` with its ``_BASE_CONFIG_`` chain merged in
    (:func:`mpchair.core.config.load_derived_yaml`): a base is a YAML path relative to the file's folder or a packaged
    config's name, and must be a complete, valid experiment on its own (checked as one, so that an error is named by
    the file that holds it)."""
    return load_derived_yaml(path, named_base=_packaged_base,
                             check_base=lambda data, base: experiment_from_dict(data, source=str(base)))


def _packaged_base(name: str) -> Path | None:
    """The shipped config called ``name`` (a ``_BASE_CONFIG_`` value without a suffix), or None."""
    return CONFIG_DIR / f"{name}.yaml" if name in available_configs() else None


def load_run_config(path: str | Path) -> ExperimentConfig:
    """The experiment a run was trained with (``RUN/config.yaml``, as
    :func:`detector.train.run_folder.write_run_files` writes it), for a reader of the run (a report, a status line):
    the schema and checks of :func:`load_experiment` but this machine's memory, since the run may come from another
    machine."""
    cfg = from_dict(ExperimentConfig, load_yaml(path), source=str(path))
    check_experiment(cfg, str(path), this_machine=False)
    return cfg
