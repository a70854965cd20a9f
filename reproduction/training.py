"""What a work folder's trainings were, from their run folders and the commands log: each model's schedule (epochs x
samples per epoch), precision, and the seconds the reproduction and its trainings took."""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from pathlib import Path

from reproduction.committed import read_committed
from reproduction.results import MODELS, epoch_records, read_run_config, step_records
from reproduction.runner import logged_commands
from reproduction.scales import SCALES, SPARSE_EPOCH_RATIO, Scale, epochs_text, model_epochs

#: {model: (epochs, samples per epoch)} as each run was trained, None for a model not trained.
Schedules = dict[str, tuple[int, int] | None]


def train_split_size(out: Path) -> int | None:
    """Frames in the train split of work folder ``out``'s dataset (None without one)."""
    from mpchair.kitti import imageset_path, read_imageset

    split = imageset_path(out / "dataset", "train")
    return len(read_imageset(split)) if split.is_file() else None


def trained_schedules(out: Path, models: tuple[str, ...] = MODELS) -> Schedules:
    """{model: (epochs, samples per epoch)} as each run of work folder ``out`` was trained (its config.yaml, and for
    committed weights the epochs their ``done`` marker names; an epoch without ``train.samples_per_epoch`` is one
    pass over the train split), None for a model not trained."""
    n_train = train_split_size(out)
    found: Schedules = {}
    for m in models:
        cfg = read_run_config(out / "runs" / m)
        spe = (cfg and cfg.train.samples_per_epoch) or n_train
        # committed weights: the epochs their study training ran (a plateau-ended run stops before its config's cap)
        held = read_committed(out / "runs" / m)
        epochs = held.epochs if held is not None and held.epochs else cfg.train.epochs if cfg else None
        found[m] = (epochs, spe) if cfg and spe else None
    return found


def schedules_text(trained: Schedules, sc: Scale | None = None) -> str:
    """"dense 16 epochs x 3,000 samples / sparse 20 epochs x 3,000 samples" (before training: the scale's epochs)."""
    if all(trained.values()):
        return " / ".join(f"{m} {e} epoch{'s' * (e != 1)} x {n:,} samples" for m, (e, n) in trained.items())
    return f"epochs {epochs_text(sc)}" if sc else "n/a"


def short_of_recipe(trained: Schedules, n_train: int | None) -> bool:
    """Whether a trained model saw fewer samples than the full recipe's epochs over the train split."""
    recipe = model_epochs(SCALES["recipe"].epochs)
    return bool(n_train) and any(v[0] * v[1] < recipe[m] * n_train for m, v in trained.items() if v)


def schedule_why(trained: Schedules, n_train: int | None) -> str:
    """Why this run's schedule differs from the paper's, with the sparse/dense ratio of samples it actually had."""
    full = model_epochs(SCALES["recipe"].epochs)
    seen = {m: v[0] * v[1] for m, v in trained.items() if v}
    why = "CPU budget"
    if short_of_recipe(trained, n_train):
        why += (f"; cut below the recipe's dense {full['dense']} / sparse {full['sparse']} epochs to fit the session "
                "it ran in, so the models are not converged")
    else:
        why += "; the one-cycle schedule converges in few epochs (docs/training.md)"
    if seen.get("dense") and seen.get("sparse"):
        ratio = seen["sparse"] / seen["dense"]
        why += (f"; sparse/dense ratio of training samples {ratio:.2f} (the paper's 1.25, rounded up to whole epochs)"
                if abs(ratio - SPARSE_EPOCH_RATIO) > 1e-9 else "; the paper's 1.25 sparse/dense ratio is kept")
    return why


def precision_text(out: Path) -> str:
    """The ``train.precision`` each model of work folder ``out`` was trained with ("fp32" if not recorded): one value
    when both agree, else "dense fp32, sparse bf16"; "n/a" before any training."""
    found = {m: cfg.train.precision for m in MODELS if (cfg := read_run_config(out / "runs" / m)) is not None}
    values = set(found.values())
    if len(values) == 1:
        return values.pop()
    return ", ".join(f"{m} {v}" for m, v in found.items()) or "n/a"


def epoch_seconds(run: Path) -> float:
    """Training seconds of one run: the sum of its epochs' ``time_s`` in metrics.jsonl (0 if there is none)."""
    return sum(r.time_s for r in epoch_records(run))


def elapsed_seconds(log: str, runs: Path) -> tuple[float, dict[str, float]]:
    """(seconds of the whole reproduction, {model: training seconds}) from commands.log's text and the runs' metrics.

    A resumed reproduction spans several invocations and commands.log records each *finished* command once, so a
    training cut by an interruption and resumed logs only its last part; its run's epoch times (which survive the
    resume) count all of it. Each training command counts as the larger of the two."""
    logged = {"dense": 0.0, "sparse": 0.0}
    total = 0.0
    for seconds, line in logged_commands(log):
        model = next((m for m in logged if " train " in line and f"/runs/{m} " in line + " "), None)
        if model is None:
            total += seconds
        else:
            logged[model] += seconds
    train = {m: max(t, epoch_seconds(runs / m)) for m, t in logged.items()}
    return total + sum(train.values()), train


@dataclass(frozen=True)
class TrainingTime:
    """How long one run trained, from its metrics.jsonl: finished epochs, the median seconds of an epoch and of a
    step, and the sum of its epochs' seconds (the whole run, resumed parts included)."""

    epochs: int
    epoch_s: float
    step_s: float | None
    total_s: float


def training_time(run: Path) -> TrainingTime | None:
    """The :class:`TrainingTime` of run folder ``run`` (None before its first finished epoch)."""
    epochs = epoch_records(run)
    if not epochs:
        return None
    steps = step_records(run)
    return TrainingTime(epochs=len(epochs), epoch_s=statistics.median(e.time_s for e in epochs),
                        step_s=statistics.median(s.time_s for s in steps) if steps else None,
                        total_s=sum(e.time_s for e in epochs))
