"""``detector train``: parse arguments, call :func:`detector.train.train`, print where the run is."""

from __future__ import annotations

import shlex
import sys

import click

from detector.commands import config_help
from mpchair.core import limits


def _say(line: str) -> None:
    """One line on stdout, above any progress bar, flushed at once (a parent such as tools/reproduce.py passes it
    through as it comes, even when stdout is a pipe or a file)."""
    from tqdm import tqdm

    tqdm.write(line, file=sys.stdout)
    sys.stdout.flush()


def _resume_command(ctx: click.Context) -> str:
    """This command line as typed (the options given on it, in the command's order) with ``--resume``; under
    torchrun the ``torchrun ... -m detector`` prefix stands for the one used."""
    import os

    words = ["detector", "train"]
    for param in ctx.command.params:
        source = ctx.get_parameter_source(param.name)
        if source != click.core.ParameterSource.COMMANDLINE or param.name == "resume":
            continue
        value = ctx.params[param.name]
        if isinstance(param, click.Option) and param.is_flag:
            words += [param.opts[0]] if value else []
        else:
            words += [param.opts[0], str(value)]
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        words[:1] = ["torchrun", "...", "-m", "detector"]
    return shlex.join(words + ["--resume"])


@click.command("train")
@click.option("--config", "config_path", required=True, type=click.Path(dir_okay=False), metavar="NAME|YAML",
              help=config_help())
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False),
              help="KITTI-format dataset folder (training/ + ImageSets/).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Run folder: checkpoints, last.pt, metrics.jsonl, config.yaml.")
@click.option("--epochs", type=int, default=None, help="Override train.epochs.")
@click.option("--precision", type=click.Choice(["fp32", "bf16"]), default=None,
              help="Override train.precision: bf16 runs the forward pass under torch.autocast (weights, optimiser "
                   "and losses stay fp32); ~1.85x faster dense steps on CPUs with AVX512-BF16/AMX.")
@click.option("--resume", is_flag=True, help="Continue from OUT/last.pt (identical to an uninterrupted run).")
@click.option("--max-steps", type=int, default=None, help="Stop after this many optimiser steps (whole run) and save.")
@click.option("--max-minutes", type=float, default=None,
              help="Stop after this much wall time (at the next step), save last.pt and print how to resume: a "
                   "long training split over sessions.")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@click.option("--threads", type=limits.parallel_range(), default=None,
              help="torch intra-op threads (default: torch's choice).")
@click.option("--split", default="train", show_default=True, help="ImageSets split to train on.")
@click.option("--eval-split", default="val", show_default=True,
              help="Split evaluated every train.eval_every epochs (skipped if the dataset lacks it).")
@click.option("--no-progress", is_flag=True,
              help="No progress bars (the plan, the duration estimate and one line per epoch are still printed).")
def train(config_path: str, data_dir: str, out_dir: str, epochs: int | None, precision: str | None, resume: bool,
          max_steps: int | None, max_minutes: float | None, device: str, threads: int | None, split: str,
          eval_split: str,
          no_progress: bool) -> None:
    """Train dense or sparse PointPillars on a KITTI-format dataset.

    \b
    Prints the plan, the expected duration after the first few steps (steps x measured seconds per step), one line
    per epoch (mean loss, time) and per validation (AP). Metrics go to OUT/metrics.jsonl (one JSON object per line),
    checkpoints to OUT/checkpoints/epoch_NNN.pt and OUT/last.pt (written atomically). Same seed, same data → same
    weights; --resume continues exactly.
    Distributed (DDP, gloo on CPU / nccl on CUDA; train.batch_size is per process):
      torchrun --standalone --nproc-per-node=2 -m detector train --config CFG --data DIR --out RUN
    """
    from detector.train import TrainingError, dist_info_from_env
    from detector.train import train as run_training
    from mpchair.core.atomic import check_writable

    # Under torchrun every rank runs this command; rank 0 speaks for the job (the others' results are the same).
    main_rank = dist_info_from_env().is_main
    check_writable(out_dir, folder=True)
    try:
        result = run_training(config_path, data_dir, out_dir, epochs=epochs, precision=precision, resume=resume,
                              max_steps=max_steps, max_minutes=max_minutes, device=device, threads=threads, split=split,
                              eval_split=eval_split, progress=not no_progress, log=_say)
    except KeyboardInterrupt:
        if main_rank:
            from pathlib import Path

            from detector.train.resume import interrupted_line

            click.echo(interrupted_line(Path(out_dir) / "last.pt", _resume_command(click.get_current_context())),
                       err=True)
        sys.exit(130)
    except TrainingError as e:
        if main_rank:  # the failing loss / gradient norm is all-reduced: every rank stops at the same step
            click.echo(f"error: {e}", err=True)
        sys.exit(1)
    if main_rank:
        loss = "n/a" if result.last_loss is None else f"{result.last_loss:.4f}"
        ended = {"plateau": "; ended by the plateau rule", "time": "; --max-minutes reached: continue with "
                 + _resume_command(click.get_current_context()), "max-steps": ""}.get(result.ended_by, "")
        click.echo(f"trained {result.epoch} epoch(s), {result.step} step(s), last loss {loss}; "
                   f"checkpoint {result.last_checkpoint}{ended}")
