"""The report sections of the runtime figures issue 30 asked for, each from its step's JSON ("not run" without it):
the training time of dense and sparse beside the paper's "1.8x faster despite 25 % more epochs", the total-time ratio
with the reference's head layout beside the paper's 4.6x, and the backbone ratio against density D. Times in ms
unless a name says seconds or minutes."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from mpchair.paper import KITTI_DENSITY, MATTERPORT_CHAIR_DENSITY, SPARSE_EPOCH_RATIO, SPARSE_TRAIN_SPEEDUP, TABLE_II
from reproduction.committed import STUDY_SECTION, committed_runs, weights_text
from reproduction.results import (
    ABLATIONS,
    MODELS,
    read_density,
    read_density_curve,
    read_reference_head,
    read_run_config,
)
from reproduction.training import TrainingTime, training_time

#: Copies a figure (source, file name) next to the report and gives its Markdown path relative to the report.
Figure = Callable[[Path, str], str]


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f}"


def training_time_section(out: Path) -> list[str]:
    """Per-epoch and whole-run training time of each trained model (ablations too), from the runs' metrics.jsonl, and
    the sparse model's speed-up beside the paper's."""
    lines = ["## Training time (this run's trainings, from each run's metrics.jsonl)", ""]
    times = {m: t for m in (*MODELS, *ABLATIONS) if (t := training_time(out / "runs" / m)) is not None}
    committed = committed_runs(out)
    if committed:
        # no training here: the committed weights' trainings ran in the accuracy study, sessions and machines apart
        lines += ["Dense and sparse were not trained by this run (`--weights committed`): their weights are the "
                  f"accuracy study's {weights_text(committed)}, whose trainings ran "
                  "across several sessions and machines; their epoch times and validation curves are in "
                  "docs/results-data/accuracy/runs/<training>/metrics.jsonl and their results in the section "
                  f"\"{STUDY_SECTION}\".", ""]
    if not times:
        return lines + ([] if committed else ["not run", ""])
    lines += ["| model | epochs | s per epoch (median) | s per step (median) | whole run (min, sum of epochs) |",
              "|---|---|---|---|---|"]
    for m, t in times.items():
        step = "n/a" if t.step_s is None else f"{t.step_s:.3f}"
        lines.append(f"| {m} | {t.epochs} | {t.epoch_s:.1f} | {step} | {_minutes(t.total_s)} |")
    lines.append("")
    dense, sparse = times.get("dense"), times.get("sparse")
    if dense is not None and sparse is not None:
        cfg = read_run_config(out / "runs" / "dense")
        grid = cfg.model.output_shape if cfg else None
        lines += [_speedup_text(dense, sparse, grid, cfg.train.precision if cfg else None), ""]
    return lines


def _speedup_text(dense: TrainingTime, sparse: TrainingTime, grid: tuple[int, ...] | None,
                  precision: str | None) -> str:
    """The sparse model's training speed-up per epoch and over the whole run, beside the paper's; ``grid``: the
    training canvas (ny, nx) of the runs, ``precision`` theirs."""
    per_epoch = dense.epoch_s / max(sparse.epoch_s, 1e-9)
    whole = dense.total_s / max(sparse.total_s, 1e-9)
    where = f"the {grid[0]} x {grid[1]} canvas" if grid else "their canvas"
    smaller = (f" (the paper's 768 x 512 has {768 * 512 / (grid[0] * grid[1]):.1f}x its cells, and the sparse "
               "model's advantage grows with the empty area)" if grid and tuple(grid) != (768, 512) else "")
    return (f"Sparse / dense: an epoch is {per_epoch:.2f}x as fast, the whole run {whole:.2f}x with "
            f"{sparse.epochs / dense.epochs:.2f}x the epochs (paper: sparse trains {SPARSE_TRAIN_SPEEDUP}x faster "
            f"despite {SPARSE_EPOCH_RATIO - 1:.0%} more epochs, on a GPU at 768 x 512). These trainings ran on this "
            f"machine's CPU in {precision or 'fp32'} on {where}{smaller}.")


def reference_head_section(res: Path) -> list[str]:
    """The dense / sparse total time with our fused head and with the reference's three NCHW 1x1 convs
    (``bench_reference_head.json``), beside the paper's robot-CPU ratio."""
    lines = ["## Total time with the reference's head layout (768 x 512)", ""]
    bench = read_reference_head(res / "bench_reference_head.json")
    table = res / "bench_reference_head.md"
    if bench is None or not table.exists():
        return lines + ["not run", ""]
    td, ts = (TABLE_II["robot"][m].total.mean_ms for m in ("dense", "sparse"))
    ours, ref = (bench.ratio("dense", "sparse", k) for k in ("total", "total_reference_head"))
    lines += ["Our head runs the class, box and direction 1x1 convs as one fused GEMM on a channels-last map; the "
              "reference (Open3D-ML, and SPP after its todense) runs three separate convs on an NCHW map. "
              "`tools/bench_reference_head.py` times both on the same frames (the reference's on an NCHW copy of "
              "the neck map, the copy untimed) and replaces Head in each frame's total "
              "(`detector/bench/reference_head.py`):", "", table.read_text().strip(), ""]
    if ours is not None and ref is not None:
        lines += [f"Dense / sparse total time: {ours:.2f}x with our head, {ref:.2f}x with the reference's layout "
                  f"(paper, robot CPU: {td} / {ts} ms = {td / ts:.1f}x).", ""]
    return lines


def density_curve_section(res: Path, figure: Figure) -> list[str]:
    """The backbone ratio against D (``density_curve.json``), its table and plot, the crossings, the paper's D and
    this dataset's beside them."""
    lines = ["## Dense / sparse backbone against density D (768 x 512)", ""]
    curve = read_density_curve(res / "density_curve.json")
    table = res / "density_curve.md"
    if curve is None or not table.exists():
        return lines + ["not run", ""]
    density = read_density(res / "density.json")
    median = density.values.get("median") if density else None
    here = f"; this run's test split: median D {median:.5f}" if median else ""
    lines += [f"Sites: {curve.sites}; {curve.weights}; {curve.cpu}, {curve.threads} torch threads. Each row times "
              "both backbones (backbone + neck, the paper's Backbone timer) on the same pseudo-images, interleaved "
              "per frame; the op-count ratio is the dense backbone + neck's MACs over the sparse one's exact MACs on "
              "the same sites (`detector/opcount.py`). Rows marked *real frame* are test frames at their own D. "
              f"The paper's Matterport-Chair median D is {MATTERPORT_CHAIR_DENSITY.median}, KITTI's "
              f"{KITTI_DENSITY.median}{here}.", "",
              table.read_text().strip(), ""]
    if (res / "density_curve.png").exists():
        lines += [f"![dense / sparse against D]({figure(res / 'density_curve.png', 'density_curve.png')})", ""]
    return lines
