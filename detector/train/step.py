"""One optimiser step: forward (optionally under bf16 autocast), target assignment, losses normalised by the global
batch's positives, backward, gradient clipping, AdamW and LR-scheduler step.

**Loss normalisation across ranks.** The losses are sums over anchors divided by the positives; each rank rescales
its loss by ``world * max(1, pos_rank) / max(1, pos_global)`` because DDP averages gradients, so N processes x batch
b get the gradient of one process x batch N·b (with :func:`~detector.train.distributed.convert_to_global_batchnorm`
for the BatchNorm statistics).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import torch
from torch import nn

from detector.data import Batch
from detector.device import pin_memory, synchronize
from detector.models import HeadOutput, Losses, PointPillars, compute_loss
from detector.train.distributed import all_reduce_sum


class TrainingError(Exception):
    """Training cannot go on (e.g. a non-finite loss); the message says why and which checkpoint is intact."""


@dataclasses.dataclass(frozen=True)
class ModelAndOptimiser:
    """The model under training and what updates it: ``model`` (the plain module: targets, losses, state dict),
    ``ddp`` (the same model wrapped in ``DistributedDataParallel`` under torchrun, else ``model``), the AdamW
    optimiser, the LR scheduler (None: constant LR) and the trainable parameters (clipped together)."""

    model: PointPillars
    ddp: nn.Module
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler | None
    params: list[nn.Parameter]


@dataclasses.dataclass(frozen=True)
class StepSettings:
    """What every step of a run shares: the device, bf16 autocast of the forward, the clipping norm (None: off), the
    number of processes, the run's global steps (the scheduler is not stepped past the last) and the checkpoint that
    stays intact when a step fails (named in :class:`TrainingError`)."""

    device: torch.device
    bf16: bool
    grad_clip_norm: float | None
    world_size: int
    total_steps: int
    last_good: Path


@dataclasses.dataclass(frozen=True)
class StepStats:
    """What one step measured: ``losses`` (floats, this step's global-batch losses summed over ranks), the gradient
    norm before clipping, the positive anchors of the global batch, and the lr / beta1 the step used."""

    losses: Losses
    grad_norm: float
    num_pos: int
    lr: float
    beta1: float


def all_reduce_losses(losses: Losses, scale: torch.Tensor) -> Losses:
    """``losses * scale`` detached, summed over ranks in float64, as float :class:`Losses` (one all-reduce)."""
    stacked = torch.stack([getattr(losses, name).detach() * scale for name in Losses._fields]).to(torch.float64)
    summed = all_reduce_sum(stacked).tolist()
    return Losses(**dict(zip(Losses._fields, summed, strict=True)))


def _forward_losses(batch: Batch, parts: ModelAndOptimiser, settings: StepSettings) -> tuple[torch.Tensor, Losses, int]:
    """The loss to back-propagate on this rank, the global batch's logged losses and its positive anchors."""
    with torch.autocast(settings.device.type, dtype=torch.bfloat16, enabled=settings.bf16):
        preds = parts.ddp(list(batch.points))
    preds = HeadOutput(*(p.float() for p in preds))  # losses in fp32 (a no-op for fp32 training)
    model = parts.model
    targets = model.targets(list(batch.boxes), list(batch.labels))
    losses = compute_loss(preds, targets, num_classes=model.num_classes, **model.loss_params)
    # Re-normalise by the positives of the whole global batch (see the module docstring).
    pos_rank = targets.pos.sum().to(torch.float64)
    pos_global = all_reduce_sum(pos_rank.detach().reshape(1))[0]
    own = pos_rank.clamp(min=1)
    scale = (own / pos_global.clamp(min=1)).to(preds.cls.dtype)
    return losses.total * scale * settings.world_size, all_reduce_losses(losses, scale), int(pos_global)


def _kept(last_good: Path) -> str:
    """What a stopped run keeps, in words: the checkpoint when one was written, else that nothing was (a run that
    fails before its first checkpoint must not point at a file that does not exist)."""
    if last_good.is_file():
        return f"{last_good} keeps the last good state"
    return f"no checkpoint was written yet ({last_good} does not exist), so nothing is kept"


def train_step(batch: Batch, parts: ModelAndOptimiser, settings: StepSettings, *, epoch: int, step: int) -> StepStats:
    """Train on this rank's ``batch`` of global step ``step + 1`` in epoch ``epoch + 1`` (both counted from 0 here,
    from 1 in messages). A non-finite loss or gradient norm raises :class:`TrainingError` before the weights change
    (every rank sees the same all-reduced values and stops at the same step)."""
    batch = batch.to(settings.device, non_blocking=pin_memory(settings.device))
    loss, logged, num_pos = _forward_losses(batch, parts, settings)
    if not math.isfinite(logged.total):
        raise TrainingError(
            f"non-finite loss ({logged.total}) at epoch {epoch + 1}, step {step + 1} (frames "
            f"{', '.join(batch.frame_ids)}); training stopped, {_kept(settings.last_good)}. Check the data for "
            "NaN/inf values or lower train.lr")
    optimizer = parts.optimizer
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    max_norm = settings.grad_clip_norm if settings.grad_clip_norm is not None else math.inf
    grad_norm = float(torch.nn.utils.clip_grad_norm_(parts.params, max_norm))
    if not math.isfinite(grad_norm):
        raise TrainingError(
            f"non-finite gradient norm at epoch {epoch + 1}, step {step + 1}; training stopped, "
            f"{_kept(settings.last_good)}. Lower train.lr or enable train.grad_clip_norm")
    lr, beta1 = optimizer.param_groups[0]["lr"], optimizer.param_groups[0]["betas"][0]
    optimizer.step()
    if parts.scheduler is not None and step + 1 < settings.total_steps:
        parts.scheduler.step()  # not past the last step, so a finished run keeps the final lr
    synchronize(settings.device)  # CUDA queues the optimiser's kernels: the step's time must include them
    return StepStats(losses=logged, grad_norm=grad_norm, num_pos=num_pos, lr=lr, beta1=beta1)
