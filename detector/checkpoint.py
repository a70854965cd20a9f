"""Checkpoint files: the one place that writes and reads them, and the one model loader (:func:`load_model`) that
``detector eval``, ``bench``, ``viz-sparsity``, ``stream-eval`` and the tools share.

In memory a checkpoint is a :class:`Checkpoint` record; on disk it is a ``torch.save`` dict of tensors and plain data
only (numbers, strings, lists, tuples, dicts, None): the model and optimiser state dicts, the LR scheduler's state,
the epoch / step counters, the RNG states and the experiment config as a plain dict. It is read with
``torch.load(weights_only=True)``, which refuses any pickle that would import or call something else: a checkpoint
from elsewhere cannot run code here. It is serialised in memory and written with
:func:`mpchair.core.atomic.write_bytes` (temp file + rename), so a full disk is an ``OSError`` naming the file and a
kill never leaves a half-written ``last.pt``.
"""

from __future__ import annotations

import dataclasses
import io
import json
import re
import sys
import warnings
from collections import OrderedDict
from pathlib import Path

import torch
from torch import nn

from detector.config import ExperimentConfig, experiment_from_dict
from detector.models import PointPillars, build_model
from detector.pretrained import add_to_index, resolve_checkpoint
from mpchair.core.atomic import write_bytes
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError

CHECKPOINT_FORMAT = 1


@dataclasses.dataclass(frozen=True)
class RngStates:
    """The global torch generators' states: ``cpu`` (``torch.get_rng_state()``, the file's ``rng["torch"]``) and one
    per visible CUDA device (``cuda``; empty without CUDA)."""

    cpu: torch.Tensor
    cuda: tuple[torch.Tensor, ...] = ()

    @classmethod
    def capture(cls) -> RngStates:
        """This process's generator states now."""
        return cls(cpu=torch.get_rng_state(),
                   cuda=tuple(torch.cuda.get_rng_state_all()) if torch.cuda.is_available() else ())

    def restore(self) -> None:
        """Set this process's generators to these states (the CUDA ones only where CUDA is available)."""
        torch.set_rng_state(self.cpu)
        if self.cuda and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(list(self.cuda))


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """What a checkpoint holds: the model's ``state_dict`` and, from a training run, the optimiser's and the LR
    scheduler's state dicts (``scheduler`` None for a constant LR), ``epoch`` (completed epochs), ``step_in_epoch``,
    the global ``step``, the ``global_batch`` (samples per optimiser step, all processes), the RNG states and the
    experiment ``config`` as a plain dict. A file without some training field (one not written by a training run)
    reads it as None."""

    model: dict[str, torch.Tensor]
    optimizer: dict | None = None
    scheduler: dict | None = None
    epoch: int | None = None
    step_in_epoch: int | None = None
    step: int | None = None
    global_batch: int | None = None
    rng: RngStates | None = None
    config: dict | None = None
    format: int = CHECKPOINT_FORMAT

    @classmethod
    def capture(cls, *, model: nn.Module, optimizer: torch.optim.Optimizer, cfg: ExperimentConfig, epoch: int,
                step_in_epoch: int, step: int, global_batch: int,
                scheduler: torch.optim.lr_scheduler.LRScheduler | None = None) -> Checkpoint:
        """The training state now (``epoch``: completed epochs; ``step``: global steps), with this process's RNG
        states. The state dicts reference the live tensors: save it before the next optimiser step."""
        if isinstance(model, nn.parallel.DistributedDataParallel):
            model = model.module
        return cls(model=model.state_dict(), optimizer=optimizer.state_dict(),
                   scheduler=scheduler.state_dict() if scheduler is not None else None, epoch=epoch,
                   step_in_epoch=step_in_epoch, step=step, global_batch=global_batch, rng=RngStates.capture(),
                   config=to_dict(cfg))


def _file_dict(checkpoint: Checkpoint) -> dict:
    """The plain dict ``torch.save`` writes (its keys in this order since format 1, so the bytes stay the same)."""
    rng = checkpoint.rng
    return {
        "format": checkpoint.format,
        "model": checkpoint.model,
        "optimizer": checkpoint.optimizer,
        "scheduler": checkpoint.scheduler,
        "epoch": checkpoint.epoch,
        "step_in_epoch": checkpoint.step_in_epoch,
        "step": checkpoint.step,
        "global_batch": checkpoint.global_batch,
        "rng": None if rng is None else {"torch": rng.cpu, "cuda": list(rng.cuda)},
        "config": checkpoint.config,
    }


def _from_file_dict(state: dict) -> Checkpoint:
    """A loaded file's dict as a :class:`Checkpoint` (keys an older or foreign writer left out read as None)."""
    rng = state.get("rng")
    has_rng = isinstance(rng, dict) and isinstance(rng.get("torch"), torch.Tensor)
    return Checkpoint(
        model=state["model"], optimizer=state.get("optimizer"), scheduler=state.get("scheduler"),
        epoch=state.get("epoch"), step_in_epoch=state.get("step_in_epoch"), step=state.get("step"),
        global_batch=state.get("global_batch"),
        rng=RngStates(cpu=rng["torch"], cuda=tuple(rng.get("cuda") or ())) if has_rng else None,
        config=state.get("config"), format=state["format"])


