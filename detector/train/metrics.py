"""What a run reports: ``RUN/metrics.jsonl`` (one JSON object per line, ``kind`` = ``step`` | ``epoch`` | ``eval``),
cut back to the checkpoint's step on resume, and the lines meant for a person (the plan, the duration estimate, one
line per epoch and per validation).
"""

from __future__ import annotations

import collections
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from types import TracebackType

from detector.models.losses import Losses
from detector.train.step import StepStats
from mpchair.core.atomic import write_text

#: The start-up estimate skips ESTIMATE_WARMUP steps (the first steps of a process allocate buffers, build the GEMM
#: kernels of each new shape and fill the loader's queue: measured on 2 cores, they ran about twice as slow as the
#: rest, which made a 20-step estimate 2x high), then takes the median of ESTIMATE_STEPS step times (one checkpoint
#: write or late kernel build among them does not move it), and adds the steps still to run at that pace to the
#: time already spent.
ESTIMATE_WARMUP = 2
ESTIMATE_STEPS = 3
#: The estimate in each epoch line is the mean wall time of the last ROLLING_STEPS steps (data loading, checkpoints
#: and validation included): step times drift by several times over a run (a shared CPU, the GT sampler's
#: boxes, thermal limits), so the start-up measurement alone can be far off.
ROLLING_STEPS = 50


def read_metrics(path: Path, max_step: int) -> list[str]:
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


def _loss_fields(losses: Losses) -> dict[str, float]:
    """The ``loss_*`` keys of a step or epoch record, in the log's order (total first)."""
    return {"loss_total": losses.total, "loss_cls": losses.cls, "loss_reg": losses.reg, "loss_dir": losses.dir}


class MetricsLog:
    """``metrics.jsonl`` of a run, appended and flushed record by record. Only rank 0 writes (``writes``); on the
    other ranks every record is dropped. Opening it cuts the file back to global step ``step``: lines an interrupted
    run wrote after its checkpoint go, so the resumed log replays cleanly."""

    def __init__(self, path: Path, *, step: int, writes: bool) -> None:
        self.path = path
        self._kept = read_metrics(path, step) if writes else []
        #: the evaluation records by epoch (kept ones, then this run's), for the plateau rule
        self.evals: dict[int, dict] = {}
        for line in self._kept:
            rec = json.loads(line)
            if rec.get("kind") == "eval":
                self.evals[int(rec["epoch"])] = rec
        if writes:
            write_text(path, "".join(line + "\n" for line in self._kept))
        self._file = open(path, "a", encoding="utf-8") if writes else None  # noqa: SIM115 (closed by close())

    def has_eval(self, epoch: int) -> bool:
        """Whether the log as it was kept at opening holds the evaluation record of ``epoch``."""
        for line in self._kept:
            rec = json.loads(line)
            if rec.get("kind") == "eval" and rec.get("epoch") == epoch:
                return True
        return False

    def write(self, record: dict) -> None:
        """Append one record (an ``OSError`` names the file)."""
        if self._file is None:
            return
        try:
            self._file.write(json.dumps(record) + "\n")
            self._file.flush()
        except OSError as e:
            e.filename = e.filename or str(self.path)
            raise

    def step(self, *, epoch: int, step: int, stats: StepStats, seconds: float) -> None:
        """The record of global step ``step`` in (1-based) epoch ``epoch``: what the step measured and its seconds."""
        self.write({"kind": "step", "epoch": epoch, "step": step, **_loss_fields(stats.losses),
                    "grad_norm": stats.grad_norm, "num_pos": stats.num_pos, "lr": stats.lr, "beta1": stats.beta1,
                    "time_s": round(seconds, 4)})

    def epoch(self, *, epoch: int, step: int, steps: int, means: Losses, seconds: float) -> None:
        """The record of completed epoch ``epoch``: its ``steps`` steps' mean losses and its seconds."""
        self.write({"kind": "epoch", "epoch": epoch, "step": step, "steps": steps, **_loss_fields(means),
                    "time_s": round(seconds, 3)})

    def eval(self, *, epoch: int, step: int, split: str, result: dict) -> None:
        """The evaluation of the weights after epoch ``epoch`` on ``split`` (a KITTI result's JSON dict)."""
        record = {"kind": "eval", "epoch": epoch, "step": step, "split": split, **result}
        self.evals[epoch] = record
        self.write(record)

    def end(self, *, epoch: int, step: int, reason: str, **details: object) -> None:
        """The record of a run's end: ``reason`` ``plateau`` (the plateau rule stopped it) or ``epochs`` (the cap)."""
        self.write({"kind": "end", "epoch": epoch, "step": step, "reason": reason, **details})

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> MetricsLog:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def add_losses(a: Losses, b: Losses) -> Losses:
    """Field-by-field sum of two float :class:`Losses`."""
    return Losses(**{name: getattr(a, name) + getattr(b, name) for name in Losses._fields})


