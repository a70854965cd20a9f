"""The paper's Figs. 3-4: which pseudo-image cells are non-zero after each Conv block, dense vs sparse backbone.

White = at least one non-zero channel, black = all channels exactly zero. Dense (Fig. 3): the SECOND backbone with
its BatchNorm layers **removed**, as in the paper (with BN kept, the BN shift makes every cell non-zero); 3x3
convolutions smear the non-zero cells outward block after block. Sparse (Fig. 4): the Sparse PointPillars blocks
as they run (active-site BatchNorm keeps inactive cells at zero; SubM convs keep the active set; the 2x2 stride-2
down-conv maps each active cell to one coarse cell). Blocks of a sparse ablation's dense tail run like the dense
backbone (BN removed).

Image layout: every picture is the full ``ny x nx`` pseudo-image size (``output_shape``; a block-i cell becomes a
``2^i x 2^i`` square, so white areas are comparable across blocks), with +x (forward) to the right and +y (left) up,
i.e. array row ``iy`` drawn at image row ``ny - 1 - iy``. Random weights show the same pattern as trained ones (zero
stays zero; a non-zero cell is non-zero in some channel almost surely); a checkpoint can be given.
"""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from detector.checkpoint import load_model
from detector.config import ExperimentConfig, load_experiment, pseudoimage_geometry
from detector.data.experiment import load_eval_frames, open_split
from detector.models import PointPillars
from mpchair.core.atomic import write_bytes
from mpchair.core.errors import InputError
from mpchair.geometry import frame_density
from mpchair.kitti import imageset_path

STAGES: tuple[str, ...] = ("input", "block1", "block2", "block3")
TITLES: dict[str, str] = {"input": "Input pseudoimage", "block1": "After Conv block 1", "block2": "After Conv block 2",
                          "block3": "After Conv block 3"}


def _nonzero(x: torch.Tensor) -> np.ndarray:
    """(1, C, h, w) → (h, w) bool: any channel non-zero."""
    return (x[0] != 0).any(dim=0).cpu().numpy()


