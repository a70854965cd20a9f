"""The robot's CPU budget (the paper's conclusion: "1 Hz with more than 75 % of the CPU left"): a model run at a fixed
sensor rate, and what it costs.

Every model x runtime x precision runs on its own, in a fresh process (as a robot runs one detector), on ``threads``
threads: a few warm-up frames, then a sensor that releases a frame every ``1 / rate`` seconds for ``duration``
seconds. The detector takes the newest released frame whenever it is free (older frames it could not start are
dropped, as a robot drops stale scans), runs the whole pipeline on it (voxelization to boxes), and sleeps until the
next release when it is ahead. Per row:

- ``cpu_share``: the process's CPU time (user + system, every thread, ``time.process_time``) over the window's wall
  time and the usable cores: 0.25 = a quarter of the machine;
- ``deadline_misses``: processed frames whose latency (release → detections) exceeded the period, and ``dropped``
  frames never started;
- ``latency_ms`` p50 / p95 (release → detections) and ``service_ms`` p50 / p95 (start → detections);
- ``peak_rss_mb``: the process's peak resident set during the window (``VmHWM``, reset at its start);
- ``max_rate_hz_at_25pct``: the highest rate whose CPU stays within 25 % of the machine at this frame cost
  (``0.25 * cores / cpu seconds per frame``), capped at ``1 / service p95`` (a rate the detector cannot keep up with
  is no budget).
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from detector.bench.result import Skipped
from detector.bench.run import (
    BenchModel,
    Variant,
    build_rows,
    check_variant,
    density_record,
    display_names,
    machine_record,
)
from detector.config import load_experiment
from detector.deploy.cpu import cpu_flags, skip_reason
from detector.deploy.deployed import graph_work_dir
from detector.device import peak_memory_bytes, reset_peak_memory, usable_cores, use_device
from detector.ops.gemm import current_backend, gemm_backend
from mpchair.core.errors import InputError

#: The CPU share the docs' "highest rate within budget" column allows (the paper's "more than 75 % left").
BUDGET_SHARE = 0.25


def fixed_rate(run: Callable[[np.ndarray], object], frames: Sequence[np.ndarray], rate: float, duration: float,
               cores: int, clock: Callable[[], float] = time.perf_counter,
               cpu_clock: Callable[[], float] = time.process_time,
               sleep: Callable[[float], None] = time.sleep) -> dict:
    """Run ``run`` on ``frames`` (cycled) at a sensor ``rate`` (Hz) for ``duration`` s on a machine of ``cores``
    cores; returns the budget fields of the module docstring (without ``peak_rss_mb``). The clocks are parameters so
    the schedule's arithmetic can be checked on a simulated clock."""
    period = 1.0 / rate
    released = max(1, int(round(duration * rate)))
    latency, service = [], []
    misses = 0
    k = 0
    cpu0, t0 = cpu_clock(), clock()
    while k < released:
        release = t0 + k * period
        now = clock()
        if now < release:
            sleep(release - now)
        start = clock()
        run(frames[k % len(frames)])
        end = clock()
        latency.append(end - release)
        service.append(end - start)
        misses += int(end - release > period)
        # the newest frame released by now is the next one; those between are dropped
        k = max(k + 1, int((end - t0) / period))
    window_end = t0 + released * period
    now = clock()
    if now < window_end:  # the rest of the window is idle time the robot gets back
        sleep(window_end - now)
    wall = max(clock(), window_end) - t0
    cpu = cpu_clock() - cpu0
    processed = len(latency)
    cpu_per_frame = cpu / processed
    service_p95 = float(np.percentile(service, 95))
    rate25 = BUDGET_SHARE * cores / cpu_per_frame if cpu_per_frame > 0 else float("inf")
    return {
        "rate_hz": rate, "duration_s": duration, "cores": cores, "released": released, "processed": processed,
        "dropped": released - processed, "deadline_misses": misses, "wall_s": wall, "cpu_s": cpu,
        "cpu_share": cpu / wall / cores, "cpu_ms_per_frame": cpu_per_frame * 1e3,
        "latency_ms": {"p50": float(np.percentile(latency, 50)) * 1e3, "p95": float(np.percentile(latency, 95)) * 1e3},
        "service_ms": {"p50": float(np.percentile(service, 50)) * 1e3, "p95": service_p95 * 1e3},
        "max_rate_hz_at_25pct": min(rate25, 1.0 / service_p95) if service_p95 > 0 else rate25,
    }