def mean_losses(sums: Losses, steps: int) -> Losses:
    """Per-step means of summed losses (``sums`` itself when no step ran)."""
    return Losses(**{name: value / max(steps, 1) for name, value in sums._asdict().items()})


ZERO_LOSSES = Losses(cls=0.0, reg=0.0, dir=0.0, total=0.0)


class DurationEstimate:
    """The duration estimates of a process that runs ``todo`` steps from global step ``first_step`` (a resumed run's
    checkpoint step: only the steps this process runs count).

    The start-up one (:meth:`after_step`): the median wall time between the ends of steps ``ESTIMATE_WARMUP + 1`` to
    ``ESTIMATE_WARMUP + ESTIMATE_STEPS`` of this process (data loading and checkpoints included), nothing for
    ``ESTIMATE_WARMUP + ESTIMATE_STEPS`` steps or fewer; :meth:`expected_total` turns it into the whole run's
    duration (the time spent so far plus the steps left at that pace). The rolling one (:meth:`rolling`): the mean
    wall time between the ends of the last ``ROLLING_STEPS`` steps after the warm-up, updated at every step, for the
    epoch lines. ``clock`` is the time source (seconds)."""

    def __init__(self, *, first_step: int, todo: int, clock: Callable[[], float] = time.perf_counter) -> None:
        self.first_step = first_step
        self.todo = todo
        self._clock = clock
        self._started = clock()
        self._last_end: float | None = None
        self._done = 0
        self._timed: list[float] = []
        self._recent: collections.deque[float] = collections.deque(maxlen=ROLLING_STEPS)
        self.first_step_s: float | None = None  # wall time of this process's first step, once it ran

    @property
    def will_measure(self) -> bool:
        return self.todo > ESTIMATE_WARMUP + ESTIMATE_STEPS

    def after_step(self, step: int) -> float | None:
        """Call after every step (``step``: the global steps done); returns the measured seconds per step once, else
        None."""
        now = self._clock()
        self._done = step - self.first_step
        if self._done == 1:
            self.first_step_s = now - self._started
        if self._last_end is not None and self._done > ESTIMATE_WARMUP:
            self._recent.append(now - self._last_end)
            if len(self._timed) < ESTIMATE_STEPS:
                self._timed.append(now - self._last_end)
        self._last_end = now
        if self._done == ESTIMATE_WARMUP + ESTIMATE_STEPS and self.will_measure:
            return statistics.median(self._timed)
        return None

    def expected_total(self, per_step: float) -> float:
        """Seconds this process will train in all: the time since it started plus its steps left at ``per_step``."""
        return (self._clock() - self._started) + per_step * max(self.todo - self._done, 0)

    def rolling(self) -> float | None:
        """Mean seconds per step over the last ``ROLLING_STEPS`` timed steps (None before the first timed one)."""
        return sum(self._recent) / len(self._recent) if self._recent else None