def _run_dense_block_without_bn(block: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    for layer in block:
        if not isinstance(layer, nn.modules.batchnorm._BatchNorm):
            x = layer(x)
    return x


@torch.no_grad()
def dense_masks(model: PointPillars, points: np.ndarray) -> list[np.ndarray]:
    """Non-zero masks of the dense model's input canvas and after each backbone block (BatchNorm removed)."""
    voxels = model.voxelize([torch.from_numpy(points)])
    features, coords = model.pillar_net(voxels)
    x = model.feature_net(features, coords, 1)
    masks = [_nonzero(x)]
    for block in model.backbone.blocks:
        x = _run_dense_block_without_bn(block, x)
        masks.append(_nonzero(x))
    return masks


@torch.no_grad()
def sparse_masks(model: PointPillars, points: np.ndarray) -> list[np.ndarray]:
    """Non-zero masks of the sparse model's input and after each block (sparse blocks as they run; dense tail
    blocks of an ablation with BatchNorm removed)."""
    voxels = model.voxelize([torch.from_numpy(points)])
    features, coords = model.pillar_net(voxels)
    x = model.feature_net(features, coords, 1)
    masks = [_nonzero(x.dense())]
    bb = model.backbone
    for i, block in enumerate(bb.blocks):
        if i < bb.sparse_blocks:
            x = block(x)
            masks.append(_nonzero(x.dense()))
        else:
            if not isinstance(x, torch.Tensor):
                x = x.dense()
            x = _run_dense_block_without_bn(block, x)
            masks.append(_nonzero(x))
    return masks


def to_image(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) bool at stride ``ny / h`` → (ny, nx) uint8 0/255, nearest upsampling, +y up (rows flipped)."""
    ny, nx = shape
    fy, fx = ny // mask.shape[0], nx // mask.shape[1]
    big = np.repeat(np.repeat(mask, fy, axis=0), fx, axis=1)
    return np.flipud(big).astype(np.uint8) * 255


def _png(img: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img), mode="L").save(buf, format="PNG")
    return buf.getvalue()


def panel_png(images: dict[str, list[np.ndarray]], fractions: dict[str, list[float]], title: str) -> bytes:
    """2 x 4 grid (dense row, sparse row; input and blocks 1-3) as PNG bytes (Agg canvas, no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows = list(images)
    ny, nx = images[rows[0]][0].shape
    fig = Figure(figsize=(4 * 2.6 * nx / max(nx, ny) + 0.5, len(rows) * 2.9 * ny / max(nx, ny) + 0.6), dpi=130)
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(rows), len(STAGES), squeeze=False)
    for r, name in enumerate(rows):
        for c, stage in enumerate(STAGES):
            ax = axes[r][c]
            ax.imshow(images[name][c], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{name}: {TITLES[stage]}\n{100 * fractions[name][c]:.2f}% non-zero", fontsize=7)
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


#: With neither --frame nor --index, the frame drawn is the one of median density D among the split's first
#: TYPICAL_FRAMES: the first frame may be nearly empty (D = 0.00036 on the demo data), which draws a blank panel.
TYPICAL_FRAMES = 50


def split_position(cfg: ExperimentConfig, data_dir: str | Path, split: str, *, frame_id: str | None = None,
                   index: int | None = None) -> int:
    """Position in ``split`` of the frame named by at most one of ``frame_id`` (``"000123"``; it must be listed in the
    split) or ``index`` (0 = the split's first frame); with neither, :func:`typical_position`. An
    :class:`InputError` naming the split file otherwise."""
    if frame_id is not None and index is not None:
        raise InputError("give either --frame ID (a frame id) or --index N (a position in the split), not both")
    if frame_id is None and index is None:
        return typical_position(cfg, data_dir, split)
    ids = open_split(cfg, data_dir, split).ids
    listing = imageset_path(data_dir, split)
    if frame_id is not None:
        if frame_id not in ids:
            raise InputError(f"frame {frame_id} is not in split {split!r} ({len(ids)} frames, {ids[0]} ... "
                             f"{ids[-1]}); pick one of its ids, or --split another split", listing)
        return ids.index(frame_id)
    if not 0 <= index < len(ids):
        raise InputError(f"--index {index} is outside split {split!r} (positions 0 to {len(ids) - 1})", listing)
    return index


def typical_position(cfg: ExperimentConfig, data_dir: str | Path, split: str) -> int:
    """Position in ``split`` of the frame of median pseudo-image density D (the lower median, the first such frame)
    among its first :data:`TYPICAL_FRAMES` frames, at ``cfg``'s grid."""
    frames = load_eval_frames(cfg, data_dir, split, TYPICAL_FRAMES)
    geometry = pseudoimage_geometry(cfg.model)
    densities = [frame_density(f.points, geometry)[2] for f in frames]
    order = sorted(range(len(densities)), key=lambda k: (densities[k], k))
    return order[(len(order) - 1) // 2]


def viz_sparsity(
    config_path: str | Path,
    data_dir: str | Path,
    out_dir: str | Path,
    *,
    frame_id: str | None = None,
    index: int | None = None,
    split: str = "test",
    dense_checkpoint: str | Path | None = None,
    sparse_checkpoint: str | Path | None = None,
    seed: int = 0,
) -> dict:
    """Write ``OUT/{dense,sparse}_{input,block1,block2,block3}.png`` and ``OUT/panel.png`` for one frame of ``split``:
    the frame id ``frame_id`` (``"000123"``) or the ``index``-th frame of the split (give exactly one). Returns
    ``{"frame_id", "files", "nonzero_fraction": {model: [4 fractions]}, "nonzero_cells": {model: [4 counts]}}``
    (fractions and counts at each stage's own resolution)."""
    cfg: ExperimentConfig = load_experiment(config_path)
    position = split_position(cfg, data_dir, split, frame_id=frame_id, index=index)
    data = load_eval_frames(cfg, data_dir, split, 1, position)[0]
    dense_model_cfg = replace(cfg.model, backbone="dense", head="dense")
    sparse_model_cfg = cfg.model if cfg.model.backbone != "dense" else replace(cfg.model, backbone="sparse")
    dev = torch.device("cpu")
    dense = load_model(replace(cfg, model=dense_model_cfg), dense_checkpoint, dev, seed=seed)
    sparse = load_model(replace(cfg, model=sparse_model_cfg), sparse_checkpoint, dev, seed=seed)
    masks = {"dense": dense_masks(dense, data.points), "sparse": sparse_masks(sparse, data.points)}
    shape = cfg.model.output_shape
    images = {k: [to_image(m, shape) for m in v] for k, v in masks.items()}
    fractions = {k: [float(m.mean()) for m in v] for k, v in masks.items()}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for name, imgs in images.items():
        for stage, img in zip(STAGES, imgs):
            path = out / f"{name}_{stage}.png"
            write_bytes(path, _png(img))
            files.append(str(path))
    title = (f"frame {data.frame_id} ({split}), {shape[0]}x{shape[1]} pseudo-image, D = {fractions['dense'][0]:.5f}\n"
             f"white = any non-zero channel; dense without BatchNorm; weights: "
             f"{'trained' if dense_checkpoint or sparse_checkpoint else f'random (seed {seed})'}")
    panel = out / "panel.png"
    write_bytes(panel, panel_png(images, fractions, title))
    files.append(str(panel))
    return {"frame_id": data.frame_id, "files": files, "nonzero_fraction": fractions,
            "nonzero_cells": {k: [int(m.sum()) for m in v] for k, v in masks.items()}}
