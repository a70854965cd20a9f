"""How long a reproduction will take on this machine, printed before it starts.

The source is measured, never guessed: the run record's ``commands.log`` (the wall time of every command a recorded
reproduction ran, e.g. ``docs/results-data``), each command's latest time counted once, grouped by step, scaled

* to the planned scale's sizes (frames, epochs, timed frames x trials, ...: :func:`size_ratio`), and
* to this machine's speed: a short GEMM probe (:func:`probe_seconds`, about a second) timed here and, when the record
  holds one (``results/probe.json``, written by every reproduction as it starts), on the recorded machine. A record
  without a probe scales only where this CPU is the recorded one (same model, same CPU count); elsewhere it says that
  its times are the recorded machine's. A training the record ran in bf16 that runs in fp32 here (no native bf16)
  is multiplied by :data:`FP32_OVER_BF16_STEP`, the measured ratio of the dense CPU config's step times.

It is an estimate: step times drift with the machine's load (docs/benchmarks.md), so the printed line says what it
was computed from.
"""

from __future__ import annotations

import json
import os
import shlex
import statistics
import time
from dataclasses import dataclass, fields
from pathlib import Path

from detector.train.metrics import format_duration
from reproduction.results import ABLATIONS
from reproduction.runner import logged_commands
from reproduction.scales import Scale, model_epochs

#: Where a reproduction writes this machine's probe time (inside ``results/``, so that the record keeps it).
PROBE_FILE = Path("results") / "probe.json"
#: A dense training step of ``mpchair_dense_cpu.yaml`` on 2 cores: ~1.75 s in fp32 on an AVX2-only EPYC against
#: ~0.25 s in bf16 on an AVX512-BF16 one (docs/benchmarks.md, "Training"): a bf16-recorded training run in fp32.
FP32_OVER_BF16_STEP = 1.75 / 0.25
#: bench_density.py's densities when the scale names none (its default eight).
DEFAULT_CURVE_DENSITIES = 8


