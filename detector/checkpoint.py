"""Checkpoint files: the one place that writes and reads them, and the one model loader (:func:`load_model`) that
``detector eval``, ``bench``, ``viz-sparsity``, ``stream-eval`` and the tools share.

A checkpoint is a ``torch.save`` dict of tensors and plain data only (numbers, strings, lists, tuples, dicts, None):
the model and optimiser state dicts, the LR scheduler's state, the epoch / step counters, the RNG states and the
experiment config as a plain dict. It is read with ``torch.load(weights_only=True)``, which refuses any pickle that
would import or call something else: a checkpoint from elsewhere cannot run code here. It is serialised in memory and
written with :func:`mpchair.core.atomic.write_bytes` (temp file + rename), so a full disk is an ``OSError`` naming
the file and a kill never leaves a half-written ``last.pt``.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import torch
from torch import nn

from detector.config import experiment_from_dict
from detector.models import ExperimentConfig, PointPillars, build_model
from mpchair.core.atomic import write_bytes
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError

CHECKPOINT_FORMAT = 1


def save_checkpoint(path: Path, *, model: nn.Module, optimizer: torch.optim.Optimizer, cfg: ExperimentConfig,
                    epoch: int, step_in_epoch: int, step: int, global_batch: int,
                    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None) -> None:
    """Write the training state to ``path`` atomically (``epoch``: completed epochs; ``step``: global steps)."""
    if isinstance(model, nn.parallel.DistributedDataParallel):
        model = model.module
    state = {
        "format": CHECKPOINT_FORMAT,
        "model": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict() if scheduler is not None else None,
        "epoch": epoch,
        "step_in_epoch": step_in_epoch,
        "step": step,
        "global_batch": global_batch,
        "rng": {
            "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        },
        "config": to_dict(cfg),
    }
    buf = io.BytesIO()
    torch.save(state, buf)
    write_bytes(path, buf.getbuffer())


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (tensors and plain data only).

    A missing, damaged or foreign file, and one whose pickle would import or call anything else, is an
    :class:`InputError` (one line); nothing in the file runs.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("checkpoint not found", path)
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises many types for damaged files (pickle, zip, runtime)
        text = " ".join(str(e).split())
        unsafe = re.search(r"\bGLOBAL ([\w.]+)", text)  # the wording differs between torch versions
        if unsafe:
            raise InputError(f"refused: loading it would call {unsafe.group(1)}; a checkpoint holds only tensors "
                             "and plain data (numbers, strings, lists, dicts)", path) from None
        raise InputError(f"cannot read checkpoint: {type(e).__name__}: {text[:300]}", path) from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT or "model" not in state:
        raise InputError("not a detector checkpoint (missing format/model keys)", path)
    return state


def config_from_checkpoint(state: dict, source: str) -> ExperimentConfig:
    """The experiment a checkpoint was trained with."""
    return experiment_from_dict(state["config"], source=source)


def load_model(cfg: ExperimentConfig, checkpoint: str | Path | None, device: torch.device | str = "cpu", *,
               seed: int = 0) -> PointPillars:
    """``cfg.model`` in eval mode on ``device``: trained weights from ``checkpoint``, or seeded random weights when it
    is None (drawn under ``torch.random.fork_rng``, so the caller's global RNG is untouched).

    Conv weights do not depend on the grid, so a checkpoint trained at one pseudo-image size loads into a model of
    another size. A checkpoint whose weights do not fit the model is an :class:`InputError` (one line).
    """
    if checkpoint is None:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model = build_model(cfg.model)
        return model.to(device).eval()
    state = load_checkpoint(checkpoint, map_location=device)
    model = build_model(cfg.model).to(device)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as e:
        first = str(e).strip().splitlines()
        msg = " ".join(first[:2])[:300]
        raise InputError(f"checkpoint does not fit the config's model: {msg}", checkpoint) from None
    return model.eval()
