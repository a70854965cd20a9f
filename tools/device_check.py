"""The JSON / Markdown side of ``tools/device_check.sh`` (issue 32, "The GPU path, tested"): one subcommand per job.

    step NAME [--stdout FILE] [--timeout S] -- CMD ...   run one step of the check, record RESULTS/steps/NAME.json
    machine --device D --out FILE                        the GPU(s), driver, CUDA, torch and autocast dtype as JSON
    configs --out DIR [--tiny]                           the six experiment YAMLs the check runs (EXPERIMENTS)
    tests --junit XML --out FILE                         pytest's JUnit XML as JSON counts and cases
    train --config C --data D --run DIR --device D --precision fp32|autocast --steps N --out FILE
                                                         one ``detector train`` run: steps/s and peak memory
    ddp --config C --data D --run DIR --device D --steps N --out FILE
                                                         a 2-process torchrun ``detector train`` (or why not)
    report --results DIR --out DIR                       summary.json + summary.md: every result, the paper beside

Every model run goes through the ``detector`` command line (``detector train`` in this process, so that the peak
memory of the run can be read here; the rest as subprocesses). Steps run against a deadline: the shell script exports
``DEVICE_CHECK_DEADLINE`` (Unix seconds); a step that would start past it is recorded as skipped, and a running step
is stopped at it, so the whole check keeps to its time budget. Files are written with :mod:`mpchair.core.atomic`.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
import traceback
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

import yaml

from detector.config import load_experiment
from mpchair.core.atomic import write_text
from mpchair.core.config import merge_config, to_dict
from mpchair.paper import TABLE_II, TABLE_IV, ComponentTimes

if TYPE_CHECKING:  # imported where the summary is written: the step runner itself does not load torch
    from detector.bench.result import BenchResult

ROOT = Path(__file__).resolve().parents[1]
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
TINY_GRID: dict[str, dict] = {
    "mpchair": {"point_cloud_range": [0.0, -4.8, -2.0, 6.4, 4.8, 2.0], "voxel_size": [0.1, 0.1, 4.0],
                "output_shape": [96, 64], "anchor_range": [0.0, -4.8, 0.0, 6.4, 4.8, 0.0]},
    "kitti": {"point_cloud_range": [0.0, -6.4, -3.0, 12.8, 6.4, 1.0], "voxel_size": [0.16, 0.16, 4.0],
              "output_shape": [80, 80], "anchor_range": [0.0, -6.4, -1.78, 12.8, 6.4, -1.78]},
}
#: Untimed first steps of a training throughput run (the first allocates every buffer and picks kernels).
WARMUP_STEPS = 2
#: The paper's runtimes on its Desktop (an NVIDIA 2080 Ti with an AMD Ryzen 7 3700X): Table II's Desktop rows
#: (Matterport-Chair, 768 x 512) and Table IV's dense / sparse rows (KITTI, 504 x 440), from ``mpchair.paper``.
PAPER_DESKTOP: dict[str, dict[str, ComponentTimes]] = {
    "mpchair": dict(TABLE_II["desktop"]),
    "kitti": {m: TABLE_IV[m] for m in ("dense", "sparse")},
}
COMPONENT_TITLES: dict[str, str] = {"to_device": "To Device", "feature_extract": "Feature Extract",
                                    "feature_net": "Feature Net", "backbone": "Backbone", "head": "Head",
                                    "bbox_extract": "BBox Extract", "total": "Total"}
GEOMETRY: dict[str, str] = {"mpchair": "Matterport-Chair geometry",
                            "kitti": "KITTI geometry (tests/data/kitti's frames)"}
#: Table order of the training runs.
MODEL_ORDER = ("dense", "sparse", "sparse_exact")
PRECISION_ORDER = ("fp32", "autocast")


def _json(path: str | Path, obj: object) -> None:
    write_text(path, json.dumps(obj, indent=2) + "\n")


def _load(path: Path) -> dict | None:
    """A result file's JSON, or None when the step did not write it (or wrote something else)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None


# --- step ---------------------------------------------------------------------------------------------------------
def _pump(stream, sink, keep: collections.deque | None, lines: list[str] | None) -> None:
    """Copy a child's text stream to ``sink`` line by line as it comes, keeping the tail and/or every line."""
    for line in stream:
        sink.write(line)
        sink.flush()
        if keep is not None:
            keep.append(line)
        if lines is not None:
            lines.append(line)


