"""``detector bench``: parse arguments, call :func:`detector.bench.run_bench`, print the paper-shaped table."""

from __future__ import annotations

import json
from pathlib import Path

import click

from detector.commands import PRETRAINED_HELP, config_help
from mpchair.core import limits


@click.command("bench")
@click.option("--config", "configs", multiple=True, required=True, type=click.Path(dir_okay=False), metavar="NAME|YAML",
              help=config_help("Experiment config; repeat to time several models interleaved (the first is the ratio's "
                               "numerator)"))
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False),
              help="KITTI-format dataset folder (training/ + ImageSets/).")
@click.option("--checkpoint", "checkpoints", multiple=True,
              help=f"Trained weights ({PRETRAINED_HELP}), one per --config in the same order ('-' = random weights). "
                   "Default: random weights for every model (fine for timing; said so in the output).")
@click.option("--split", default="test", show_default=True, help="ImageSets split whose first frames are timed.")
@click.option("--frames", type=int, default=20, show_default=True, help="Frames per trial.")
@click.option("--trials", type=int, default=3, show_default=True, help="Timed passes over the frames.")
@click.option("--warmup", type=int, default=3, show_default=True, help="Untimed warm-up frames per model.")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@click.option("--threads", type=limits.parallel_range(), default=None,
              help="torch intra-op threads (default: the free cores, i.e. the cores minus the 1-minute load, at "
                   "least 1; a warning when threads + load exceed the cores).")
@click.option("--seed", type=limits.SEED, default=0, show_default=True, help="Seed of the random weights.")
@click.option("--peer", type=click.Choice(["open3d-ml"]), default=None,
              help="Also time Open3D-ML's own PointPillars, built like the first --config (a dense model) with its "
                   "weights, on the same frames, interleaved per frame (CPU; needs the open3d extra).")
@click.option("--runtime", "runtimes", multiple=True, type=click.Choice(["torch", "onnxruntime", "openvino"]),
              help="Runtime of every model (repeatable; default torch = eager PyTorch): onnxruntime / openvino "
                   "export the network (backbone + neck + head) and run it there (needs the deploy extra).")
@click.option("--precision", "precisions", multiple=True, type=click.Choice(["fp32", "bf16", "int8"]),
              help="Precision of every model x runtime (repeatable; default fp32): bf16 = bfloat16 (eager torch: "
                   "Feature Net, Backbone and Head under bf16 autocast; OpenVINO: its inference precision), int8 = "
                   "post-training quantization over calibration frames (deployed runtimes). One this CPU cannot "
                   "compute natively (AMX / AVX512-BF16 / VNNI flags) is skipped with a note.")
@click.option("--calibration-split", default="train", show_default=True, help="Split of the int8 calibration frames.")
@click.option("--calibration-frames", type=int, default=8, show_default=True, help="int8 calibration frames.")
@click.option("--rate", type=limits.FiniteFloat(0.0, 1e4), default=None,
              help="CPU budget mode: run each model x runtime x precision on its own at this sensor rate (Hz) for "
                   "--duration s and report CPU share, deadline misses, latency p50 / p95 and peak RSS.")
@click.option("--duration", type=limits.FiniteFloat(0.0, 1e6), default=30.0, show_default=True,
              help="Seconds per row in --rate mode.")
@click.option("--runs", type=click.IntRange(1, 100), default=1, show_default=True,
              help="Run the whole bench this many times, each in a process of its own, one after another: every "
                   "ratio reported as median [min-max] over the runs (the JSON's 'repeated'; the tables are the "
                   "first run's).")
@click.option("--json", "as_json", is_flag=True, help="Print the full result as JSON instead of the table.")
@click.option("--json-out", "json_out", type=click.Path(dir_okay=False), default=None,
              help="Also write the full result as JSON to this file (the table is still printed).")
@click.option("--markdown", is_flag=True, help="Print the table as Markdown.")
@click.option("--no-progress", is_flag=True,
              help="No progress bars (shown on stderr by default when it is a terminal, between the timed frames).")
