"""``train()``: the orchestrator of a run (arguments → experiment → plan and checks → process group and folder lock →
model, metrics log, epochs) and the epoch loop (steps, records, checkpoints, periodic evaluation).

Only rank 0 writes (run files, ``metrics.jsonl``, checkpoints) and evaluates; the others wait at barriers. Which
samples a step sees: :mod:`detector.train.data_order`; one step: :mod:`detector.train.step`; what a resume restores
and refuses: :mod:`detector.train.resume`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import NamedTuple, get_args

import torch
from torch import nn
from tqdm import tqdm

from detector.checkpoint import Checkpoint, save_checkpoint
from detector.config import ExperimentConfig, Precision, experiment_from_dict, load_experiment
from detector.data import GTDatabase, KittiDataset, TrainingSet
from detector.data.experiment import augment_options, open_split
from detector.device import pin_memory
from detector.infer import evaluate_model
from detector.models import Losses, build_model
from detector.train.data_order import epoch_frames, rank_batches, rank_loader
from detector.train.distributed import (
    DistInfo,
    all_reduce_sum,
    barrier,
    convert_to_global_batchnorm,
    dist_info_from_env,
    process_group,
    resolve_device,
)
from detector.train.metrics import (
    ZERO_LOSSES,
    DurationEstimate,
    MetricsLog,
    add_losses,
    epoch_line,
    estimate_line,
    long_run_warning,
    mean_losses,
    plan_line,
    validation_line,
)
from detector.train.plateau import PlateauState, plateau_lr, plateau_state, tracked_ap
from detector.train.resume import (
    Position,
    check_global_batch,
    check_schedule_length,
    ends_an_evaluated_epoch,
    read_resume_checkpoint,
    restore,
)
from detector.train.run_folder import (
    DATABASE_FILE,
    check_run_folder,
    discard_start,
    load_or_build_database,
    missing_folders,
    remove_empty_folders,
    shared_database,
    write_run_files,
)
from detector.train.schedule import build_scheduler, check_warmup
from detector.train.step import ModelAndOptimiser, StepSettings, TrainingError, train_step
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError
from mpchair.core.lock import folder_lock
from mpchair.kitti import imageset_path

#: Seconds between mid-epoch ``last.pt`` saves (rank 0), so a long epoch interrupted late loses little work.
SAVE_INTERVAL_S = 900.0


@dataclasses.dataclass(frozen=True)
class TrainResult:
    """What a finished (or ``max_steps`` / ``max_minutes``-stopped) run reached: completed ``epoch``s, global
    ``step``, final loss, and why it ended: ``epochs`` (the cap), ``plateau`` (the plateau schedule's rule),
    ``max-steps`` or ``time`` (stopped early, resumable)."""

    out_dir: Path
    epoch: int
    step: int
    last_checkpoint: Path
    last_loss: float | None
    ended_by: str = "epochs"

    @property
    def finished(self) -> bool:
        """Whether the run is complete (not cut by ``max_steps`` or ``max_minutes``)."""
        return self.ended_by in ("epochs", "plateau")


@dataclasses.dataclass(frozen=True)
class RunPlan:
    """What the epoch loop needs, fixed for the whole run: the experiment, the training split, the run folder, this
    process's device and rank, the step counts (``steps_per_epoch`` and ``total_steps`` count global batches of
    ``global_batch`` samples), ``max_steps`` (None: no limit), the split evaluated during training, whether to show
    progress bars, and ``report``, which receives the lines meant for a person (rank 0 only)."""

    cfg: ExperimentConfig
    frames: KittiDataset
    out: Path
    device: torch.device
    info: DistInfo
    global_batch: int
    samples_per_epoch: int
    steps_per_epoch: int
    total_steps: int
    max_steps: int | None
    #: ``time.monotonic()`` after which the run saves and stops at the next step (None: no limit)
    deadline: float | None
    data_dir: Path
    eval_split: str
    progress: bool
    report: Callable[[str], None] | None

    @property
    def last_path(self) -> Path:
        return self.out / "last.pt"

    @property
    def show_bars(self) -> bool:
        return self.progress and self.info.is_main

    @property
    def validates(self) -> bool:
        """Whether the run evaluates during training (``train.eval_every`` > 0 and the dataset has the split)."""
        return self.cfg.train.eval_every > 0 and imageset_path(self.data_dir, self.eval_split).is_file()

    def reached_max_steps(self, step: int) -> bool:
        return self.max_steps is not None and step >= self.max_steps

    def out_of_time(self) -> bool:
        """Whether ``max_minutes`` has run out (checked between steps, the same answer on every rank)."""
        if self.deadline is None:
            return False
        late = float(time.monotonic() >= self.deadline)
        return all_reduce_sum(torch.tensor([late], device=self.device))[0].item() > 0

    def say(self, line: str) -> None:
        """Hand one line meant for a person to ``report`` (rank 0 only)."""
        if self.report is not None and self.info.is_main:
            self.report(line)


def train(
    config: str | Path | ExperimentConfig,
    data_dir: str | Path,
    out_dir: str | Path,
    *,
    epochs: int | None = None,
    precision: str | None = None,
    resume: bool = False,
    max_steps: int | None = None,
    max_minutes: float | None = None,
    device: str = "cpu",
    threads: int | None = None,
    split: str = "train",
    eval_split: str = "val",
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    overrides: Mapping | None = None,
) -> TrainResult:
    """Train the experiment ``config`` on ``data_dir`` (KITTI layout) into the run folder ``out_dir``.

    ``config`` is a YAML path, a packaged config's name or an :class:`ExperimentConfig` built in memory (checked like
    a file); ``overrides`` (a nested mapping like the YAML's) goes on top of a path or name (:func:`load_experiment`).
    ``epochs`` overrides ``train.epochs`` and ``precision`` ``train.precision``; ``max_steps`` stops after that many
    global steps (counted over the whole run, resumed parts included) and saves ``last.pt``, ``max_minutes`` does the
    same after that much wall time (at the next step boundary); ``resume`` continues
    from ``out_dir/last.pt`` (a fresh start if there is none). Under torchrun (``WORLD_SIZE`` > 1) the process group
    is joined here (gloo on CPU, nccl on CUDA). ``log`` receives the lines meant for a person, on rank 0 only: the
    plan and, after the first few steps, the expected duration (steps x measured seconds per step), one line per
    epoch (mean loss, time) and one per validation (AP). Raises :class:`InputError` for bad input and
    :class:`~detector.train.step.TrainingError` for a non-finite loss or gradient (no checkpoint is written for the
    failing step).
    """
    info = dist_info_from_env()
    if threads is not None:
        if threads < 1:
            raise InputError(f"--threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)
    dev = resolve_device(device, info)
    if max_steps is not None and max_steps < 0:
        raise InputError(f"--max-steps must be >= 0, got {max_steps}")
    if epochs is not None and epochs < 0:
        raise InputError(f"--epochs must be >= 0, got {epochs}")
    if max_minutes is not None and not (math.isfinite(max_minutes) and max_minutes > 0):
        raise InputError(f"--max-minutes must be a finite number > 0, got {max_minutes}")
    deadline = None if max_minutes is None else time.monotonic() + 60.0 * max_minutes
    config_path = str(config) if not isinstance(config, ExperimentConfig) else "<experiment in memory>"
    cfg = _experiment(config, overrides, epochs=epochs, precision=precision, device=dev)
    out = Path(out_dir)
    check_run_folder(out)  # a non-empty folder that is not a run is never taken over
    checkpoint = read_resume_checkpoint(out / "last.pt", cfg, resume=resume, config_path=config_path)
    frames = open_split(cfg, data_dir, split)
    tc = cfg.train
    global_batch = tc.batch_size * info.world_size
    samples_per_epoch = tc.samples_per_epoch or len(frames)
    run = RunPlan(cfg=cfg, frames=frames, out=out, device=dev, info=info, global_batch=global_batch,
                  samples_per_epoch=samples_per_epoch, steps_per_epoch=samples_per_epoch // global_batch,
                  # The schedule spans the run's global steps: steps_per_epoch counts global batches, so it is the
                  # same number in a torchrun job and in one process with the same global batch.
                  total_steps=tc.epochs * (samples_per_epoch // global_batch), max_steps=max_steps, deadline=deadline,
                  data_dir=Path(data_dir), eval_split=eval_split, progress=progress, report=log)
    _check_plan(run, checkpoint, split=split, config_path=config_path)
    # Every frame's files are checked (and the GT database built in memory) before the run writes anything.
    frames.check()
    if run.validates:
        open_split(cfg, data_dir, eval_split).check()
    database, new_database = None, False
    if cfg.data.gt_sampling.enabled and info.is_main:
        database, new_database = load_or_build_database(frames, out / DATABASE_FILE, progress=progress)
    made = missing_folders(out)
    new_run = checkpoint is None and (bool(made) or not any(out.iterdir()))
    # The stack's callbacks run last, once the lock below is released (its file removed from the folder).
    with contextlib.ExitStack() as after_lock, process_group(info, dev):
        # One process per run folder (rank 0 writes for the job); the kernel drops the lock of a killed run.
        with folder_lock(out / ".train.lock", "detector train") if info.is_main else contextlib.nullcontext():
            try:
                return _run(run, checkpoint, database, new_database)
            except (InputError, TrainingError):
                # Bad input only the loader meets (a NaN in a scan), or a loss that went non-finite (lr 1e30): a new
                # run with no checkpoint yet leaves nothing, as its error line says (its files now, under the lock;
                # the folders it made once the lock file is gone).
                if info.is_main and new_run and not run.last_path.exists():
                    discard_start(out)
                    after_lock.callback(remove_empty_folders, made)
                raise


def _experiment(config: str | Path | ExperimentConfig, overrides: Mapping | None, *, epochs: int | None,
                precision: str | None, device: torch.device) -> ExperimentConfig:
    """The experiment of ``config`` (+ ``overrides``) with ``--epochs`` / ``--precision`` applied (bf16 refused on a
    CUDA device without it)."""
    if isinstance(config, ExperimentConfig):
        if overrides:
            raise InputError("overrides apply to a config file or name; change an in-memory experiment directly")
        config_path = "<experiment in memory>"
        cfg = experiment_from_dict(to_dict(config), source=config_path)  # the same checks as a file gets
    else:
        config_path = str(config)
        cfg = load_experiment(config, overrides)
    if epochs is not None:
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, epochs=epochs))
    if precision is not None:
        if precision not in get_args(Precision):
            raise InputError(f"--precision must be one of {', '.join(get_args(Precision))}, got {precision!r}")
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, precision=precision))
    if cfg.train.precision == "bf16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
        raise InputError(f"train.precision bf16: {torch.cuda.get_device_name(device)} has no bfloat16 support; use "
                         "fp32", config_path)
    return cfg


def _check_plan(run: RunPlan, checkpoint: Checkpoint | None, *, split: str, config_path: str | Path) -> None:
    """Refuse a split smaller than one global batch, a one-cycle warm-up of one step or less, and a checkpoint whose
    global batch or one-cycle length differs from this run's."""
    tc = run.cfg.train
    if run.steps_per_epoch == 0:
        raise InputError(f"split {split!r} gives {run.samples_per_epoch} samples per epoch, fewer than one global "
                         f"batch ({tc.batch_size} x {run.info.world_size} processes)")
    if checkpoint is not None:
        check_global_batch(checkpoint, run.last_path, run.global_batch)
    check_warmup(run.cfg, run.total_steps, config_path)
    if checkpoint is not None:
        check_schedule_length(checkpoint, run.last_path, run.cfg, total_steps=run.total_steps,
                              steps_per_epoch=run.steps_per_epoch, config_path=config_path)


def _run(run: RunPlan, checkpoint: Checkpoint | None, database: GTDatabase | None,
         new_database: bool) -> TrainResult:
    """The run inside its folder lock (and process group): run files, model and optimiser, metrics log, epochs."""
    cfg, info = run.cfg, run.info
    if info.is_main:
        write_run_files(run.out, cfg, database, new_database)
    options = augment_options(cfg)
    database = shared_database(run.out, info, database, gt_sampling=options.gt_sampling)
    base = TrainingSet(run.frames, options, seed=cfg.train.seed, database=database)
    parts, at = _model_and_optimiser(run, checkpoint)
    with MetricsLog(run.out / "metrics.jsonl", step=at.step, writes=info.is_main) as log:
        # A run stopped during an epoch's evaluation resumes from that epoch's end: evaluate those weights first.
        # (Rank 0 decides from its log; the others follow, so that every rank meets the same barriers.)
        redo = (info.is_main and checkpoint is not None and ends_an_evaluated_epoch(cfg, at)
                and not log.has_eval(at.epoch))
        if all_reduce_sum(torch.tensor([float(redo)], device=run.device))[0] > 0:
            _evaluate(run, parts.model, at, log)
        at, last_loss, ended_by = _train_epochs(run, parts, base, at, log)
    barrier()
    return TrainResult(out_dir=run.out, epoch=at.epoch, step=at.step, last_checkpoint=run.last_path,
                       last_loss=last_loss, ended_by=ended_by)


def _model_and_optimiser(run: RunPlan, checkpoint: Checkpoint | None) -> tuple[ModelAndOptimiser, Position]:
    """The seeded model, AdamW and the LR scheduler, restored from ``checkpoint`` when resuming (DDP-wrapped under
    torchrun), and the position the run starts at."""
    tc = run.cfg.train
    torch.manual_seed(tc.seed)  # identical initial weights on every rank (DDP also broadcasts rank 0's)
    model = build_model(run.cfg.model).to(run.device)
    if run.info.distributed:
        convert_to_global_batchnorm(model)
    # fused: one kernel over every parameter instead of torch's foreach ops, the same update up to float rounding;
    # 4.98 -> 2.73 ms per step for these models' 4.6 M parameters at 2 CPU threads (2-core EPYC, torch 2.13, a one-off
    # timing loop; the train-step effect: tools/bench_train_step.py), a cost both models pay alike (docs/training.md,
    # "Speed on CPU")
    optimizer = torch.optim.AdamW(model.parameters(), lr=tc.lr, betas=tc.betas, weight_decay=tc.weight_decay,
                                  fused=True)
    # Built before the optimiser state is loaded: its constructor resets lr / beta1 to step 0, the loaded param groups
    # then restore the values of the checkpoint's step.
    scheduler = build_scheduler(optimizer, run.cfg, run.total_steps)
    at = Position() if checkpoint is None else restore(checkpoint, model, optimizer, scheduler)
    ddp = model
    if run.info.distributed:
        ddp = nn.parallel.DistributedDataParallel(
            model, device_ids=[run.device.index] if run.device.type == "cuda" else None)
    params = [p for p in model.parameters() if p.requires_grad]
    return ModelAndOptimiser(model=model, ddp=ddp, optimizer=optimizer, scheduler=scheduler, params=params), at


class _SaveClock:
    """When the next mid-epoch ``last.pt`` is due: ``SAVE_INTERVAL_S`` seconds after the last save."""

    def __init__(self) -> None:
        self._last = time.monotonic()

    def due(self) -> bool:
        return time.monotonic() - self._last > SAVE_INTERVAL_S

    def saved(self) -> None:
        self._last = time.monotonic()


class _EpochPart(NamedTuple):
    """What :func:`_train_epoch` ran: the position after it, the summed step losses, the steps, the seconds, whether
    ``max_steps`` stopped it inside the epoch, and the last step's loss (None: no step)."""

    at: Position
    sums: Losses
    steps: int
    seconds: float
    stopped: bool
    last_loss: float | None


def _plateau(run: RunPlan, log: MetricsLog) -> PlateauState | None:
    """The plateau rule's state after the evaluated epochs in ``log`` (None: another schedule). Rank 0 decides from
    its log; the other ranks receive its decision."""
    tc = run.cfg.train
    if tc.schedule != "plateau":
        return None
    aps = [tracked_ap(log.evals[e], run.cfg.eval.classes) for e in range(1, len(log.evals) + 1) if e in log.evals]
    state = plateau_state(aps, tc)
    if run.info.distributed:
        mine = torch.tensor([float(state.decays), float(state.stopped_at or 0)], device=run.device)
        decided = all_reduce_sum(mine if run.info.is_main else torch.zeros_like(mine))
        stopped = int(decided[1].item())
        state = PlateauState(decays=int(decided[0].item()), decay_epochs=state.decay_epochs,
                             stopped_at=stopped or None)
    return state


def _train_epochs(run: RunPlan, parts: ModelAndOptimiser, base: TrainingSet, at: Position,
                  log: MetricsLog) -> tuple[Position, float | None, str]:
    """Epoch after epoch from ``at`` until ``train.epochs``, the plateau rule, ``max_steps`` or ``max_minutes``
    (then ``last.pt`` is saved there); returns the final position, the last step's loss and why the run ended
    (:attr:`TrainResult.ended_by`)."""
    tc = run.cfg.train
    plateau = _plateau(run, log)
    if plateau is not None and plateau.stopped_at is not None:
        run.say(f"the plateau rule stopped this run after epoch {plateau.stopped_at}: nothing to train")
        return at, None, "plateau"
    end_step = run.total_steps if run.max_steps is None else min(run.total_steps, max(run.max_steps, at.step))
    estimate = DurationEstimate(first_step=at.step, todo=end_step - at.step)
    saves = _SaveClock()
    run.say(plan_line(todo=estimate.todo, epochs=tc.epochs, steps_per_epoch=run.steps_per_epoch,
                      global_batch=run.global_batch, resumed_at=at.step, max_steps=run.max_steps,
                      stops_early=end_step < run.total_steps, will_estimate=estimate.will_measure))
    last_loss, stopped, ended_by = None, False, "epochs"
    while at.epoch < tc.epochs:
        if run.reached_max_steps(at.step) or run.out_of_time():
            stopped = True
            break
        part = _train_epoch(run, parts, base, at, log, estimate, saves, plateau)
        at = part.at
        if part.last_loss is not None:
            last_loss = part.last_loss
        if part.stopped or at.step_in_epoch < run.steps_per_epoch:
            stopped = True  # --max-steps / --max-minutes hit inside the epoch
            break
        at = Position(epoch=at.epoch + 1, step_in_epoch=0, step=at.step)
        _finish_epoch(run, parts, at, part, log, saves, per_step=estimate.rolling(), steps_left=end_step - at.step)
        if plateau is not None:
            before, plateau = plateau, _plateau(run, log)
            if plateau.stopped_at is not None:
                ended_by = "plateau"
                break
            if plateau.decays > before.decays:
                lr = plateau_lr(at.step, steps_per_epoch=run.steps_per_epoch, decays=plateau.decays, tc=tc)
                run.say(f"plateau after epoch {at.epoch}: LR x {tc.plateau_factor:g} from now ({lr:.3g})")
    if stopped:
        _save(run, parts, at, run.last_path)
        return at, last_loss, "max-steps" if run.reached_max_steps(at.step) else "time"
    log.end(epoch=at.epoch, step=at.step, reason=ended_by,
            decay_epochs=list(plateau.decay_epochs) if plateau is not None else [])
    if ended_by == "plateau":
        run.say(f"plateau rule: stopped after epoch {at.epoch} (LR decays after epochs "
                f"{', '.join(map(str, plateau.decay_epochs)) or 'none'})")
    return at, last_loss, ended_by


def _train_epoch(run: RunPlan, parts: ModelAndOptimiser, base: TrainingSet, at: Position, log: MetricsLog,
                 estimate: DurationEstimate, saves: _SaveClock, plateau: PlateauState | None) -> _EpochPart:
    """The steps of epoch ``at.epoch + 1`` from ``at.step_in_epoch`` to its end (or ``max_steps``): each trained,
    logged, counted in the estimate, and ``last.pt`` saved when the save clock is due."""
    tc = run.cfg.train
    frame_order = epoch_frames(num_frames=len(run.frames), samples_per_epoch=run.samples_per_epoch, epoch=at.epoch,
                               seed=tc.seed, shuffle=tc.shuffle)
    keys = rank_batches(frame_order, epoch=at.epoch, global_batch=run.global_batch, rank=run.info.rank,
                        per_rank=tc.batch_size, start_step=at.step_in_epoch)
    settings = StepSettings(device=run.device, bf16=tc.precision == "bf16", grad_clip_norm=tc.grad_clip_norm,
                            world_size=run.info.world_size, total_steps=run.total_steps, last_good=run.last_path)
    parts.ddp.train()
    # leave=False: the epoch's line replaces its finished bar
    sums, steps, last_loss, stopped = ZERO_LOSSES, 0, None, False
    t_epoch = time.perf_counter()
    # closed on Ctrl-C too, so that the interrupt's message starts on a line of its own
    with tqdm(total=run.steps_per_epoch, initial=at.step_in_epoch, desc=f"epoch {at.epoch + 1}/{tc.epochs}",
              unit="step", disable=not run.show_bars, dynamic_ncols=True, leave=False) as bar:
        for batch in rank_loader(keys, base, tc.num_workers, pin=pin_memory(settings.device)):
            if run.reached_max_steps(at.step) or run.out_of_time():
                stopped = True
                break
            if plateau is not None:  # the plateau schedule's LR is a function of the step and the decays so far
                lr = plateau_lr(at.step, steps_per_epoch=run.steps_per_epoch, decays=plateau.decays, tc=tc)
                for group in parts.optimizer.param_groups:
                    group["lr"] = lr
            t0 = time.perf_counter()
            stats = train_step(batch, parts, settings, epoch=at.epoch, step=at.step)
            at = Position(epoch=at.epoch, step_in_epoch=at.step_in_epoch + 1, step=at.step + 1)
            steps += 1
            last_loss = stats.losses.total
            sums = add_losses(sums, stats.losses)
            log.step(epoch=at.epoch + 1, step=at.step, stats=stats, seconds=time.perf_counter() - t0)
            per_step = estimate.after_step(at.step)
            if at.step - estimate.first_step == 1 and estimate.first_step_s is not None:
                warning = long_run_warning(estimate.todo, estimate.first_step_s)
                if warning:
                    run.say(warning)
            if per_step is not None:
                validation = (f" (+ validation on {run.eval_split} every {tc.eval_every} epochs)"
                              if run.validates else "")
                run.say(estimate_line(estimate.todo, per_step, validation, estimate.expected_total(per_step)))
            bar.update(1)
            bar.set_postfix(loss=f"{last_loss:.4f}")
            if run.info.is_main and saves.due():
                _save(run, parts, at, run.last_path)
                saves.saved()
    return _EpochPart(at=at, sums=sums, steps=steps, seconds=time.perf_counter() - t_epoch, stopped=stopped,
                      last_loss=last_loss)


def _finish_epoch(run: RunPlan, parts: ModelAndOptimiser, at: Position, part: _EpochPart, log: MetricsLog,
                  saves: _SaveClock, *, per_step: float | None, steps_left: int) -> None:
    """After epoch ``at.epoch``: its record and line (with the time left at ``per_step``, the rolling mean seconds
    per step), ``checkpoints/epoch_NNN.pt`` when due, ``last.pt``, and the evaluation every ``train.eval_every``
    epochs."""
    tc = run.cfg.train
    means = mean_losses(part.sums, part.steps)
    log.epoch(epoch=at.epoch, step=at.step, steps=part.steps, means=means, seconds=part.seconds)
    run.say(epoch_line(epoch=at.epoch, epochs=tc.epochs, means=means, steps=part.steps, seconds=part.seconds,
                       step=at.step, total_steps=run.total_steps, per_step=per_step, steps_left=steps_left))
    if at.epoch % max(tc.checkpoint_every, 1) == 0 or at.epoch == tc.epochs:
        _save(run, parts, at, run.out / "checkpoints" / f"epoch_{at.epoch:03d}.pt")
    _save(run, parts, at, run.last_path)
    saves.saved()
    if tc.eval_every > 0 and at.epoch % tc.eval_every == 0:
        _evaluate(run, parts.model, at, log)


def _save(run: RunPlan, parts: ModelAndOptimiser, at: Position, path: Path) -> None:
    """Rank 0 writes the training state at ``at`` to ``path`` (atomically)."""
    if run.info.is_main:
        save_checkpoint(path, Checkpoint.capture(
            model=parts.model, optimizer=parts.optimizer, cfg=run.cfg, epoch=at.epoch,
            step_in_epoch=at.step_in_epoch, step=at.step, global_batch=run.global_batch, scheduler=parts.scheduler))


@contextlib.contextmanager
def _mode_kept(model: nn.Module) -> Iterator[nn.Module]:
    """``model``, back in the training or eval mode it had when the block ends (however it ends)."""
    was_training = model.training
    try:
        yield model
    finally:
        model.train(was_training)


def _evaluate(run: RunPlan, model: nn.Module, at: Position, log: MetricsLog) -> None:
    """The evaluation of the weights after epoch ``at.epoch`` on the eval split (rank 0; the others wait): results
    under ``RUN/eval/epoch_NNN/``, the AP in the log and a line. Nothing when the dataset lacks the split."""
    if run.info.is_main and imageset_path(run.data_dir, run.eval_split).is_file():
        t_eval = time.perf_counter()
        with _mode_kept(model):  # the evaluation switches the model to eval mode; training goes on after it
            result = evaluate_model(model, run.cfg, run.data_dir, run.eval_split,
                                    run.out / "eval" / f"epoch_{at.epoch:03d}", device=run.device,
                                    progress=run.show_bars).to_json_dict()
        log.eval(epoch=at.epoch, step=at.step, split=run.eval_split, result=result)
        run.say(validation_line(epoch=at.epoch, epochs=run.cfg.train.epochs, split=run.eval_split, result=result,
                                classes=run.cfg.eval.classes, seconds=time.perf_counter() - t_eval))
    barrier()
