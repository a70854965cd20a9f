"""Training: AdamW (constant or one-cycle LR) on a KITTI-format split, reproducible, resumable and optionally
distributed (torchrun + DDP).

One run lives in one folder ``RUN``::

    RUN/config.yaml              the experiment as loaded (with --epochs applied)
    RUN/gt_database.npz          the GT-sampling database of the training split (rebuilt if the data changes)
    RUN/metrics.jsonl            one JSON object per line: {"kind": "step" | "epoch" | "eval", ...}
    RUN/checkpoints/epoch_NNN.pt after every ``train.checkpoint_every`` epochs (and the last one)
    RUN/last.pt                  the newest state (also written at --max-steps and every SAVE_INTERVAL_S seconds)

**Data order.** Epoch ``e`` draws ``samples_per_epoch`` samples (default: the split size) in a fixed order (frame
``k mod N`` for slot ``k``, every epoch the same: the reference's unshuffled loop over ``steps_per_epoch_train``
indices, each taken modulo the split) or, with ``train.shuffle``, a permutation seeded by ``(seed, e)``. Slot ``k``
is augmented with the generator ``(seed, e, k)``. Step ``s`` of the epoch takes the global batch of slots
``[s*G, (s+1)*G)`` with ``G = batch_size * world_size``; rank ``r`` takes the ``r``-th per-rank slice.

**Distributed semantics (exactly a single process with batch G).** Every BatchNorm computes its statistics over the
whole global batch (:func:`convert_to_global_batchnorm`: torch's ``SyncBatchNorm`` refuses CPU tensors, so the
project uses its own all-reduce of sums), and the losses are normalised by the number of positive anchors of the
global batch (each rank rescales its loss by ``world * max(1, pos_rank) / max(1, pos_global)`` because DDP averages
gradients). Therefore N processes × batch b and one process × batch N·b see the same statistics, losses and
gradients, up to float summation order.

**Schedule.** ``train.schedule: onecycle`` drives the learning rate and AdamW's beta1 with
``torch.optim.lr_scheduler.OneCycleLR`` over ``epochs * steps_per_epoch`` global steps (``steps_per_epoch`` counts
global batches, so a torchrun job and one process with the same global batch get the same schedule), stepped once per
optimiser step. The step records log the ``lr`` and ``beta1`` the step used.

**Resume.** A checkpoint holds the model, the optimiser, the LR scheduler, the epoch, the step within it, the global
step, the RNG states and the config. Data order and augmentation depend only on ``(seed, epoch, slot)``, so resuming at
step ``s`` replays exactly the batches an uninterrupted run would see: the weights are identical. A one-cycle run's
length is fixed when it starts: resuming it with another ``train.epochs`` (or steps per epoch) is an error.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import math
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import get_args

import numpy as np
import torch
import torch.distributed as dist
import yaml
from torch import nn
from tqdm import tqdm

from detector.checkpoint import load_checkpoint, save_checkpoint
from detector.config import Precision, experiment_from_dict
from detector.data import GTDatabase, KittiDataset, TrainingSet, build_gt_database, collate
from detector.data.experiment import augment_options, open_split
from detector.infer import evaluate_model
from detector.models import ExperimentConfig, HeadOutput, build_model, compute_loss, load_experiment
from mpchair.core.atomic import write_text
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError
from mpchair.core.lock import folder_lock
from mpchair.kitti import imageset_path

#: Seconds between mid-epoch ``last.pt`` saves (rank 0), so a long epoch interrupted late loses little work.
SAVE_INTERVAL_S = 900.0
#: Config keys that may change between a run and its resume: they do not change the trained weights. (``epochs`` only
#: with the constant schedule: it fixes the length of a one-cycle schedule, see :func:`train`.)
RESUMABLE_CHANGES = ("epochs", "num_workers", "checkpoint_every", "eval_every")
#: The start-up estimate times ESTIMATE_STEPS steps after ESTIMATE_WARMUP untimed ones (the first step of a process
#: allocates its buffers and is several times slower than the rest).
ESTIMATE_WARMUP = 1
ESTIMATE_STEPS = 3


class TrainingError(Exception):
    """Training cannot go on (e.g. a non-finite loss); the message says why and which checkpoint is intact."""


@dataclasses.dataclass(frozen=True)
class TrainResult:
    """What a finished (or ``max_steps``-stopped) run reached: completed ``epoch``s, global ``step``, final loss."""

    out_dir: Path
    epoch: int
    step: int
    last_checkpoint: Path
    last_loss: float | None


@dataclasses.dataclass(frozen=True)
class DistInfo:
    """This process's place in a torchrun job (``rank 0 of 1`` for a plain run)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