def bench(configs: tuple[str, ...], data_dir: str, checkpoints: tuple[str, ...], split: str, frames: int, trials: int,
          warmup: int, device: str, threads: int | None, seed: int, peer: str | None, runtimes: tuple[str, ...],
          precisions: tuple[str, ...], calibration_split: str, calibration_frames: int, rate: float | None,
          duration: float, runs: int, as_json: bool, json_out: str | None, markdown: bool,
          no_progress: bool) -> None:
    """Per-component runtime (ms per frame) of one or more models, as the paper's Tables II / IV.

    \b
    Columns: To Device, Feature Extract (voxelize + pillar net), Feature Net (scatter / sparse tensor), Backbone
    (backbone + neck, incl. todense), Head, BBox Extract (decode + NMS), Total; mean ± std over trials; a ratio row
    (first model / each other). Also records density D, machine, allocator env and page faults per frame.
    With two or more --config, a second table times Head and BBox Extract back to back (every model to its neck,
    then every model's Head, then every BBox Extract, order rotated per frame; --trials more passes): in the
    per-frame pipeline they follow each model's own backbone and pay for the state it leaves, so compare these
    identical components between models there (docs/benchmarks.md).
    --peer open3d-ml adds Open3D-ML's PointPillars (same architecture, grid and weights as the first --config) as a
    last row, and ratio rows open3d-ml / each of ours (> 1: ours is faster).
    --runtime / --precision (each repeatable): every model x runtime x precision is one row, all interleaved per
    frame; a headline line compares the fastest sparse row with the fastest dense row (docs/deployment.md).
    --rate HZ --duration S: the CPU budget instead of the tables (each row alone, in its own process).
    --runs N (>= 3 for a spread worth quoting): the same bench N times in separate processes; each ratio as the
    median with its min-max over the runs (docs/benchmarks.md).
    Allocator: CPU timings depend on glibc's; compare with
      MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=68719476736 detector bench ...
    Example:
      detector bench --config mpchair_dense --config mpchair_sparse \\
        --data dataset/ --frames 20 --trials 3 --peer open3d-ml --json-out bench.json
    """
    from detector.bench import BenchModel, format_table, run_bench
    from detector.bench.run import Variant, bench_checkpoints
    from detector.device import free_cores, load_1m, oversubscription_warning, usable_cores
    from mpchair.core.atomic import check_writable, write_text
    from mpchair.core.errors import InputError

    ckpts = bench_checkpoints(configs, checkpoints)
    models = [BenchModel(name="", config=c, checkpoint=k) for c, k in zip(configs, ckpts)]
    if json_out:
        check_writable(json_out)  # before the minutes of timing, not after
    if device == "cpu":
        # oversubscribed threads wait on each other: a loaded machine measured a 2.2x sparse/dense backbone ratio at
        # --threads 2 and 14.2x at --threads 1 minutes later, so warn before timing, not after
        cores, load = usable_cores(), load_1m()
        threads = free_cores(cores, load) if threads is None else threads
        warning = oversubscription_warning(threads, cores, load) if threads >= 1 else None
        if warning:
            click.echo(f"warning: {warning}", err=True)
    variant = Variant(runtimes=runtimes or ("torch",), precisions=precisions or ("fp32",),
                      calibration_split=calibration_split, calibration_frames=calibration_frames)
    if runs > 1:
        from detector.bench.repeat import child_args, format_repeated, run_repeated

        if rate is not None:
            raise InputError("--runs repeats the runtime tables: drop --rate (the budget runs each row alone already)")
        ctx = click.get_current_context()
        result, rep, data = run_repeated(child_args(ctx.params, ctx.command.params, Path("run.json")), runs,
                                         echo=lambda line: click.echo(line, err=True))
        if json_out:
            write_text(json_out, json.dumps(data, indent=2) + "\n")
        click.echo(json.dumps(data, indent=2) if as_json else
                   format_table(result, markdown=markdown) + "\n\n" + format_repeated(rep, markdown))
        return
    if rate is not None:
        from detector.bench.budget import run_budget
        from detector.bench.report import format_budget

        if device != "cpu" or peer is not None:
            raise InputError("--rate measures the CPU budget of our models: drop --device / --peer")
        result = run_budget(models, data_dir, rate=rate, duration=duration, split=split, frames=frames,
                            warmup=warmup, threads=threads, seed=seed, variant=variant)
        text = format_budget(result, markdown=markdown)
        data = result
    else:
        result = run_bench(models, data_dir, split=split, frames=frames, trials=trials, warmup=warmup,
                           device=device, threads=threads, seed=seed, peer=peer, progress=not no_progress,
                           variant=variant)
        text = format_table(result, markdown=markdown)
        data = result.to_json()
    if json_out:
        write_text(json_out, json.dumps(data, indent=2) + "\n")
    click.echo(json.dumps(data, indent=2) if as_json else text)
