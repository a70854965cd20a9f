"""Resuming a run from ``RUN/last.pt``: which checkpoint may continue this config, and restoring its state.

A checkpoint holds the model, the optimiser, the LR scheduler, the epoch, the step within it, the global step, the RNG
states and the config. Data order and augmentation depend only on ``(seed, epoch, slot)``, so resuming at step ``s``
replays exactly the batches an uninterrupted run would see: the weights are identical. Only
:data:`RESUMABLE_CHANGES` may differ from the checkpoint's config, the global batch must stay the same, and a
one-cycle run's length is fixed when it starts.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn

from detector.checkpoint import Checkpoint, load_checkpoint
from detector.config import ExperimentConfig, experiment_from_dict
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError

#: Config keys that may change between a run and its resume: they do not change the trained weights. (``epochs`` only
#: with the constant schedule: it fixes the length of a one-cycle schedule, see :func:`check_schedule_length`.)
RESUMABLE_CHANGES = ("epochs", "num_workers", "checkpoint_every", "eval_every")
#: What a checkpoint must hold beyond the model's weights to continue a run.
_TRAINING_FIELDS = ("optimizer", "epoch", "step_in_epoch", "step", "global_batch", "rng", "config")


class Position(NamedTuple):
    """Where a run is: ``epoch`` completed epochs, ``step_in_epoch`` steps into the next one, ``step`` global steps."""

    epoch: int = 0
    step_in_epoch: int = 0
    step: int = 0


def comparable_config(cfg_dict: dict) -> dict:
    """A config dict as JSON data without :data:`RESUMABLE_CHANGES`, for comparing a run with its checkpoint."""
    # Through the dataclasses first, so a checkpoint written before a key existed compares with its default.
    d = json.loads(json.dumps(to_dict(experiment_from_dict(cfg_dict))))
    for key in RESUMABLE_CHANGES:
        d.get("train", {}).pop(key, None)
    return d


def read_resume_checkpoint(last_path: Path, cfg: ExperimentConfig, *, resume: bool,
                           config_path: str | Path) -> Checkpoint | None:
    """The checkpoint at ``last_path`` that this run continues, or None for a fresh start (no such file).

    An existing run without ``resume``, a checkpoint without training state, and a config that differs from the
    checkpoint's in more than :data:`RESUMABLE_CHANGES` are an :class:`InputError`.
    """
    if not last_path.is_file():
        return None
    if not resume:
        raise InputError(f"{last_path.parent} already holds a run (last.pt); pass --resume to continue it or pick a "
                         "new --out")
    checkpoint = load_checkpoint(last_path)
    missing = [name for name in _TRAINING_FIELDS if getattr(checkpoint, name) is None]
    if missing:
        raise InputError(f"holds no training state to resume ({', '.join(missing)} missing)", last_path)
    if comparable_config(checkpoint.config) != comparable_config(to_dict(cfg)):
        raise InputError(f"the config differs from the one {last_path} was trained with (only "
                         f"{', '.join('train.' + k for k in RESUMABLE_CHANGES)} may change on resume)", config_path)
    return checkpoint


def check_global_batch(checkpoint: Checkpoint, last_path: Path, global_batch: int) -> None:
    """The resumed run must keep the checkpoint's global batch (``batch_size x processes``)."""
    if checkpoint.global_batch != global_batch:
        raise InputError(f"{last_path} was trained with global batch {checkpoint.global_batch}, this run has "
                         f"{global_batch} (batch_size x processes must stay the same to resume)")


def check_schedule_length(checkpoint: Checkpoint, last_path: Path, cfg: ExperimentConfig, *, total_steps: int,
                          steps_per_epoch: int, config_path: str | Path) -> None:
    """A one-cycle run resumes only with the schedule length it started with (``total_steps`` global steps)."""
    tc = cfg.train
    if tc.schedule != "onecycle":
        return
    saved = (checkpoint.scheduler or {}).get("total_steps")
    if saved != total_steps:
        raise InputError(f"{last_path} follows a one-cycle schedule over {saved} steps; this run would have "
                         f"{total_steps} (train.epochs {tc.epochs} x {steps_per_epoch} steps per epoch). The "
                         "schedule's length is fixed when a run starts: resume with the original train.epochs "
                         "/ --epochs and split, or start a new run", config_path)


def restore(checkpoint: Checkpoint, model: nn.Module, optimizer: torch.optim.Optimizer,
            scheduler: torch.optim.lr_scheduler.LRScheduler | None) -> Position:
    """Load the checkpoint's weights, optimiser and scheduler state and RNG states; returns its position."""
    model.load_state_dict(checkpoint.model)
    optimizer.load_state_dict(checkpoint.optimizer)
    if scheduler is not None:
        scheduler.load_state_dict(checkpoint.scheduler)
    checkpoint.rng.restore()
    return Position(int(checkpoint.epoch), int(checkpoint.step_in_epoch), int(checkpoint.step))


def ends_an_evaluated_epoch(cfg: ExperimentConfig, at: Position) -> bool:
    """Whether ``at`` is the end of an epoch that ``train.eval_every`` evaluates: a run resumed there whose log lacks
    that evaluation was stopped during it, and evaluates those weights first."""
    tc = cfg.train
    return at.step_in_epoch == 0 and at.epoch > 0 and tc.eval_every > 0 and at.epoch % tc.eval_every == 0


def interrupted_line(last_path: Path, resume_command: str) -> str:
    """What a person needs after Ctrl-C: the step ``last_path`` holds (the newest save: an epoch's end, ``--max-steps``
    or the mid-epoch save every ``SAVE_INTERVAL_S`` seconds) and ``resume_command``, or that nothing was saved yet."""
    if not last_path.is_file():
        return (f"interrupted before the first checkpoint ({last_path} not written): nothing to resume; start again "
                f"with: {resume_command.removesuffix(' --resume')}")
    try:
        saved = load_checkpoint(last_path)
    except InputError as e:
        return f"interrupted; {last_path} cannot be resumed: {e}"
    where = f"step {saved.step} (epoch {saved.epoch} done" + (
        f", {saved.step_in_epoch} step(s) into epoch {saved.epoch + 1})" if saved.step_in_epoch else ")")
    return (f"interrupted: {last_path} holds {where}; steps after it are lost. Continue with: {resume_command}")