def _canonical(obj):
    """``obj`` rebuilt with every container new and every string interned, so that pickle's memo (which writes an
    object seen before as a back-reference) sees the same sharing whatever the objects' history: a resumed run's
    optimiser state holds the keys it unpickled, an uninterrupted run's the interned literals, and without this the
    same checkpoint pickled to different bytes (the ``step`` key once in full, once as a back-reference)."""
    if isinstance(obj, str):
        return sys.intern(obj)
    if isinstance(obj, OrderedDict):  # a state_dict: keep its type and the modules' versions in ``_metadata``
        out = OrderedDict((_canonical(k), _canonical(v)) for k, v in obj.items())
        if hasattr(obj, "_metadata"):
            out._metadata = _canonical(obj._metadata)
        return out
    if isinstance(obj, dict):
        return {_canonical(k): _canonical(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_canonical(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_canonical(v) for v in obj)
    return obj


def save_checkpoint(path: Path, checkpoint: Checkpoint) -> None:
    """Write ``checkpoint`` to ``path`` atomically, as the plain dict of tensors and plain data described above; the
    same state gives the same bytes, resumed or not (:func:`_canonical`)."""
    buf = io.BytesIO()
    torch.save(_canonical(_file_dict(checkpoint)), buf)
    write_bytes(path, buf.getbuffer())


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint` (tensors and plain data only), tensors on
    ``map_location``.

    ``path`` may name packaged weights (``pretrained:sparse``, :mod:`detector.pretrained`). A missing, damaged or
    foreign file, and one whose pickle would import or call anything else, is an :class:`InputError` (one line);
    nothing in the file runs.
    """
    path = resolve_checkpoint(path)
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
        # torch's own text advises weights_only=False, which would run whatever the file holds: never repeat it
        raise InputError(f"not a detector checkpoint: torch.load cannot read it ({type(e).__name__}); a checkpoint "
                         "is the last.pt or checkpoints/epoch_NNN.pt of a detector train run", path) from None
    if isinstance(state, dict) and "format" in state and state["format"] != CHECKPOINT_FORMAT:
        # before the keys: another format may hold other keys, and "missing keys" would hide why it is refused
        raise InputError(f"checkpoint format {state['format']!r}, but this version reads format {CHECKPOINT_FORMAT} "
                         "only (written by another version of detector?)", path)
    if not isinstance(state, dict) or "format" not in state or "model" not in state:
        raise InputError("not a detector checkpoint (missing format/model keys)", path)
    return _from_file_dict(state)


def config_from_checkpoint(checkpoint: Checkpoint, source: str) -> ExperimentConfig:
    """The experiment a checkpoint was trained with (``source`` names it in errors)."""
    if checkpoint.config is None:
        raise InputError("the checkpoint holds no experiment config", source)
    return experiment_from_dict(checkpoint.config, source=source)


def _differing_model_keys(stored: dict, cfg: ExperimentConfig) -> dict[str, tuple[object, object]]:
    """The ``model`` keys on which a checkpoint's stored config dict and ``cfg`` differ: key -> (the checkpoint's
    value, ``cfg``'s), as JSON values, in the schema's key order."""
    try:
        # through the dataclasses, so a checkpoint written before a key existed compares with its default
        theirs = json.loads(json.dumps(to_dict(experiment_from_dict(stored).model)))
    except InputError:
        theirs = json.loads(json.dumps(stored.get("model", {}), default=str))
    ours = json.loads(json.dumps(to_dict(cfg.model)))
    return {key: (theirs.get(key), value) for key, value in ours.items() if theirs.get(key) != value}


def config_differences(stored: dict, cfg: ExperimentConfig) -> list[str]:
    """The ``model.*`` keys on which a checkpoint's stored config dict and ``cfg`` differ, in plain words
    (``model.output_shape is [288, 144] in the checkpoint, [768, 512] here``), in the schema's key order. Only the
    model section: data, train and eval settings do not change what the weights mean."""
    return _difference_lines(_differing_model_keys(stored, cfg))


def _difference_lines(differing: dict[str, tuple[object, object]]) -> list[str]:
    """:func:`_differing_model_keys`'s result in plain words, one line per key."""
    return [f"model.{key} is {json.dumps(theirs)} in the checkpoint, {json.dumps(ours)} here"
            for key, (theirs, ours) in differing.items()]


def weights_misfit(model: nn.Module, weights: dict[str, torch.Tensor]) -> str | None:
    """What keeps ``weights`` from loading into ``model`` (tensors of another shape, missing, unexpected), or None."""
    own = model.state_dict()
    shapes = [k for k in own if k in weights and tuple(weights[k].shape) != tuple(own[k].shape)]
    missing = [k for k in own if k not in weights]
    unexpected = [k for k in weights if k not in own]
    parts = [f"{len(keys)} tensor(s) {what} (first {keys[0]})"
             for keys, what in ((shapes, "of another shape"), (missing, "missing"), (unexpected, "unexpected"))
             if keys]
    return ", ".join(parts) or None


GRID_KEYS = ("point_cloud_range", "voxel_size", "output_shape")
"""The model keys that make a pseudo-image grid: weights moved between grids get cell-centred anchors."""

GRID_MOVE_KEYS = frozenset({"point_cloud_range", "output_shape", "anchor_range", "anchor_centres"})
"""The keys a move to a larger or smaller grid of the same pillars changes: weights moved so are said in one line."""


def load_model(cfg: ExperimentConfig, checkpoint: str | Path | None, device: torch.device | str = "cpu", *,
               seed: int = 0) -> PointPillars:
    """``cfg.model`` in eval mode on ``device``: trained weights from ``checkpoint``, or seeded random weights when it
    is None (drawn under ``torch.random.fork_rng``, so the caller's global RNG is untouched).

    The checkpoint's stored config is compared with ``cfg`` (:func:`config_differences`). Conv weights do not depend
    on the grid, so a checkpoint trained at one pseudo-image size loads into a model of another size: that loads,
    with one warning naming what differs, and with cell-centred anchors (``anchor_centres: cells``,
    :mod:`detector.models.anchors`), so that boxes land where the trained network puts them on any grid.
    A checkpoint whose weights do not fit the model is an :class:`InputError`
    (one line: the differing keys, or the tensors when the file stores no config).
    """
    if checkpoint is None:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model = build_model(cfg.model)
        return model.to(device).eval()
    saved = load_checkpoint(checkpoint, map_location=device)
    differing = _differing_model_keys(saved.config, cfg) if isinstance(saved.config, dict) else {}
    differences = _difference_lines(differing)
    moved = any(key in GRID_KEYS for key in differing)
    model_cfg = cfg.model
    if moved and model_cfg.anchor_centres != "cells":
        # The network learned box offsets for the anchor placement of the grid it trained on; with the reference's
        # linspace placement that drift differs per grid (9-39 cm between 288 x 144 and 768 x 512), so every box on
        # the new grid would be off by it. Cell-centred anchors are exact for weights trained with them and within
        # a linspace grid's own drift (±5 cm on 288 x 144) of its anchors otherwise.
        model_cfg = dataclasses.replace(model_cfg, anchor_centres="cells")
        differences.append("anchors are placed at the head map's cell centres (model.anchor_centres: cells) "
                           "because the weights move to another grid")
    model = build_model(model_cfg).to(device)
    misfit = weights_misfit(model, saved.model)
    if misfit is not None:
        why = "; ".join(differences) if differences else misfit
        raise InputError(f"checkpoint does not fit the config's model: {why}", checkpoint)
    if differing and set(differing) <= GRID_MOVE_KEYS | {"head"} and "output_shape" in differing:
        # the documented transfer (make reproduce times the 288 x 144-trained weights at 768 x 512, the sparse ones
        # also with the exact sparse head, the same weights computing the same maps): one plain line
        (was, now) = ((" x ".join(str(v) for v in shape) if isinstance(shape, list) else str(shape))
                      for shape in differing["output_shape"])
        head = (f"; head {differing['head'][1]} here (the same weights)" if "head" in differing else "")
        warnings.warn(f"{checkpoint}: weights trained on the {was} grid run on this config's {now} grid (same "
                      f"pillars, larger area; anchors at the head map's cell centres{head})", stacklevel=2)
    elif differences:
        warnings.warn(f"{checkpoint}: trained under another config ({'; '.join(differences)}); its weights load "
                      "into this one, but results may differ from the trained model's", stacklevel=2)
    model.load_state_dict(saved.model)
    return model.eval()


#: Precisions a packed file may store its floating-point tensors in (loading casts them back to the model's fp32).
PACK_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16, "fp32": torch.float32}


def pack_pretrained(checkpoint: str | Path, names: dict[str, str], folder: Path, *, dtype: str = "bf16") -> Path:
    """Pack a training's checkpoint as packaged weights (:mod:`detector.pretrained`): its model state dict with the
    floating-point tensors cast to ``dtype`` and its experiment config, nothing else, written to
    ``folder/<first name>.pt``; each of ``names`` (name → the packaged config to use it with, e.g. ``{"sparse":
    "mpchair_sparse_cpu", "sparse_exact": "mpchair_sparse_exact_cpu"}``) is listed in ``folder/index.json``. Returns
    the weights file."""
    if dtype not in PACK_DTYPES:
        raise InputError(f"dtype must be one of {', '.join(PACK_DTYPES)}, got {dtype!r}")
    if not names:
        raise InputError("give at least one name for the packed weights")
    saved = load_checkpoint(checkpoint)
    if saved.config is None:
        raise InputError("the checkpoint holds no experiment config; pack a detector train run's last.pt", checkpoint)
    half = {k: v.to(PACK_DTYPES[dtype]) if v.is_floating_point() else v for k, v in saved.model.items()}
    out = Path(folder) / f"{next(iter(names))}.pt"
    save_checkpoint(out, Checkpoint(model=half, config=saved.config))
    add_to_index(Path(folder), out, names)
    return out