def format_duration(seconds: float) -> str:
    """``"42 s"``, ``"12 min"`` or ``"3.4 h"``: a duration as a person reads it."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def plan_line(*, todo: int, epochs: int, steps_per_epoch: int, global_batch: int, resumed_at: int,
              max_steps: int | None, stops_early: bool, will_estimate: bool) -> str:
    """``training 6 step(s): 2 epochs x 4 steps (global batch 2)[, resumed at step S][, stopping at --max-steps M]
    [; timing the first steps...]``."""
    return (f"training {todo} step(s): {epochs} epochs x {steps_per_epoch} steps (global batch {global_batch})"
            + (f", resumed at step {resumed_at}" if resumed_at else "")
            + (f", stopping at --max-steps {max_steps}" if stops_early else "")
            + ("; timing the first steps..." if will_estimate else ""))


#: A plan that would run longer than this on this machine is said at once, after its first step (not after the
#: warm-up: on a CPU the paper's GPU-sized config takes ~37 s a step, so the measured estimate came ~2 min later).
LONG_RUN_S = 24 * 3600.0


def long_run_warning(todo: int, first_step_s: float) -> str | None:
    """After the first step (``first_step_s`` seconds): a warning when even at half that pace (the first step is the
    slowest) the ``todo`` steps take longer than :data:`LONG_RUN_S`, else None."""
    lower = todo * first_step_s / 2
    if lower <= LONG_RUN_S:
        return None
    return (f"warning: the first step took {first_step_s:.0f} s: even at half that pace the {todo:,} steps take "
            f"~{lower / 86400:.0f} days on this machine; on a CPU, train the "
            "*_cpu configs (e.g. --config mpchair_sparse_cpu, sized for 2 cores) or pass --max-steps")


def estimate_line(todo: int, per_step: float, validation: str, total: float | None = None) -> str:
    """``6 steps, ~0.85 s/step measured -> ~5 s`` followed by ``validation`` (what comes on top, or empty); ``total``:
    the expected seconds of the whole run (default ``todo x per_step``)."""
    total = per_step * todo if total is None else total
    return f"{todo} steps, ~{per_step:.2f} s/step measured -> ~{format_duration(total)}" + validation


def epoch_line(*, epoch: int, epochs: int, means: Losses, steps: int, seconds: float, step: int,
               total_steps: int, per_step: float | None = None, steps_left: int = 0) -> str:
    """``epoch 1/2: loss L (cls C, reg R, dir D), N steps in T, step S/TOTAL`` and, with ``per_step`` (the rolling
    mean, seconds) and steps still to run, ``, ~0.85 s/step now -> ~5 min left``."""
    left = (f", ~{per_step:.2f} s/step now -> ~{format_duration(per_step * steps_left)} left"
            if per_step is not None and steps_left > 0 else "")
    return (f"epoch {epoch}/{epochs}: loss {means.total:.4f} (cls {means.cls:.4f}, reg {means.reg:.4f}, dir "
            f"{means.dir:.4f}), {steps} steps in {format_duration(seconds)}, step {step}/{total_steps}" + left)


def ap_text(result: dict, classes: tuple[str, ...]) -> str:
    """``"Chair BEV AP 12.34, 3D AP 5.67"`` (R40, Overall level) of a KITTI result's JSON dict."""
    parts = [f"{c} BEV AP {result[c]['bev']['overall']['R40']:.2f}, 3D AP {result[c]['3d']['overall']['R40']:.2f}"
             for c in classes if c in result]
    return "; ".join(parts) + " (R40, Overall)"


def validation_line(*, epoch: int, epochs: int, split: str, result: dict, classes: tuple[str, ...],
                    seconds: float) -> str:
    """``epoch 5/25 validation on val: Chair BEV AP 12.34, 3D AP 5.67 (R40, Overall), 48 s``."""
    return f"epoch {epoch}/{epochs} validation on {split}: {ap_text(result, classes)}, {format_duration(seconds)}"
