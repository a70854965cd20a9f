"""The sizes of each reproduction scale (houses, frames, epochs, bench trials), the sparse model's epochs, and whether
this CPU computes bfloat16 natively (the ``auto`` precision)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Scale:
    """Sizes of one scale: houses x frames per house, the dense model's training epochs (the sparse model trains
    :data:`SPARSE_EPOCH_RATIO` times as many, as the paper's 250 vs 200) and precision (None: the config's), bench
    (frames, trials, runs)."""

    houses: int
    frames_per_house: int
    epochs: int | None
    bench_frames: int
    bench_trials: int
    ops_frames: int
    precision: str | None = None
    #: the density curve (tools/bench_density.py): synthetic frames per density, timed passes, densities (None: the
    #: tool's eight from 0.002 to 0.0246) and real test frames timed at their own D
    curve_frames: int = 3
    curve_trials: int = 3
    curve_densities: tuple[float, ...] | None = None
    curve_real_frames: int = 5
    budget_seconds: float = 30.0  # each CPU-budget row of the deploy step (detector bench --rate)
    #: ``mpchair generate --split-mode``: ``house`` keeps whole houses per split (val and test houses never seen in
    #: training); ``frame`` (the records made before 2026-12-06 and the small scale) a seeded per-frame split
    split_mode: str = "frame"
    #: ``detector bench --runs``: the bench step's (and the deploy step's runtime table's) runs, each a process of its
    #: own, whose median and min-max the report quotes (one run: the records made before 2026-12-07, and the quick
    #: scales)
    bench_runs: int = 1


SCALES = {
    "small": Scale(houses=2, frames_per_house=150, epochs=2, bench_frames=5, bench_trials=2, ops_frames=10,
                   curve_frames=1, curve_trials=1, curve_densities=(0.002, 0.0075, 0.0246), curve_real_frames=2,
                   budget_seconds=5.0),
    # about 2 h on 2 idle cores: the full pipeline on 8 houses with fewer frames and epochs than the targets
    "medium": Scale(houses=8, frames_per_house=250, epochs=10, bench_frames=20, bench_trials=3, ops_frames=100,
                    budget_seconds=20.0),
    # make reproduce's default: the data (8 houses x 625 frames) with a schedule chosen (estimated, not yet
    # timed) to fit one 3-hour session of a 2-core AVX512-BF16 machine together with make reproduce-stream (this
    # project's machines keep no files between sessions, so the stream reproduction must run on the same machine as
    # the training): dense 4 / sparse 5 bf16 epochs (the paper's 1.25 ratio exactly; 8 / 10 took 126 min of training
    # before the sparse speed-ups of issue 28, a 4 / 5 retrain reached KITTI 3D Overall R40 58.9 / 57.6 against
    # 68.2 / 64.1 at 8 / 10)
    # (bench 30 frames: at 10, BBox Extract's 5-10 ms per frame swung 0.65-1.43x between the models on a noisy VM)
    #
    # Since 2026-12-06 (issue 44): 12 houses x 400 frames split by house, 8 / 2 / 2 (3,200 train / 800 val / 800 test
    # frames; val and test houses are never trained on), the dataset of the accuracy study (tools/accuracy_study.py),
    # whose plateau-trained seeds replace this scale's short trainings in the accuracy claims.
    "full": Scale(houses=12, frames_per_house=400, epochs=4, bench_frames=30, bench_trials=3, ops_frames=200,
                  precision="auto", split_mode="house", bench_runs=3),
    # the recipe's longer schedule: dense 16 / sparse 20 bf16 epochs (24,000 / 30,000 steps; 15 epochs each reached
    # dense 80.77 / sparse 79.32 3D AP Moderate, pre-issue-15 labels, in 184 min on 2 AVX512-BF16 cores); a GPU's job
    # or a machine that outlives a session (every step resumes)
    "recipe": Scale(houses=12, frames_per_house=400, epochs=16, bench_frames=30, bench_trials=3, ops_frames=200,
                    precision="auto", split_mode="house", bench_runs=3),
}


#: The paper trains the sparse model 250 epochs and the dense 200: the recipe keeps that ratio (rounded up).
SPARSE_EPOCH_RATIO = 1.25


def model_epochs(dense_epochs: int | None) -> dict[str, int | None]:
    """Training epochs of each model: the dense model's, and ceil(1.25x) for the sparse one (None: the configs')."""
    if dense_epochs is None:
        return {"dense": None, "sparse": None}
    return {"dense": dense_epochs, "sparse": math.ceil(dense_epochs * SPARSE_EPOCH_RATIO - 1e-9)}


def bench_run_args(sc: Scale) -> list[str]:
    """``--runs N`` of a ``detector bench`` whose ratios the report quotes (none for one run: the commands of the
    records made before it existed stay as logged)."""
    return ["--runs", str(sc.bench_runs)] if sc.bench_runs > 1 else []


def epochs_text(sc: Scale) -> str:
    """"dense 16 / sparse 20" (or "from the configs")."""
    e = model_epochs(sc.epochs)
    return f"dense {e['dense']} / sparse {e['sparse']}" if sc.epochs else "from the configs"


def cpu_has_native_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Whether the CPU computes bfloat16 natively (AVX512-BF16 or AMX-BF16 among /proc/cpuinfo's flags)."""
    try:
        flags = set(cpuinfo.read_text().split())
    except OSError:
        return False
    return bool(flags & {"avx512_bf16", "amx_bf16"})
