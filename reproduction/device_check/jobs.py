"""The GPU check's jobs that each write one result file: the machine, the configs the check runs, the tests' JUnit
XML as JSON, and the training throughput runs (one process, then two under torchrun)."""

from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
import traceback
import xml.etree.ElementTree as ET
from pathlib import Path

import yaml

from detector.config import load_experiment
from mpchair.core.atomic import write_text
from mpchair.core.config import merge_config, to_dict
from reproduction.checkout import ROOT
from reproduction.device_check.files import write_json

#: The check's experiments: name → (packaged config, overrides). The KITTI geometry has no exact-head config of its
#: own; its sparse config with ``head: sparse_exact`` is what mpchair_sparse_exact.yaml is to mpchair_sparse.yaml.
EXPERIMENTS: dict[str, tuple[str, dict]] = {
    "mpchair_dense": ("mpchair_dense", {}),
    "mpchair_sparse": ("mpchair_sparse", {}),
    "mpchair_sparse_exact": ("mpchair_sparse_exact", {}),
    "kitti_car_dense": ("kitti_car_dense", {}),
    "kitti_car_sparse": ("kitti_car_sparse", {}),
    "kitti_car_sparse_exact": ("kitti_car_sparse", {"model": {"head": "sparse_exact"}}),
}
#: ``--dry-run``'s models: the same configs on a small grid (6 x 10 m of a room, 13 x 13 m of a road) with slim
#: layers and batch 1, so that a CPU runs every step in seconds; voxelizer, anchors, head and losses are unchanged.
TINY: dict = {"model": {"pfn_channels": 32, "layer_channels": [32, 32, 64], "layer_nums": [1, 1, 1],
                        "neck_channels": [32, 32, 32], "max_pillars_train": 6144, "max_pillars_test": 6144},
              "train": {"batch_size": 1}}
#: ``--dry-run``'s grids, per geometry.
TINY_GRID: dict[str, dict] = {
    "mpchair": {"point_cloud_range": [0.0, -4.8, -2.0, 6.4, 4.8, 2.0], "voxel_size": [0.1, 0.1, 4.0],
                "output_shape": [96, 64], "anchor_range": [0.0, -4.8, 0.0, 6.4, 4.8, 0.0]},
    "kitti": {"point_cloud_range": [0.0, -6.4, -3.0, 12.8, 6.4, 1.0], "voxel_size": [0.16, 0.16, 4.0],
              "output_shape": [80, 80], "anchor_range": [0.0, -6.4, -1.78, 12.8, 6.4, -1.78]},
}
#: Untimed first steps of a training throughput run (the first allocates every buffer and picks kernels).
WARMUP_STEPS = 2


def cmd_machine(args: argparse.Namespace) -> int:
    """What the device results depend on, beyond the CPU line ``detector bench`` records itself."""
    import platform

    import torch

    from detector.device import autocast_dtype

    dev = torch.device(args.device)
    info = {"device": args.device, "dry_run": args.dry_run, "torch": torch.__version__, "cuda": torch.version.cuda,
            "python": platform.python_version(), "cuda_available": torch.cuda.is_available(),
            "gpu_count": torch.cuda.device_count() if torch.cuda.is_available() else 0, "gpus": [],
            "autocast_dtype": None, "nvidia_smi": None}
    if dev.type == "cpu" or torch.cuda.is_available():
        info["autocast_dtype"] = str(autocast_dtype(dev)).replace("torch.", "")
    for i in range(info["gpu_count"]):
        p = torch.cuda.get_device_properties(i)
        info["gpus"].append({"name": p.name, "memory_gib": round(p.total_memory / 2**30, 1),
                             "capability": f"{p.major}.{p.minor}", "multiprocessors": p.multi_processor_count})
    if info["gpu_count"]:
        info["cudnn"] = torch.backends.cudnn.version()
        info["tf32"] = {"cudnn": torch.backends.cudnn.allow_tf32, "matmul": torch.backends.cuda.matmul.allow_tf32}
    if shutil.which("nvidia-smi"):
        q = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                           capture_output=True, text=True, timeout=60)
        info["nvidia_smi"] = q.stdout.strip() or q.stderr.strip()
    write_json(args.out, info)
    return 0


def cmd_configs(args: argparse.Namespace) -> int:
    """Write the :data:`EXPERIMENTS` as ``OUT/<name>.yaml``, loaded and validated with their overrides
    (``--tiny``: with :data:`TINY` and the geometry's :data:`TINY_GRID` on top) and written out in full."""
    out = Path(args.out)
    for name, (source, overrides) in EXPERIMENTS.items():
        changes = [overrides]
        if args.tiny:
            changes += [TINY, {"model": TINY_GRID[name.split("_")[0]]}]
        merged: dict = {}
        for change in changes:
            merged = merge_config(merged, change)
        cfg = load_experiment(source, overrides=merged)
        said = "; ".join(f"{s}.{k} = {v}" for c in changes for s, vals in c.items() for k, v in vals.items())
        head = f"# Written by tools/device_check.py from the packaged config {source}" + (f"; {said}" if said else "")
        write_text(out / f"{name}.yaml", head + "\n" + yaml.safe_dump(to_dict(cfg), sort_keys=False))
    return 0