def probe_seconds(threads: int, repeats: int = 5) -> float:
    """Median seconds of a fixed fp32 GEMM workload (10 products of a 4096 x 512 by a 512 x 128 matrix, about the
    shape of a pillar backbone's convolution GEMMs) on ``threads`` torch threads, after two untimed runs: a measure of
    this machine's speed, compared between machines, not a model's time."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(max(1, threads))
    try:
        gen = torch.Generator().manual_seed(0)
        a, b = torch.randn(4096, 512, generator=gen), torch.randn(512, 128, generator=gen)
        times = []
        for k in range(repeats + 2):
            t0 = time.perf_counter()
            for _ in range(10):
                torch.mm(a, b)
            if k >= 2:
                times.append(time.perf_counter() - t0)
        return statistics.median(times)
    finally:
        torch.set_num_threads(before)


def this_machine() -> dict:
    """The CPU model, logical CPU count and native-bf16 flag of this machine (as ``detector bench`` records them: a
    model name such as "AMD EPYC" covers CPUs with and without AVX512-BF16)."""
    from detector.device import cpu_model
    from reproduction.scales import cpu_has_native_bf16

    return {"cpu": cpu_model(), "logical_cpus": os.cpu_count(), "bf16": cpu_has_native_bf16()}


def write_probe(out: Path, threads: int) -> dict:
    """``out/results/probe.json`` = this machine and its :func:`probe_seconds` at ``threads``; an existing one (this
    work folder's earlier machine, or a restored record's) is kept, since its steps' times are that machine's."""
    path = out / PROBE_FILE
    if path.is_file():
        return json.loads(path.read_text())
    from mpchair.core.atomic import write_text

    probe = {**this_machine(), "threads": threads, "probe_s": probe_seconds(threads)}
    write_text(path, json.dumps(probe, indent=1) + "\n")
    return probe


# --- the record's measured times ----------------------------------------------------------------------------------


def command_step(line: str) -> tuple[str, str] | None:
    """``(step, size kind)`` of one commands.log command line (None: not a reproduction step's). The kind says what
    its time grows with (:func:`size_ratio`)."""
    words = line.split()
    if "synth" in words and any(w.endswith("mpchair") for w in words):
        return "synth", "houses"
    if "generate" in words:
        return "generate", "frames"
    if "stats" in words:
        return "stats", "frames"
    ablation = any(a in line for a in ABLATIONS)
    if "train" in words:
        return ("ablations" if ablation else "train"), "train"
    if "eval" in words:
        if ablation:
            return "ablations", "frames"
        return ("deploy" if "--runtime" in words else "eval"), "frames"
    if "bench" in words:
        if "--rate" in words:
            return "deploy", "budget"
        if "--runtime" in words:
            return "deploy", "bench"
        if "kitti_car_dense.yaml" in line or "sparse1_dense23" in line:
            return "ablation-bench", "bench"
        return "bench", "bench"
    if "bench_reference_head.py" in line:
        return "refhead", "bench"
    if "bench_density.py" in line:
        return "curve", "curve"
    if "ops" in words:
        return "ops", "ops"
    if "viz-sparsity" in words:
        return "viz", "fixed"
    return None


def _command_key(line: str) -> str:
    """What a command makes (its ``> FILE`` or ``--out`` / ``--json-out`` target): a command re-run later (a resumed or
    forced step) is the same key, and only its latest time counts."""
    command = line.split(" s  ", 1)[-1]
    try:
        words = shlex.split(command)
    except ValueError:
        words = command.split()
    for flag in (">", "--out", "--json-out", "--json"):
        if flag in words[:-1]:
            return words[words.index(flag) + 1]
    return command


@dataclass(frozen=True)
class RecordedTimes:
    """A record's measured times: ``seconds[(step, kind)]`` (each command's latest time, summed), the scale it ran
    at, its training precision, its machine and probe (None where it holds none)."""

    seconds: dict[tuple[str, str], float]
    scale: Scale
    machine: dict
    probe_s: float | None
    source: str


def recorded_times(record: Path) -> RecordedTimes | None:
    """The measured times of the record folder ``record`` (None when it has no commands.log or record.json)."""
    log, meta_path = record / "commands.log", record / "record.json"
    if not log.is_file() or not meta_path.is_file():
        return None
    meta = json.loads(meta_path.read_text())
    sizes = {k: v for k, v in meta.get("scale_sizes", {}).items() if k in {f.name for f in fields(Scale)}}
    if sizes.get("curve_densities") is not None:
        sizes["curve_densities"] = tuple(sizes["curve_densities"])
    try:
        scale = Scale(**sizes)
    except TypeError:
        return None
    latest: dict[str, tuple[tuple[str, str], float]] = {}
    for seconds, line in logged_commands(log.read_text()):
        step = command_step(line)
        if step is not None:
            latest[_command_key(line)] = (step, seconds)
    totals: dict[tuple[str, str], float] = {}
    for step, seconds in latest.values():
        totals[step] = totals.get(step, 0.0) + seconds
    probe = record / PROBE_FILE
    probe_data = json.loads(probe.read_text()) if probe.is_file() else {}
    machine = probe_data or _bench_machine(record)
    return RecordedTimes(totals, scale, machine, probe_data.get("probe_s"), str(record))


def _bench_machine(record: Path) -> dict:
    """The machine a record's bench step ran on (``results/bench_default.json``), or {}."""
    bench = record / "results" / "bench_default.json"
    if not bench.is_file():
        return {}
    machine = json.loads(bench.read_text()).get("machine", {})
    flags = machine.get("precision_flags") or {}
    return {"cpu": machine.get("cpu"), "logical_cpus": machine.get("logical_cpus"),
            "bf16": bool(flags.get("bf16")) if "bf16" in flags else None}


# --- scaling ------------------------------------------------------------------------------------------------------


def _frames(sc: Scale) -> int:
    return sc.houses * sc.frames_per_house


def _curve(sc: Scale) -> int:
    densities = len(sc.curve_densities) if sc.curve_densities else DEFAULT_CURVE_DENSITIES
    return sc.curve_frames * sc.curve_trials * densities + sc.curve_real_frames


