"""``--status``: where the reproduction in a work folder stands: each step's outputs, and each model's training step
of its total, recent pace, time left, and whether a process trains it right now."""

from __future__ import annotations

import statistics
from pathlib import Path

from mpchair.core.errors import InputError
from reproduction.committed import read_committed
from reproduction.results import ABLATIONS, MODELS, read_run_config, step_records
from reproduction.steps import step_outputs
from reproduction.training import trained_schedules


def train_status(out: Path, model: str) -> str:
    """One line on a model's training in work folder ``out``: trained, not started, or at step s of N with its recent
    pace and the time left, and whether a process is training it right now (its run folder's lock is held)."""
    from detector.train import format_duration
    from mpchair.core.lock import held

    run = out / "runs" / model
    committed = read_committed(run)
    if committed is not None:
        return f"{model}: the committed weights {committed.text()} (--weights committed: not trained here)"
    if (run / "done").exists():
        return f"{model}: trained"
    schedule = trained_schedules(out, (model,))[model]  # (epochs, samples per epoch) of the run's config
    steps = step_records(run)
    if schedule is None or not steps:
        return f"{model}: not started"
    epochs, samples = schedule
    batch = read_run_config(run).train.batch_size
    if not isinstance(batch, int) or batch < 1 or not isinstance(epochs, int) or not isinstance(samples, int):
        raise InputError(f"train: expected whole numbers, batch_size >= 1 (got batch_size {batch!r}, epochs "
                         f"{epochs!r}, samples_per_epoch {samples!r}); not the config detector train wrote",
                         run / "config.yaml")
    total = epochs * (samples // batch)
    pace = statistics.median(r.time_s for r in steps[-200:])
    now = steps[-1]
    running = "running now" if held([run / ".train.lock"]) else "stopped (the same command resumes it)"
    return (f"{model}: step {now.step:,} / {total:,} (epoch {now.epoch} of {epochs}), {pace:.2f} s/step "
            f"lately -> ~{format_duration(pace * (total - now.step))} left; {running}")


def other_scales(out: Path, scale: str, scales: tuple[str, ...]) -> dict[str, Path]:
    """The work folders of the other ``scales`` beside ``out`` (``out/reproduce-<scale>``, the default naming) that
    exist, by scale."""
    folders = {s: out.parent / f"reproduce-{s}" for s in scales if s != scale}
    return {s: f for s, f in folders.items() if f.is_dir()}


def status_lines(out: Path, others: dict[str, Path] | None = None) -> list[str]:
    """Where the reproduction in work folder ``out`` stands: each step's outputs (:func:`step_outputs`) and each
    model's training progress. Where ``out`` holds none, which of ``others`` (work folders of other scales) do, and
    the ``--scale`` that shows each."""
    if not out.is_dir():
        found = [f"{folder} (--scale {s})" for s, folder in sorted((others or {}).items())]
        return [f"{out}: no reproduction here yet" + (f"; there is one in {', '.join(found)}" if found else "")]
    lines = [f"{out}:"]
    for step, files in step_outputs(out).items():
        paths = list(files.values())
        have = sum(p.exists() for p in paths)
        lines.append(f"  {step:<9} {'done' if have == len(paths) else f'{have} of {len(paths)} outputs'}")
        if step == "train":
            lines += [f"    {train_status(out, m)}" for m in MODELS]
        if step == "ablations":
            lines += [f"    {train_status(out, a)}" for a in ABLATIONS]
    return lines