def cmd_tests(args: argparse.Namespace) -> int:
    """pytest's JUnit XML → ``{"total", "passed", "failed", "errors", "skipped", "seconds", "skip_reasons",
    "cases": [{"name", "outcome", "seconds", "message"}]}``."""
    root = ET.parse(args.junit).getroot()
    cases = []
    for case in root.iter("testcase"):
        outcome, message = "passed", ""
        for kind in ("failure", "error", "skipped"):
            el = case.find(kind)
            if el is not None:
                outcome, message = {"failure": "failed", "error": "error", "skipped": "skipped"}[kind], \
                    (el.get("message") or "")[:500]
                break
        cases.append({"name": f"{case.get('classname')}::{case.get('name')}", "outcome": outcome,
                      "seconds": float(case.get("time", 0)), "message": message})
    count = collections.Counter(c["outcome"] for c in cases)
    reasons = collections.Counter(c["message"] for c in cases if c["outcome"] == "skipped")
    write_json(args.out, {"total": len(cases), "passed": count["passed"], "failed": count["failed"],
                     "errors": count["error"], "skipped": count["skipped"],
                     "seconds": round(sum(c["seconds"] for c in cases), 2), "skip_reasons": dict(reasons),
                     "cases": cases})
    return 0 if count["failed"] == count["error"] == 0 else 1


def step_records(run: Path) -> list[dict]:
    path = run / "metrics.jsonl"
    if not path.is_file():
        return []
    return [r for r in map(json.loads, path.read_text(encoding="utf-8").splitlines()) if r.get("kind") == "step"]


def throughput(steps: list[dict], batch: int) -> dict:
    """Seconds per optimiser step (``detector train``'s ``time_s``: batch to device, forward, loss, backward, step;
    data loading excluded) after :data:`WARMUP_STEPS`, as mean / median / steps per second / samples per second."""
    times = [r["time_s"] for r in steps][WARMUP_STEPS:] or [r["time_s"] for r in steps][-1:]
    if not times:
        return {"timed_steps": 0}
    mean = statistics.fmean(times)
    return {"timed_steps": len(times), "step_s_mean": mean, "step_s_median": statistics.median(times),
            "steps_per_s": 1.0 / mean if mean > 0 else None, "samples_per_s": batch / mean if mean > 0 else None,
            "last_loss": steps[-1]["loss_total"]}


def cmd_train(args: argparse.Namespace) -> int:
    """One ``detector train --max-steps`` run in this process; its throughput and peak memory as JSON."""
    import torch

    from detector.cli import main as detector_main
    from detector.device import autocast_dtype, peak_memory_bytes, reset_peak_memory

    dev = torch.device(args.device)
    row = {"model": args.name, "config": str(args.config), "device": args.device, "precision": args.precision,
           "batch_size": load_experiment(args.config).train.batch_size, "steps": args.steps}
    precision = "fp32"
    if args.precision == "autocast":
        if autocast_dtype(dev) != torch.bfloat16:
            row.update(status="skipped", reason=f"{torch.cuda.get_device_name(dev)} has no native bfloat16 and "
                       "detector train's autocast is bf16 only (fp16 needs a GradScaler it does not have)")
            write_json(args.out, row)
            return 0
        precision = row["autocast_dtype"] = "bf16"
    run = Path(args.run)
    shutil.rmtree(run, ignore_errors=True)  # a fresh run each time: scratch under the check's work folder
    reset_peak_memory(dev)
    t0 = time.perf_counter()
    try:
        detector_main(["train", "--config", str(args.config), "--data", str(args.data), "--out", str(run),
                       "--max-steps", str(args.steps), "--device", args.device, "--precision", precision,
                       "--no-progress"])
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except Exception as e:  # a crash inside the run (a kernel, the device): recorded, then the traceback
        code, row["error"] = 1, f"{type(e).__name__}: {e}"[:2000]
        traceback.print_exc()
    peak = peak_memory_bytes(dev)
    row.update(wall_s=round(time.perf_counter() - t0, 2), returncode=code,
               peak_memory_mib=None if peak is None else round(peak / 2**20, 1),
               peak_memory_kind="torch.cuda.max_memory_allocated" if dev.type == "cuda" else "process peak RSS")
    if dev.type == "cuda":
        row["peak_reserved_mib"] = round(torch.cuda.max_memory_reserved(dev) / 2**20, 1)
    steps = step_records(run)
    row.update(throughput(steps, row["batch_size"]), steps_done=len(steps))
    row["status"] = "ok" if code == 0 and len(steps) == args.steps else "failed"
    write_json(args.out, row)
    return 0 if row["status"] == "ok" else 1


def cmd_ddp(args: argparse.Namespace) -> int:
    """A 2-process ``torchrun ... detector train`` (nccl on 2 GPUs, gloo on the CPU), or why it did not run."""
    import torch

    world = 2
    have = torch.cuda.device_count() if args.device == "cuda" else world
    row: dict = {"device": args.device, "world_size": world, "config": str(args.config), "steps": args.steps}
    if have < world:
        row.update(ran=False, status="skipped",
                   reason=f"{have} CUDA device(s) here; the DDP smoke test needs {world} (one process per GPU)")
        write_json(args.out, row)
        return 0
    run = Path(args.run)
    shutil.rmtree(run, ignore_errors=True)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={world}", "-m",
           "detector", "train", "--config", str(args.config), "--data", str(args.data), "--out", str(run),
           "--max-steps", str(args.steps), "--device", args.device, "--no-progress"]
    env = dict(os.environ)
    if args.device == "cpu":
        cmd += ["--threads", "1"]
        env["OMP_NUM_THREADS"] = "1"
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
    steps = step_records(run)
    row.update(ran=True, backend="nccl" if args.device == "cuda" else "gloo", returncode=proc.returncode,
               wall_s=round(time.perf_counter() - t0, 2), steps_done=len(steps),
               loss=[r["loss_total"] for r in steps], num_pos=[r["num_pos"] for r in steps],
               step_s=[r["time_s"] for r in steps])
    row["status"] = "ok" if proc.returncode == 0 and len(steps) == args.steps else "failed"
    if row["status"] != "ok":
        row["stderr_tail"] = proc.stderr[-4000:]
    write_json(args.out, row)
    return 0 if row["status"] == "ok" else 1