# --- distributed helpers -----------------------------------------------------------------------------------------


def dist_info_from_env() -> DistInfo:
    """Rank / world size / local rank from the variables torchrun sets (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``)."""
    return DistInfo(
        rank=int(os.environ.get("RANK", "0")),
        world_size=int(os.environ.get("WORLD_SIZE", "1")),
        local_rank=int(os.environ.get("LOCAL_RANK", "0")),
    )


def _world_active() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


class _AllReduceSum(torch.autograd.Function):
    """Differentiable sum over ranks: every rank gets the sum, and the gradient of each rank's input is the sum of
    the output gradients of all ranks (each rank's output depends on every input).

    Written here with the public ``dist.all_reduce`` because ``torch.distributed.nn.functional.all_reduce`` is
    deprecated (a FutureWarning per call site and rank) and its suggested replacement is a private module."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, tensor: torch.Tensor) -> torch.Tensor:
        out = tensor.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(out)
        return out

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor) -> torch.Tensor:
        return _AllReduceSum.apply(grad)


class _GlobalStatsBatchNorm(nn.modules.batchnorm._BatchNorm):
    """Mixin that makes a BatchNorm's training statistics span every process (see :func:`convert_to_global_batchnorm`).

    Mean and biased variance (used to normalise) come from all-reduced sums ``sum x`` and ``sum (x - mean)^2`` over
    all ranks; the all-reduce is differentiable (:class:`_AllReduceSum`), so gradients flow through the statistics
    exactly as in one process. Running buffers get the global mean and the unbiased global variance. Outside
    distributed training it is the ordinary BatchNorm.
    """

    def forward(self, input: torch.Tensor) -> torch.Tensor:
        if not (self.training and _world_active()):
            return super().forward(input)
        all_reduce = _AllReduceSum.apply
        self._check_input_dim(input)
        c = input.shape[1]
        dims = [0, *range(2, input.dim())]
        shape = [1, c] + [1] * (input.dim() - 2)
        count = input.new_tensor([input.numel() / max(c, 1)])
        sums = all_reduce(torch.cat([input.sum(dims), count]))
        n = sums[-1]
        mean = sums[:-1] / n
        centred = input - mean.view(shape)
        var = all_reduce(centred.pow(2).sum(dims)) / n
        out = centred * torch.rsqrt(var + self.eps).view(shape)
        if self.affine:
            out = out * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                m = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
                self.running_mean.mul_(1 - m).add_(mean.detach() * m)
                unbiased = var.detach() * (n / (n - 1).clamp(min=1))
                self.running_var.mul_(1 - m).add_(unbiased * m)
        return out


_GLOBAL_BN_CLASSES: dict[type, type] = {}


def convert_to_global_batchnorm(model: nn.Module) -> nn.Module:
    """Make every BatchNorm of ``model`` (incl. subclasses such as the sparse active-site BN) use global-batch
    statistics across the process group; returns ``model`` (changed in place).

    Each BN instance gets a subclass of its own class whose MRO puts :class:`_GlobalStatsBatchNorm` right before
    ``_BatchNorm``: a subclass's own ``forward`` (e.g. one that unwraps a ``SparseTensor``) still runs and reaches the
    global statistics through ``super().forward``. Parameters, buffers and ``state_dict`` keys are unchanged.
    (``torch.nn.SyncBatchNorm`` would do the same on GPUs only: it refuses CPU tensors.)
    """
    for module in model.modules():
        cls = type(module)
        if isinstance(module, nn.modules.batchnorm._BatchNorm) and not isinstance(module, _GlobalStatsBatchNorm):
            if cls not in _GLOBAL_BN_CLASSES:
                _GLOBAL_BN_CLASSES[cls] = type(f"Global{cls.__name__}", (cls, _GlobalStatsBatchNorm), {})
            module.__class__ = _GLOBAL_BN_CLASSES[cls]
    return model


def _all_reduce_sum(values: torch.Tensor) -> torch.Tensor:
    """Sum over ranks (identity in a single process)."""
    if _world_active():
        values = values.clone()
        dist.all_reduce(values)
    return values


def _barrier() -> None:
    if _world_active():
        dist.barrier()


# --- data plan -------------------------------------------------------------------------------------------------------


def epoch_frames(*, num_frames: int, samples_per_epoch: int, epoch: int, seed: int, shuffle: bool) -> np.ndarray:
    """(S,) int64 frame index of every slot of epoch ``epoch`` (see the module docstring for the rule)."""
    if shuffle:
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), int(epoch), 0x5EED])))
        reps = -(-samples_per_epoch // num_frames)
        order = np.concatenate([rng.permutation(num_frames) for _ in range(reps)])
        return order[:samples_per_epoch].astype(np.int64)
    return (np.arange(samples_per_epoch) % num_frames).astype(np.int64)


def rank_batches(
    frames: np.ndarray, *, epoch: int, global_batch: int, rank: int, per_rank: int, start_step: int
) -> list[list[tuple[int, int, int]]]:
    """Per-step lists of keys ``(epoch, slot, frame)`` for this rank, from step ``start_step`` on (last partial
    global batch dropped, so every rank runs the same number of steps)."""
    steps = len(frames) // global_batch
    out = []
    for s in range(start_step, steps):
        slots = range(s * global_batch + rank * per_rank, s * global_batch + (rank + 1) * per_rank)
        out.append([(epoch, k, int(frames[k])) for k in slots])
    return out


class _SlotDataset(torch.utils.data.Dataset):
    """Keys ``(epoch, slot, frame)`` → the augmented sample; slot ``k`` is augmented with generator (seed, epoch, k)."""

    def __init__(self, base: TrainingSet) -> None:
        self.base = base

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, key: tuple[int, int, int]):
        epoch, slot, frame = key
        return self.base.sample(epoch, slot, frame)


def load_or_build_database(frames: KittiDataset, path: Path, *, progress: bool) -> tuple[GTDatabase, bool]:
    """The GT database of ``frames`` as cached at ``path``, or built anew when the split, classes or options differ
    (then ``True``: the caller saves it, once the run may write)."""
    meta = {
        "root": str(frames.root.resolve()),
        "split": frames.split,
        "ids": frames.ids,
        "classes": list(frames.classes),
        "name_map": frames.name_map,
        "fov_crop": frames.fov_crop,
    }
    if path.is_file():
        try:
            db = GTDatabase.load(path)
            if db.meta == json.loads(json.dumps(meta)):
                return db, False
        except InputError:
            pass  # a damaged cache is rebuilt
    return build_gt_database(frames, meta=meta, progress=progress), True


# --- checkpoints ------------------------------------------------------------------------------------------------------


def _unwrap(model: nn.Module) -> nn.Module:
    return model.module if isinstance(model, nn.parallel.DistributedDataParallel) else model


def _comparable(cfg_dict: dict) -> dict:
    # Through the dataclasses first, so a checkpoint written before a key existed compares with its default.
    d = json.loads(json.dumps(to_dict(experiment_from_dict(cfg_dict))))
    for key in RESUMABLE_CHANGES:
        d.get("train", {}).pop(key, None)
    return d


def _read_metrics(path: Path, max_step: int) -> list[str]:
    """Lines of ``metrics.jsonl`` up to global step ``max_step`` (a torn last line from a crash is dropped)."""
    if not path.is_file():
        return []
    kept = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if int(rec.get("step", 0)) <= max_step:
            kept.append(line)
    return kept


def _has_eval(lines: list[str], epoch: int) -> bool:
    """Whether the metrics ``lines`` hold the evaluation record of ``epoch``."""
    for line in lines:
        rec = json.loads(line)
        if rec.get("kind") == "eval" and rec.get("epoch") == epoch:
            return True
    return False


def _remove_stale_temps(out: Path) -> None:
    """Delete temp files (``.<name>.<random>.tmp``) a killed run left in the run folder (the caller holds its lock)."""
    for p in out.rglob(".*.tmp"):
        if p.is_file():
            p.unlink(missing_ok=True)


# --- the loop --------------------------------------------------------------------------------------------------------


def _resolve_device(device: str, info: DistInfo) -> torch.device:
    if device == "cpu":
        return torch.device("cpu")
    if device == "cuda":
        if not torch.cuda.is_available():
            raise InputError("--device cuda: no CUDA device is available")
        return torch.device("cuda", info.local_rank if info.distributed else torch.cuda.current_device())
    raise InputError(f"unknown device {device!r} (cpu or cuda)")


def build_scheduler(optimizer: torch.optim.Optimizer, cfg: ExperimentConfig,
                    total_steps: int) -> torch.optim.lr_scheduler.LRScheduler | None:
    """The LR scheduler of ``train.schedule`` over ``total_steps`` global optimiser steps (None: constant LR).

    ``onecycle``: ``OneCycleLR`` with ``max_lr = train.lr``, cosine annealing, and AdamW's beta1 cycled from
    ``beta1_range[0]`` down to ``beta1_range[1]`` at the peak and back (OpenPCDet's ``adam_onecycle``). Creating it
    sets the optimiser's lr and beta1 to their step-0 values. A run without steps (``total_steps == 0``) gets None.
    """
    tc = cfg.train
    if tc.schedule == "constant" or total_steps == 0:
        return None
    return torch.optim.lr_scheduler.OneCycleLR(
        optimizer, max_lr=tc.lr, total_steps=total_steps, pct_start=tc.pct_start, anneal_strategy="cos",
        cycle_momentum=True, max_momentum=tc.beta1_range[0], base_momentum=tc.beta1_range[1],
        div_factor=tc.div_factor, final_div_factor=tc.final_div_factor, three_phase=False)


def _batches(keys: list[list[tuple[int, int, int]]], base: TrainingSet, workers: int) -> Iterator:
    if not keys:
        return iter(())
    loader = torch.utils.data.DataLoader(
        _SlotDataset(base), batch_sampler=keys, collate_fn=collate, num_workers=workers
    )
    return iter(loader)


def train(
    config_path: str | Path,
    data_dir: str | Path,
    out_dir: str | Path,
    *,
    epochs: int | None = None,
    precision: str | None = None,
    resume: bool = False,
    max_steps: int | None = None,
    device: str = "cpu",
    threads: int | None = None,
    split: str = "train",
    eval_split: str = "val",
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> TrainResult:
    """Train the experiment ``config_path`` on ``data_dir`` (KITTI layout) into the run folder ``out_dir``.

    ``epochs`` overrides ``train.epochs`` and ``precision`` ``train.precision``; ``max_steps`` stops after that many
    global steps (counted over the whole run, resumed parts included) and saves ``last.pt``; ``resume`` continues
    from ``out_dir/last.pt`` (a fresh start if there is none). Under torchrun (``WORLD_SIZE`` > 1) the process group
    is joined here (gloo on CPU, nccl on CUDA). ``log`` receives the lines meant for a person, on rank 0 only: the
    plan and, after the first few steps, the expected duration (steps x measured seconds per step), one line per
    epoch (mean loss, time) and one per validation (AP). Raises :class:`InputError` for bad input and
    :class:`TrainingError` for a non-finite loss or gradient (no checkpoint is written for the failing step).
    """
    info = dist_info_from_env()
    if threads is not None:
        if threads < 1:
            raise InputError(f"--threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)
    dev = _resolve_device(device, info)
    if max_steps is not None and max_steps < 0:
        raise InputError(f"--max-steps must be >= 0, got {max_steps}")
    if epochs is not None and epochs < 0:
        raise InputError(f"--epochs must be >= 0, got {epochs}")
    cfg = load_experiment(config_path)
    if epochs is not None:
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, epochs=epochs))
    if precision is not None:
        if precision not in get_args(Precision):
            raise InputError(f"--precision must be one of {', '.join(get_args(Precision))}, got {precision!r}")
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, precision=precision))
    tc = cfg.train
    if tc.precision == "bf16" and dev.type == "cuda" and not torch.cuda.is_bf16_supported():
        raise InputError(f"train.precision bf16: {torch.cuda.get_device_name(dev)} has no bfloat16 support; use fp32",
                         config_path)
    out = Path(out_dir)
    last_path = out / "last.pt"
    state = None
    if last_path.is_file():
        if not resume:
            raise InputError(f"{out} already holds a run (last.pt); pass --resume to continue it or pick a new --out")
        state = load_checkpoint(last_path)
        if _comparable(state["config"]) != _comparable(to_dict(cfg)):
            raise InputError(f"the config differs from the one {last_path} was trained with (only "
                             f"{', '.join('train.' + k for k in RESUMABLE_CHANGES)} may change on resume)", config_path)
    frames = open_split(cfg, data_dir, split)
    global_batch = tc.batch_size * info.world_size
    samples_per_epoch = tc.samples_per_epoch or len(frames)
    steps_per_epoch = samples_per_epoch // global_batch
    if steps_per_epoch == 0:
        raise InputError(f"split {split!r} gives {samples_per_epoch} samples per epoch, fewer than one global batch "
                         f"({tc.batch_size} x {info.world_size} processes)")
    if state is not None and state["global_batch"] != global_batch:
        raise InputError(f"{last_path} was trained with global batch {state['global_batch']}, this run has "
                         f"{global_batch} (batch_size x processes must stay the same to resume)")
    # The schedule spans the run's global steps: steps_per_epoch counts global batches, so it is the same number in a
    # torchrun job and in one process with the same global batch.
    total_steps = tc.epochs * steps_per_epoch
    if tc.schedule == "onecycle":
        if 0 < total_steps and tc.pct_start * total_steps <= 1:
            raise InputError(f"train.pct_start x total steps = {tc.pct_start} x {total_steps} must exceed 1: the "
                             "one-cycle warm-up needs more than one step (raise train.epochs or pct_start)",
                             config_path)
        saved = None if state is None else (state.get("scheduler") or {}).get("total_steps")
        if state is not None and saved != total_steps:
            raise InputError(f"{last_path} follows a one-cycle schedule over {saved} steps; this run would have "
                             f"{total_steps} (train.epochs {tc.epochs} x {steps_per_epoch} steps per epoch). The "
                             "schedule's length is fixed when a run starts: resume with the original train.epochs "
                             "/ --epochs and split, or start a new run", config_path)
    # Every frame's files are checked (and the GT database built in memory) before the run writes anything.
    frames.check()
    if tc.eval_every > 0 and imageset_path(data_dir, eval_split).is_file():
        open_split(cfg, data_dir, eval_split).check()
    database, new_database = None, False
    if cfg.data.gt_sampling.enabled and info.is_main:
        database, new_database = load_or_build_database(frames, out / "gt_database.npz",
                                                        progress=progress and info.is_main)

    if info.distributed and not dist.is_initialized():
        backend = "nccl" if dev.type == "cuda" else "gloo"
        if dev.type == "cuda":
            torch.cuda.set_device(dev)
        # Rank 0 may evaluate or build the GT database while the others wait at a barrier: allow hours, not minutes.
        dist.init_process_group(backend=backend, timeout=datetime.timedelta(hours=6))
    try:
        # One process per run folder (rank 0 writes for the job); the kernel drops the lock of a killed run.
        with folder_lock(out / ".train.lock", "detector train") if info.is_main else contextlib.nullcontext():
            return _train_loop(cfg, frames, out, dev, info, state, max_steps=max_steps, global_batch=global_batch,
                               steps_per_epoch=steps_per_epoch, samples_per_epoch=samples_per_epoch,
                               total_steps=total_steps, data_dir=data_dir, eval_split=eval_split, progress=progress,
                               database=database, new_database=new_database, report=log)
    finally:
        if info.distributed and dist.is_initialized():
            dist.destroy_process_group()


def _train_loop(cfg: ExperimentConfig, frames: KittiDataset, out: Path, dev: torch.device, info: DistInfo,
                state: dict | None, *, max_steps: int | None, global_batch: int, steps_per_epoch: int,
                samples_per_epoch: int, total_steps: int, data_dir: str | Path, eval_split: str,
                progress: bool, database: GTDatabase | None, new_database: bool,
                report: Callable[[str], None] | None = None) -> TrainResult:
    tc = cfg.train
    show = progress and info.is_main

    def say(line: str) -> None:
        if report is not None and info.is_main:
            report(line)

    db_path = out / "gt_database.npz"
    if info.is_main:
        _remove_stale_temps(out)
        write_text(out / "config.yaml", yaml.safe_dump(to_dict(cfg), sort_keys=False))
        if new_database:
            database.save(db_path)
    options = augment_options(cfg)
    if options.gt_sampling:
        _barrier()
        if not info.is_main:
            database = GTDatabase.load(db_path)
    base = TrainingSet(frames, options, seed=tc.seed, database=database)

    torch.manual_seed(tc.seed)  # identical initial weights on every rank (DDP also broadcasts rank 0's)
    model = build_model(cfg.model).to(dev)
    if info.distributed:
        convert_to_global_batchnorm(model)
    optimizer = torch.optim.AdamW(model.parameters(), lr=tc.lr, betas=tc.betas, weight_decay=tc.weight_decay)
    # Built before the optimiser state is loaded: its constructor resets lr / beta1 to step 0, the loaded param groups
    # then restore the values of the checkpoint's step.
    scheduler = build_scheduler(optimizer, cfg, total_steps)
    epoch, step_in_epoch, step = 0, 0, 0
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        if scheduler is not None:
            scheduler.load_state_dict(state["scheduler"])
        epoch, step_in_epoch, step = int(state["epoch"]), int(state["step_in_epoch"]), int(state["step"])
        torch.set_rng_state(state["rng"]["torch"])
        if state["rng"]["cuda"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["rng"]["cuda"])
    ddp = model
    if info.distributed:
        ddp = nn.parallel.DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None)

    metrics_path = out / "metrics.jsonl"
    logged: list[str] = []
    if info.is_main:
        # Drop log lines past the checkpoint (written after it by an interrupted run), so the log replays cleanly.
        logged = _read_metrics(metrics_path, step)
        write_text(metrics_path, "".join(line + "\n" for line in logged))
    log = open(metrics_path, "a", encoding="utf-8") if info.is_main else None  # noqa: SIM115 (closed below)

    def emit(record: dict) -> None:
        if log is not None:
            try:
                log.write(json.dumps(record) + "\n")
                log.flush()
            except OSError as e:
                e.filename = e.filename or str(metrics_path)
                raise

    def evaluate() -> None:
        """The end-of-epoch evaluation (rank 0; the others wait)."""
        if info.is_main:
            t_eval = time.perf_counter()
            result = _evaluate_during_training(model, cfg, data_dir, eval_split, out, epoch, dev, show)
            if result is not None:
                emit({"kind": "eval", "epoch": epoch, "step": step, "split": eval_split, **result})
                say(f"epoch {epoch}/{tc.epochs} validation on {eval_split}: {_ap_text(result, cfg.eval.classes)}, "
                    f"{format_duration(time.perf_counter() - t_eval)}")
        _barrier()

    # A run stopped during an epoch's evaluation resumes from that epoch's end: evaluate those weights first. (Rank 0
    # decides from its log; the others follow, so that every rank meets the same barriers.)
    redo = (info.is_main and state is not None and step_in_epoch == 0 and epoch > 0 and tc.eval_every > 0
            and epoch % tc.eval_every == 0 and not _has_eval(logged, epoch))
    if _all_reduce_sum(torch.tensor([float(redo)], device=dev))[0] > 0:
        evaluate()

    def checkpoint(path: Path) -> None:
        if info.is_main:
            save_checkpoint(path, model=model, optimizer=optimizer, cfg=cfg, epoch=epoch,
                            step_in_epoch=step_in_epoch, step=step, global_batch=global_batch, scheduler=scheduler)

    params = [p for p in model.parameters() if p.requires_grad]
    last_loss = None
    last_save = time.monotonic()
    stopped = False
    first_step = step
    end_step = total_steps if max_steps is None else min(total_steps, max(max_steps, step))
    todo = end_step - first_step
    say(f"training {todo} step(s): {tc.epochs} epochs x {steps_per_epoch} steps (global batch {global_batch})"
        + (f", resumed at step {step}" if step else "")
        + (f", stopping at --max-steps {max_steps}" if end_step < total_steps else "")
        + ("; timing the first steps..." if todo > ESTIMATE_WARMUP + ESTIMATE_STEPS else ""))
    # wall clock at the end of step ESTIMATE_WARMUP of this process (data loading, checkpoints included)
    t_timed: float | None = None
    try:
        while epoch < tc.epochs:
            if max_steps is not None and step >= max_steps:
                stopped = True
                break
            frame_order = epoch_frames(num_frames=len(frames), samples_per_epoch=samples_per_epoch, epoch=epoch,
                                       seed=tc.seed, shuffle=tc.shuffle)
            keys = rank_batches(frame_order, epoch=epoch, global_batch=global_batch, rank=info.rank,
                                per_rank=tc.batch_size, start_step=step_in_epoch)
            ddp.train()
            # leave=False: the epoch's line (below) replaces its finished bar
            bar = tqdm(total=steps_per_epoch, initial=step_in_epoch, desc=f"epoch {epoch + 1}/{tc.epochs}",
                       unit="step", disable=not show, dynamic_ncols=True, leave=False)
            sums = {"total": 0.0, "cls": 0.0, "reg": 0.0, "dir": 0.0}
            n_steps = 0
            t_epoch = time.perf_counter()
            for batch in _batches(keys, base, tc.num_workers):
                if max_steps is not None and step >= max_steps:
                    stopped = True
                    break
                t0 = time.perf_counter()
                batch = batch.to(dev)
                with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=tc.precision == "bf16"):
                    preds = ddp(list(batch.points))
                preds = HeadOutput(*(p.float() for p in preds))  # losses in fp32 (a no-op for fp32 training)
                raw = _unwrap(ddp)
                targets = raw.targets(list(batch.boxes), list(batch.labels))
                losses = compute_loss(preds, targets, num_classes=raw.num_classes, **raw.loss_params)
                # Re-normalise by the positives of the whole global batch (see the module docstring).
                pos_rank = targets.pos.sum().to(torch.float64)
                pos_global = _all_reduce_sum(pos_rank.detach().reshape(1))[0]
                own = pos_rank.clamp(min=1)
                scale = (own / pos_global.clamp(min=1)).to(preds.cls.dtype)
                loss = losses["total"] * scale * info.world_size
                logged = _all_reduce_sum(torch.stack([losses[k].detach() * scale for k in sums]).to(torch.float64))
                values = dict(zip(sums, logged.tolist()))
                if not math.isfinite(values["total"]):
                    raise TrainingError(
                        f"non-finite loss ({values['total']}) at epoch {epoch + 1}, step {step + 1} (frames "
                        f"{', '.join(batch.frame_ids)}); training stopped, {out / 'last.pt'} keeps the last good "
                        "state. Check the data for NaN/inf values or lower train.lr")
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                max_norm = tc.grad_clip_norm if tc.grad_clip_norm is not None else math.inf
                grad_norm = float(torch.nn.utils.clip_grad_norm_(params, max_norm))
                if not math.isfinite(grad_norm):
                    raise TrainingError(
                        f"non-finite gradient norm at epoch {epoch + 1}, step {step + 1}; training stopped, "
                        f"{out / 'last.pt'} keeps the last good state. Lower train.lr or enable train.grad_clip_norm")
                lr, beta1 = optimizer.param_groups[0]["lr"], optimizer.param_groups[0]["betas"][0]
                optimizer.step()
                if scheduler is not None and step + 1 < total_steps:
                    scheduler.step()  # not past the last step, so a finished run keeps the final lr
                step += 1
                step_in_epoch += 1
                n_steps += 1
                last_loss = values["total"]
                for k in sums:
                    sums[k] += values[k]
                emit({"kind": "step", "epoch": epoch + 1, "step": step, **{f"loss_{k}": v for k, v in values.items()},
                      "grad_norm": grad_norm, "num_pos": int(pos_global), "lr": lr, "beta1": beta1,
                      "time_s": round(time.perf_counter() - t0, 4)})
                if step - first_step == ESTIMATE_WARMUP:
                    t_timed = time.perf_counter()
                elif (step - first_step == ESTIMATE_WARMUP + ESTIMATE_STEPS and t_timed is not None
                      and todo > ESTIMATE_WARMUP + ESTIMATE_STEPS):
                    per_step = (time.perf_counter() - t_timed) / ESTIMATE_STEPS
                    validation = (f" (+ validation on {eval_split} every {tc.eval_every} epochs)"
                                  if tc.eval_every > 0 and imageset_path(data_dir, eval_split).is_file() else "")
                    say(f"{todo} steps, ~{per_step:.2f} s/step measured -> ~{format_duration(per_step * todo)}"
                        + validation)
                bar.update(1)
                bar.set_postfix(loss=f"{values['total']:.4f}")
                if info.is_main and time.monotonic() - last_save > SAVE_INTERVAL_S:
                    checkpoint(out / "last.pt")
                    last_save = time.monotonic()
            bar.close()
            if stopped or step_in_epoch < steps_per_epoch:
                stopped = True  # --max-steps hit inside the epoch
                break
            epoch += 1
            step_in_epoch = 0
            epoch_s = time.perf_counter() - t_epoch
            means = {k: v / max(n_steps, 1) for k, v in sums.items()}
            emit({"kind": "epoch", "epoch": epoch, "step": step, "steps": n_steps,
                  **{f"loss_{k}": v for k, v in means.items()}, "time_s": round(epoch_s, 3)})
            say(f"epoch {epoch}/{tc.epochs}: loss {means['total']:.4f} (cls {means['cls']:.4f}, reg "
                f"{means['reg']:.4f}, dir {means['dir']:.4f}), {n_steps} steps in {format_duration(epoch_s)}, "
                f"step {step}/{total_steps}")
            if epoch % max(tc.checkpoint_every, 1) == 0 or epoch == tc.epochs:
                checkpoint(out / "checkpoints" / f"epoch_{epoch:03d}.pt")
            checkpoint(out / "last.pt")
            last_save = time.monotonic()
            if tc.eval_every > 0 and epoch % tc.eval_every == 0:
                evaluate()
        if stopped:
            checkpoint(out / "last.pt")
    finally:
        if log is not None:
            log.close()
    _barrier()
    return TrainResult(out_dir=out, epoch=epoch, step=step, last_checkpoint=out / "last.pt", last_loss=last_loss)


def format_duration(seconds: float) -> str:
    """``"42 s"``, ``"12 min"`` or ``"3.4 h"``: a duration as a person reads it."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _ap_text(result: dict, classes: tuple[str, ...]) -> str:
    """``"Chair BEV AP 12.34, 3D AP 5.67"`` (R40, Overall level) of a KITTI result's JSON dict."""
    parts = [f"{c} BEV AP {result[c]['bev']['overall']['R40']:.2f}, 3D AP {result[c]['3d']['overall']['R40']:.2f}"
             for c in classes if c in result]
    return "; ".join(parts) + " (R40, Overall)"


def _evaluate_during_training(model: nn.Module, cfg: ExperimentConfig, data_dir: str | Path, split: str, out: Path,
                              epoch: int, dev: torch.device, progress: bool) -> dict | None:
    """AP of the current weights on ``split`` (None when the dataset has no such split); results under RUN/eval/."""
    if not imageset_path(data_dir, split).is_file():
        return None
    was_training = model.training
    try:
        result = evaluate_model(model, cfg, data_dir, split, out / "eval" / f"epoch_{epoch:03d}", device=dev,
                                progress=progress)
    finally:
        model.train(was_training)
    return result.to_json_dict()