def size_ratio(kind: str, planned: Scale, recorded: Scale) -> float | None:
    """How many times the recorded time a step of size ``kind`` takes at the ``planned`` scale (None: unknown, e.g. a
    training whose length is not a number of epochs)."""
    if kind == "houses":
        return planned.houses / recorded.houses
    if kind == "frames":
        return _frames(planned) / _frames(recorded)
    if kind == "train":
        if not isinstance(planned.epochs, int) or not isinstance(recorded.epochs, int):
            return None
        epochs = model_epochs(planned.epochs)["dense"] / model_epochs(recorded.epochs)["dense"]
        return _frames(planned) / _frames(recorded) * epochs
    if kind == "bench":
        return planned.bench_frames * planned.bench_trials / (recorded.bench_frames * recorded.bench_trials)
    if kind == "ops":
        return planned.ops_frames / recorded.ops_frames
    if kind == "curve":
        return _curve(planned) / _curve(recorded)
    if kind == "budget":
        return planned.budget_seconds / recorded.budget_seconds
    return 1.0


@dataclass(frozen=True)
class Estimate:
    """Seconds per step (None: not estimated), and the sentence saying what the numbers come from."""

    seconds: dict[str, float | None]
    basis: str

    @property
    def total(self) -> float:
        return sum(s for s in self.seconds.values() if s is not None)


def estimate(rec: RecordedTimes, planned: Scale, steps: list[str], here: dict, probe_here: float | None) -> Estimate:
    """The seconds each of ``steps`` will take at the ``planned`` scale on the machine ``here`` (its CPU model and
    count) whose probe took ``probe_here`` s, from the record's times ``rec``."""
    if rec.probe_s and probe_here:
        speed = probe_here / rec.probe_s
        machine = (f"this machine's GEMM probe {probe_here:.2f} s against {rec.probe_s:.2f} s on the recorded one "
                   f"(x{speed:.2f})")
    elif rec.machine and all(rec.machine.get(k) == here.get(k) for k in ("cpu", "logical_cpus")) and (
            rec.machine.get("bf16") is None or here.get("bf16") is None or rec.machine["bf16"] == here["bf16"]):
        speed, machine = 1.0, f"the same CPU as the record's ({here['cpu']}, {here['logical_cpus']} CPUs)"
    else:
        speed = 1.0
        def cpu(m: dict) -> str:
            bf16 = {True: ", native bf16", False: ", no native bf16"}.get(m.get("bf16"), "")
            return f"{m.get('cpu') or 'another CPU'} ({m.get('logical_cpus', '?')} CPUs{bf16})"

        machine = (f"not scaled to this machine: the record ran on {cpu(rec.machine)} and holds no probe time; this "
                   f"one is {cpu(here)}")
    # None: the configs' precision, which the CPU configs leave at the schema's fp32
    slower_training = rec.scale.precision == "bf16" and (planned.precision or "fp32") == "fp32"
    seconds: dict[str, float | None] = {}
    for (step, kind), recorded in rec.seconds.items():
        if step not in steps:
            continue
        ratio = size_ratio(kind, planned, rec.scale)
        if ratio is None:
            seconds[step] = None
            continue
        if kind == "train" and slower_training:
            ratio *= FP32_OVER_BF16_STEP
        if kind == "bench" and step in ("bench", "deploy"):  # the benches that run --bench-runs processes
            ratio *= planned.bench_runs / rec.scale.bench_runs
        seconds[step] = (seconds.get(step) or 0.0) + recorded * ratio * speed
    precision = (f"; trainings x{FP32_OVER_BF16_STEP:.0f} for fp32 here against the record's bf16 (dense step 1.75 s "
                 "vs 0.25 s, docs/benchmarks.md)" if slower_training else "")
    basis = (f"from the record {rec.source} (commands.log: each command's latest wall time), scaled to this scale's "
             f"sizes; {machine}{precision}")
    return Estimate(seconds, basis)


def estimate_lines(est: Estimate, done: set[str]) -> list[str]:
    """The lines printed before a reproduction starts: the total of the steps still to run, each step's share, and
    where the numbers come from."""
    todo = {s: v for s, v in est.seconds.items() if s not in done}
    if not todo:
        return ["estimate: every step asked for is done already (--force redoes them)"]
    parts = ", ".join(f"{s} {'?' if v is None else format_duration(v)}" for s, v in todo.items())
    unknown = [s for s, v in todo.items() if v is None]
    total = sum(v for v in todo.values() if v is not None)
    return [f"estimate: ~{format_duration(total)} on this machine" + (f" plus {', '.join(unknown)}" if unknown else "")
            + f" ({parts})", f"  {est.basis}; an estimate: sizes scale linearly, so a small scale's fixed costs "
            "(start-up, model builds, exports) and a loaded machine make it longer"]