def cmd_step(args: argparse.Namespace) -> int:
    """Run ``args.cmd`` as one step of the check: its output passes through; stdout goes to ``--stdout`` too; the
    step's status, time and (on failure) stderr tail go to ``RESULTS/steps/NAME.json``. Exit status: the child's."""
    record = {"name": args.name, "command": shlex.join(args.cmd), "seconds": 0.0, "returncode": None}
    deadline = float(os.environ.get("DEVICE_CHECK_DEADLINE", "inf"))
    left = deadline - time.time()
    if left < 5:
        record.update(status="skipped", reason="the check's time budget (--budget) was spent before this step")
        _json(Path(args.results) / "steps" / f"{args.name}.json", record)
        print(f"[{args.name}] skipped: time budget spent", file=sys.stderr)
        return 0
    print(f"[{args.name}] {record['command']}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    # its own process group, so that a timeout also ends what it started (torchrun's workers, DataLoader workers)
    proc = subprocess.Popen(args.cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            start_new_session=True)
    tail: collections.deque = collections.deque(maxlen=40)
    out_lines: list[str] = []
    pumps = [threading.Thread(target=_pump, args=(proc.stdout, sys.stdout, None, out_lines)),
             threading.Thread(target=_pump, args=(proc.stderr, sys.stderr, tail, None))]
    for t in pumps:
        t.start()
    try:
        rc = proc.wait(timeout=min(args.timeout, left))
        timed_out = False
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        rc, timed_out = proc.wait(), True
    for t in pumps:
        t.join()
    record.update(seconds=round(time.perf_counter() - t0, 2), returncode=rc,
                  status="ok" if rc == 0 and not timed_out else "failed")
    if timed_out:
        record["reason"] = f"stopped after {min(args.timeout, left):.0f} s (step timeout or the check's budget)"
    if record["status"] != "ok":
        record["stderr_tail"] = "".join(tail)[-4000:]
    if args.stdout:
        write_text(args.stdout, "".join(out_lines))
    _json(Path(args.results) / "steps" / f"{args.name}.json", record)
    return 0 if record["status"] == "ok" else (rc or 1)


# --- machine, configs, tests --------------------------------------------------------------------------------------
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
    _json(args.out, info)
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
    _json(args.out, {"total": len(cases), "passed": count["passed"], "failed": count["failed"],
                     "errors": count["error"], "skipped": count["skipped"],
                     "seconds": round(sum(c["seconds"] for c in cases), 2), "skip_reasons": dict(reasons),
                     "cases": cases})
    return 0 if count["failed"] == count["error"] == 0 else 1


# --- training throughput ------------------------------------------------------------------------------------------
def _step_records(run: Path) -> list[dict]:
    path = run / "metrics.jsonl"
    if not path.is_file():
        return []
    return [r for r in map(json.loads, path.read_text(encoding="utf-8").splitlines()) if r.get("kind") == "step"]


def _throughput(steps: list[dict], batch: int) -> dict:
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
            _json(args.out, row)
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
    steps = _step_records(run)
    row.update(_throughput(steps, row["batch_size"]), steps_done=len(steps))
    row["status"] = "ok" if code == 0 and len(steps) == args.steps else "failed"
    _json(args.out, row)
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
        _json(args.out, row)
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
    steps = _step_records(run)
    row.update(ran=True, backend="nccl" if args.device == "cuda" else "gloo", returncode=proc.returncode,
               wall_s=round(time.perf_counter() - t0, 2), steps_done=len(steps),
               loss=[r["loss_total"] for r in steps], num_pos=[r["num_pos"] for r in steps],
               step_s=[r["time_s"] for r in steps])
    row["status"] = "ok" if proc.returncode == 0 and len(steps) == args.steps else "failed"
    if row["status"] != "ok":
        row["stderr_tail"] = proc.stderr[-4000:]
    _json(args.out, row)
    return 0 if row["status"] == "ok" else 1


# --- report -------------------------------------------------------------------------------------------------------
def _md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows)]


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:,.3f}" if x < 100 else f"{x:,.1f}"


def paper_rows(bench: BenchResult, geometry: str) -> list[list[str]]:
    """Per component: the paper's Desktop dense / sparse (ms) beside ours (dense, sparse, sparse+sparse_head)."""
    ours = {name: m.mean_ms for name, m in bench.ours().items()}
    paper = PAPER_DESKTOP[geometry]
    rows = []
    for key, title in COMPONENT_TITLES.items():
        row = [title]
        for model in ("dense", "sparse"):
            cell = getattr(paper[model], key)
            row += [f"{cell.mean_ms:.3f} ± {cell.std_ms:.3f}", _ms(ours.get(model, {}).get(key))]
        row.append(_ms(ours.get("sparse+sparse_head", {}).get(key)))
        rows.append(row)
    return rows