def _budget_row(model: BenchModel, runtime: str, precision: str, data_dir: str, split: str, frames: int,
                threads: int, seed: int, variant: Variant, rate: float, duration: float, warmup: int,
                gemm: str = "auto") -> dict:
    """One row in this (fresh) process, under the parent's GEMM library ``gemm`` (a spawned process starts outside
    its :func:`detector.ops.gemm.gemm_backend` block): its record (:func:`_row_record`) and, under ``"warnings"``,
    the text of each Python warning it raised: the parent raises them again, so that the command prints them as its
    own one-line ``warning:`` lines instead of the fresh interpreter printing each with its source line."""
    with gemm_backend(gemm), warnings.catch_warnings(record=True) as held:
        warnings.simplefilter("always")
        record = _row_record(model, runtime, precision, data_dir, split, frames, threads, seed, variant, rate,
                             duration, warmup)
    return {**record, "warnings": list(dict.fromkeys(str(w.message) for w in held))}


def _row_record(model: BenchModel, runtime: str, precision: str, data_dir: str, split: str, frames: int,
                threads: int, seed: int, variant: Variant, rate: float, duration: float, warmup: int) -> dict:
    """One row in this (fresh) process: build it, warm up, run :func:`fixed_rate`; its record."""
    dev = use_device("cpu", threads)
    one = replace(variant, runtimes=(runtime,), precisions=(precision,))
    with graph_work_dir("detector-budget-") as work:
        rows, nets, _ = build_rows([model], dev, data_dir, split, frames, seed, False, one, work)
        row, net = rows[0], nets[0]
        points = [f.points for f in row.frames]

        def run(pts: np.ndarray) -> None:
            import torch

            with torch.no_grad():
                net.predict([torch.from_numpy(pts)])

        for i in range(warmup):
            run(points[i % len(points)])
        reset_peak_memory("cpu")
        record = fixed_rate(run, points, rate, duration, usable_cores())
        peak = peak_memory_bytes("cpu")
    return {"name": row.name, "runtime": runtime, "precision": precision, "config": str(model.config),
            "weights": row.weights, "backbone": row.cfg.model.backbone, "head": row.cfg.model.head,
            "threads": threads, **record, "peak_rss_mb": None if peak is None else peak / 2**20,
            "density": density_record(row).to_json()}


def run_budget(models: Sequence[BenchModel], data_dir: str | Path, *, rate: float, duration: float,
               split: str = "test", frames: int = 20, warmup: int = 3, threads: int = 1, seed: int = 0,
               variant: Variant = Variant()) -> dict:
    """Every model x runtime x precision at ``rate`` Hz for ``duration`` s, one fresh process each (see the module):
    ``{"budget": [row records], "skipped": [...], "density": {...}, "machine": {...}, "protocol": {...}}``."""
    if not models:
        raise InputError("bench needs at least one --config")
    if rate <= 0 or duration <= 0 or frames < 1 or warmup < 0 or threads < 1:
        raise InputError(f"need --rate > 0, --duration > 0, --frames >= 1, --warmup >= 0, --threads >= 1 (got "
                         f"{rate}, {duration}, {frames}, {warmup}, {threads})")
    check_variant(variant, "cpu")
    rows: list[dict] = []
    skipped: list[dict] = []
    names = display_names(models, [load_experiment(m.config) for m in models])
    flags = cpu_flags()
    # spawn, not fork: a fresh interpreter per row, so its CPU time, threads and peak memory are its own
    context = multiprocessing.get_context("spawn")
    for model, name in zip(models, names):
        for runtime in variant.runtimes:
            for precision in variant.precisions:
                why = skip_reason(runtime, precision, flags)
                if why is not None:  # decided here: no process to start for it
                    skipped.append(asdict(Skipped(name, runtime, precision, why)))
                    continue
                with concurrent.futures.ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
                    rec = pool.submit(_budget_row, replace(model, name=name), runtime, precision, str(data_dir),
                                      split, frames, threads, seed, variant, rate, duration, warmup,
                                      current_backend()).result()
                for text in rec.pop("warnings"):
                    warnings.warn(text, stacklevel=2)
                rows.append(rec)
    if not rows:
        raise InputError("every model x runtime x precision asked for is skipped on this CPU: "
                         + "; ".join(f"{s['name']} {s['runtime']} {s['precision']}: {s['reason']}" for s in skipped))
    density = rows[0]["density"]
    for r in rows:
        del r["density"]
    return {
        "budget": rows,
        "skipped": skipped,
        "density": density,
        "machine": machine_record(use_device("cpu", threads), None, variant).to_json(),
        "protocol": {"data": str(data_dir), "split": split, "frames": frames, "warmup": warmup, "rate_hz": rate,
                     "duration_s": duration, "threads": threads, "budget_share": BUDGET_SHARE,
                     "process": "one fresh process per row (spawn)", "policy": "newest released frame; "
                     "older unstarted frames dropped", "runtimes": list(variant.runtimes),
                     "precisions": list(variant.precisions)},
    }

