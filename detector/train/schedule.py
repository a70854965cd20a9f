"""The learning-rate schedule of ``train.schedule``: a constant LR or OpenPCDet's one-cycle over the run's global
optimiser steps.

``onecycle`` drives the learning rate and AdamW's beta1 with ``torch.optim.lr_scheduler.OneCycleLR`` over ``epochs *
steps_per_epoch`` global steps (``steps_per_epoch`` counts global batches, so a torchrun job and one process with the
same global batch get the same schedule), stepped once per optimiser step. A one-cycle run's length is fixed when it
starts (:func:`detector.train.resume.check_schedule_length`).
"""

from __future__ import annotations

from pathlib import Path

import torch

from detector.config import ExperimentConfig
from mpchair.core.errors import InputError


def build_scheduler(optimizer: torch.optim.Optimizer, cfg: ExperimentConfig,
                    total_steps: int) -> torch.optim.lr_scheduler.LRScheduler | None:
    """The LR scheduler of ``train.schedule`` over ``total_steps`` global optimiser steps (None: constant LR, or
    ``plateau``, whose LR the epoch loop sets from :func:`detector.train.plateau.plateau_lr`).

    ``onecycle``: ``OneCycleLR`` with ``max_lr = train.lr``, cosine annealing, and AdamW's beta1 cycled from
    ``beta1_range[0]`` down to ``beta1_range[1]`` at the peak and back (OpenPCDet's ``adam_onecycle``). Creating it
    sets the optimiser's lr and beta1 to their step-0 values. A run without steps (``total_steps == 0``) gets None.
    """
    tc = cfg.train
    if tc.schedule in ("constant", "plateau") or total_steps == 0:  # plateau: the loop sets the LR per step
        return None
    return torch.optim.lr_scheduler.OneCycleLR(
        optimizer, max_lr=tc.lr, total_steps=total_steps, pct_start=tc.pct_start, anneal_strategy="cos",
        cycle_momentum=True, max_momentum=tc.beta1_range[0], base_momentum=tc.beta1_range[1],
        div_factor=tc.div_factor, final_div_factor=tc.final_div_factor, three_phase=False)


def check_warmup(cfg: ExperimentConfig, total_steps: int, config_path: str | Path) -> None:
    """A one-cycle warm-up must last more than one step (``pct_start * total_steps > 1``), else an
    :class:`InputError` naming the config."""
    tc = cfg.train
    if tc.schedule == "onecycle" and 0 < total_steps and tc.pct_start * total_steps <= 1:
        raise InputError(f"train.pct_start x total steps = {tc.pct_start} x {total_steps} must exceed 1: the "
                         "one-cycle warm-up needs more than one step (raise train.epochs or pct_start)", config_path)