def _machine_lines(machine: dict | None, bench: BenchResult | None) -> list[str]:
    lines = []
    if machine:
        gpus = ", ".join(f"{g['name']} ({g['memory_gib']} GiB, sm {g['capability']})" for g in machine["gpus"])
        lines.append(f"- device {machine['device']}: {gpus or 'no GPU'}; torch {machine['torch']}, CUDA "
                     f"{machine['cuda']}, autocast dtype {machine['autocast_dtype']}"
                     + (f"; nvidia-smi: {machine['nvidia_smi']}" if machine.get("nvidia_smi") else ""))
    if bench and bench.machine:
        m = bench.machine.machine
        lines.append(f"- host: {m.cpu}, {m.logical_cpus} logical CPUs, {m.torch_threads} torch threads")
    return lines


def _steps_section(steps: list[dict]) -> list[str]:
    rows = [[s["name"], s["status"], f"{s['seconds']:.1f}", s.get("reason", "")] for s in steps]
    return ["## Steps", "", *_md_table(["step", "status", "seconds", "note"], rows), ""]


def _tests_section(tests: dict | None) -> list[str]:
    if not tests:
        return ["## Tests", "", "not run", ""]
    lines = ["## Tests (tests/test_device_paths.py)", "",
             f"{tests['passed']} passed, {tests['failed']} failed, {tests['errors']} errors, {tests['skipped']} "
             f"skipped of {tests['total']} ({tests['seconds']:.1f} s)", ""]
    lines += [f"- {c['outcome']}: {c['name']}: {c['message']}" for c in tests["cases"]
              if c["outcome"] in ("failed", "error")]
    lines += [f"- skipped ({n}): {reason}" for reason, n in tests["skip_reasons"].items()]
    return lines + [""]


def _bench_section(geometry: str, bench: BenchResult | None, table_md: str | None) -> list[str]:
    if not bench:
        return [f"## Runtime, {GEOMETRY[geometry]}", "", "not run", ""]
    grid = bench.density.geometry
    cm = round(grid.voxel_size[0] * 100)
    lines = [f"## Runtime, {GEOMETRY[geometry]}: {grid.output_shape[0]} x {grid.output_shape[1]}, {cm} cm "
             "pillars", ""]
    p = bench.protocol
    lines += [f"`detector bench`, {p.frames} frames of the {p.split} split x {p.trials} trials, {p.warmup} "
              "warm-up frames, batch 1, random weights (timing only), ms per frame:", "", (table_md or "").strip(), ""]
    title = "Table II's Desktop rows" if geometry == "mpchair" else "Table IV"
    lines += [f"Beside the paper's {title} (NVIDIA 2080 Ti, AMD Ryzen 7 3700X; ms, mean ± std):", ""]
    lines += _md_table(["component", "paper dense", "ours dense", "paper sparse", "ours sparse",
                        "ours sparse+sparse_head"], paper_rows(bench, geometry))
    return lines + [""]


def _train_section(rows: list[dict]) -> list[str]:
    lines = ["## Training throughput (`detector train --max-steps`)", ""]
    if not rows:
        return lines + ["not run", ""]
    table = []
    for r in rows:
        if r.get("status") == "skipped":
            table.append([r["model"], r["precision"], str(r["batch_size"]), "-", "-", "-", "-", "-", r["reason"]])
            continue
        table.append([r["model"], r.get("autocast_dtype", r["precision"]), str(r["batch_size"]),
                      str(r.get("timed_steps", 0)), _ms(r.get("step_s_mean")), _ms(r.get("steps_per_s")),
                      _ms(r.get("samples_per_s")), _ms(r.get("peak_memory_mib")), r.get("status", "")])
    lines += _md_table(["model", "precision", "batch", "timed steps", "s / step", "steps / s", "samples / s",
                        "peak memory (MiB)", "status"], table)
    kinds = sorted({r["peak_memory_kind"] for r in rows if r.get("peak_memory_kind")})
    return lines + ["", f"Peak memory: {', '.join(kinds)}; the first {WARMUP_STEPS} steps of each run are untimed.",
                    ""]


