"""``detector bench``: parse arguments, call :func:`detector.bench.run_bench`, print the paper-shaped table."""

from __future__ import annotations

import json

import click


@click.command("bench")
@click.option("--config", "configs", multiple=True, required=True, type=click.Path(dir_okay=False),
              help="Experiment YAML; repeat to time several models interleaved (the first is the ratio's numerator).")
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False),
              help="KITTI-format dataset folder (training/ + ImageSets/).")
@click.option("--checkpoint", "checkpoints", multiple=True,
              help="Trained weights, one per --config in the same order ('-' = random weights). Default: random "
                   "weights for every model (fine for timing; said so in the output).")
@click.option("--split", default="test", show_default=True, help="ImageSets split whose first frames are timed.")
@click.option("--frames", type=int, default=20, show_default=True, help="Frames per trial.")
@click.option("--trials", type=int, default=3, show_default=True, help="Timed passes over the frames.")
@click.option("--warmup", type=int, default=3, show_default=True, help="Untimed warm-up frames per model.")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@click.option("--threads", type=int, default=None,
              help="torch intra-op threads (default: the free cores, i.e. the cores minus the 1-minute load, at "
                   "least 1; a warning when threads + load exceed the cores).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the random weights.")
@click.option("--peer", type=click.Choice(["open3d-ml"]), default=None,
              help="Also time Open3D-ML's own PointPillars, built like the first --config (a dense model) with its "
                   "weights, on the same frames, interleaved per frame (CPU; needs the open3d extra).")
@click.option("--json", "json_out", type=click.Path(dir_okay=False), default=None,
              help="Also write the full result as JSON to this file.")
@click.option("--markdown", is_flag=True, help="Print the table as Markdown.")
@click.option("--no-progress", is_flag=True,
              help="No progress bars (shown on stderr by default when it is a terminal, between the timed frames).")
@click.option("--precision", type=click.Choice(["fp32", "bf16", "auto"]), default="fp32", show_default=True,
              help="Inference precision of our models: bf16 runs Feature Net, Backbone and Head in bfloat16 (fp32 "
                   "sums); auto = bf16 where the CPU computes it natively (AVX512-BF16 / AMX), else fp32.")
def bench(configs: tuple[str, ...], data_dir: str, checkpoints: tuple[str, ...], split: str, frames: int, trials: int,
          warmup: int, device: str, threads: int | None, seed: int, peer: str | None, json_out: str | None,
          markdown: bool, no_progress: bool, precision: str) -> None:
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
    Allocator: CPU timings depend on glibc's; compare with
      MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=68719476736 detector bench ...
    Example:
      detector bench --config configs/models/mpchair_dense.yaml --config configs/models/mpchair_sparse.yaml \\
        --data dataset/ --frames 20 --trials 3 --peer open3d-ml --json bench.json
    """
    from detector.bench import BenchModel, format_table, run_bench
    from detector.device import free_cores, load_1m, oversubscription_warning, usable_cores
    from mpchair.core.atomic import check_writable, write_text
    from mpchair.core.errors import InputError

    if checkpoints and len(checkpoints) != len(configs):
        raise InputError(f"give one --checkpoint per --config ('-' for random weights): {len(checkpoints)} "
                         f"checkpoint(s) for {len(configs)} config(s)")
    ckpts = [None if c in ("-", "") else c for c in checkpoints] or [None] * len(configs)
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
    if precision == "auto":
        from detector.models.pointpillars import native_bf16

        precision = "bf16" if device == "cpu" and native_bf16() else "fp32"
    result = run_bench(models, data_dir, split=split, frames=frames, trials=trials, warmup=warmup, device=device,
                       threads=threads, seed=seed, peer=peer, progress=not no_progress, precision=precision)
    if json_out:
        write_text(json_out, json.dumps(result, indent=2) + "\n")
    click.echo(format_table(result, markdown=markdown))