def _eval_ddp_section(ev: dict | None, ddp: dict | None) -> list[str]:
    lines = ["## Evaluation (`detector eval` of the dense fp32 run's checkpoint, val split)", ""]
    if ev:
        chair = ev.get("Chair", {})
        lines.append(f"Chair BEV AP {chair.get('bev', {}).get('overall', {}).get('R40', float('nan')):.2f}, 3D AP "
                     f"{chair.get('3d', {}).get('overall', {}).get('R40', float('nan')):.2f} (R40, Overall; weights "
                     "of a few training steps: this checks the device path, not the accuracy)")
    else:
        lines.append("not run")
    lines += ["", "## DDP smoke test (2 processes)", ""]
    if not ddp:
        return lines + ["not run", ""]
    if not ddp.get("ran"):
        return lines + [f"skipped: {ddp['reason']}", ""]
    return lines + [f"{ddp['status']}: {ddp['backend']}, world size {ddp['world_size']}, {ddp['steps_done']} steps, "
                    f"loss {', '.join(f'{x:.4f}' for x in ddp['loss'])}", ""]


def cmd_report(args: argparse.Namespace) -> int:
    """``OUT/summary.json`` (every result file of ``RESULTS`` in one document) and ``OUT/summary.md``."""
    res, out = Path(args.results), Path(args.out)
    steps = [_load(p) for p in sorted((res / "steps").glob("*.json"), key=lambda p: p.stat().st_mtime)]
    steps = [s for s in steps if s]
    machine = _load(res / "machine.json")
    bench = {g: _load(res / f"bench_{g}.json") for g in GEOMETRY}
    train = [r for p in (res / "train").glob("*.json") if (r := _load(p))]
    train.sort(key=lambda r: (MODEL_ORDER.index(r["model"]) if r["model"] in MODEL_ORDER else len(MODEL_ORDER),
                              r["model"], PRECISION_ORDER.index(r["precision"])))
    paper = {g: {m: t.to_json() for m, t in rows.items()} for g, rows in PAPER_DESKTOP.items()}
    summary = {"dry_run": bool(machine and machine.get("dry_run")), "machine": machine, "steps": steps,
               "tests": _load(res / "tests.json"), "bench": bench, "paper_desktop": paper, "train": train,
               "eval": _load(res / "eval.json"), "ddp": _load(res / "ddp.json"),
               "failed": [s["name"] for s in steps if s["status"] == "failed"]}
    _json(out / "summary.json", summary)
    title = "# GPU check (tools/device_check.sh" + (" --dry-run: CPU, tiny grids and layers)" if summary["dry_run"]
                                                    else ")")
    from detector.bench.result import BenchResult

    results = {g: BenchResult.from_json(b) if b else None for g, b in bench.items()}  # its one reader
    any_bench = next((b for b in results.values() if b), None)
    md = [title, "", *_machine_lines(machine, any_bench), "", *_steps_section(steps), *_tests_section(summary["tests"])]
    for g in GEOMETRY:
        table = res / f"bench_{g}.md"
        md += _bench_section(g, results[g], table.read_text(encoding="utf-8") if table.is_file() else None)
    md += _train_section(train) + _eval_ddp_section(summary["eval"], summary["ddp"])
    write_text(out / "summary.md", "\n".join(md))
    print(f"wrote {out / 'summary.json'} and {out / 'summary.md'}" + (f"; failed: {', '.join(summary['failed'])}"
                                                                       if summary["failed"] else ""))
    return 0


# --- command line -------------------------------------------------------------------------------------------------
def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("step")
    s.add_argument("name")
    s.add_argument("--results", required=True)
    s.add_argument("--stdout")
    s.add_argument("--timeout", type=float, default=600.0)
    s = sub.add_parser("machine")
    s.add_argument("--device", required=True)
    s.add_argument("--dry-run", action="store_true")
    s.add_argument("--out", required=True)
    s = sub.add_parser("configs")
    s.add_argument("--out", required=True)
    s.add_argument("--tiny", action="store_true")
    s = sub.add_parser("tests")
    s.add_argument("--junit", required=True)
    s.add_argument("--out", required=True)
    for name in ("train", "ddp"):
        s = sub.add_parser(name)
        for opt in ("--config", "--data", "--run", "--device", "--out"):
            s.add_argument(opt, required=True)
        s.add_argument("--steps", type=int, required=True)
        if name == "train":
            s.add_argument("--name", required=True)
            s.add_argument("--precision", choices=["fp32", "autocast"], required=True)
    s = sub.add_parser("report")
    s.add_argument("--results", required=True)
    s.add_argument("--out", required=True)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # ``step``'s command follows ``--`` verbatim (its own options must not be parsed as the step's)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = parser().parse_args(argv[:cut])
    args.cmd = argv[cut + 1 :]
    if args.command == "step" and not args.cmd:
        print("error: step needs a command after --", file=sys.stderr)
        return 2
    run = {"step": cmd_step, "machine": cmd_machine, "configs": cmd_configs, "tests": cmd_tests, "train": cmd_train,
           "ddp": cmd_ddp, "report": cmd_report}[args.command]
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
