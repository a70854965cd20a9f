"""The benchmark result as the paper's runtime tables: mean ± std ms per model, ratio rows, notes (text or Markdown).

Reads only the result of :func:`detector.bench.run.run_bench` (a :class:`detector.bench.result.BenchResult`, or the
same read back from ``detector bench --json`` with ``BenchResult.from_json``), so a saved result can be re-printed.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence

from detector.bench.result import BenchResult, ModelResult, Stat
from detector.bench.timing import COMPONENTS, SHARED, TITLES
from detector.device import Machine


def _fmt(x: float) -> str:
    return f"{x:,.3f}" if x < 100 else f"{x:,.1f}"


def ratio_rows(result: BenchResult, section: str = "components") -> list[tuple[str, dict[str, float]]]:
    """Per-component speed-ups: within each runtime x precision, ``first / other`` for every one of our models after
    the first of that group (dense / sparse: > 1 means sparse faster; one group without ``--runtime`` /
    ``--precision``), then ``peer / ours`` for every one of our models (> 1 means ours is faster than the peer).
    ``section="back_to_back"``: the same for the :data:`SHARED` components timed back to back (ours only). Across
    runtimes and precisions the result's ``headline`` compares the fastest rows (:func:`headline_line`)."""
    ours = [m for m in result.models if not m.peer]
    peers = [m for m in result.models if m.peer]
    groups: dict[tuple[str, str], list[ModelResult]] = {}
    for m in ours:
        groups.setdefault((m.runtime, m.precision), []).append(m)
    pairs = [(g[0], m) for g in groups.values() for m in g[1:]]
    if section == "components":
        pairs += [(p, m) for p in peers for m in ours]
    rows = []
    for a, b in pairs:
        sa, sb = getattr(a, section), getattr(b, section)
        if not sa or not sb:
            continue
        r = {}
        for key in sa:
            ta, tb = sa[key].mean_ms, sb[key].mean_ms
            r[key] = ta / tb if tb > 0 else math.inf
        rows.append((f"{a.name} / {b.name}", r))
    return rows


def machine_line(mach: Machine) -> str:
    """One line describing the machine of a result (its :class:`detector.device.Machine` record)."""
    line = (f"machine: {mach.cpu}, {mach.torch_threads} torch threads of {mach.logical_cpus} CPUs, "
            f"torch {mach.torch}, device {mach.device}")
    if mach.gpu:
        line += f" ({mach.gpu})"
    if mach.loadavg_1m is not None:
        line += f", load average {mach.loadavg_1m:.2f} when it ended"
    return line


def format_table(result: BenchResult, markdown: bool = False) -> str:
    """The paper-shaped table: one row per model (mean ± std ms), one ratio row per further model; then the shared
    components timed back to back (same shape), then notes."""
    lines = _table(result, "components", COMPONENTS, markdown)
    if any(m.back_to_back for m in result.models):
        title = (f"{' and '.join(TITLES[k] for k in SHARED)} timed back to back (every model's, on its own maps, order "
                 "rotated per frame; the components' own cost, to compare between models):")
        title_lines = [title] if markdown else textwrap.wrap(title, 118)
        lines += ["", *title_lines, ""] + _table(result, "back_to_back", SHARED, markdown)
    headline = headline_line(result)
    if headline:
        lines += ["", headline]
    prefix = "- " if markdown else ""
    return "\n".join(lines) + "\n\n" + "\n".join(prefix + n for n in _notes(result))


def headline_line(result: BenchResult) -> str | None:
    """The like-for-like headline of a result with several runtimes or precisions: fastest sparse row vs fastest
    dense row (and vs the fastest fp32 dense row); None for a result without it (eager fp32 only, or one kind)."""
    h = result.headline
    runs = {(m.runtime, m.precision) for m in result.models if not m.peer}
    if not h or runs == {("torch", "fp32")}:
        return None
    line = (f"headline: fastest sparse {h.fastest_sparse} ({_fmt(h.sparse_total_ms)} ms) vs fastest dense "
            f"{h.fastest_dense} ({_fmt(h.dense_total_ms)} ms): {h.speedup:.2f}x")
    if h.fastest_fp32_dense != h.fastest_dense:
        line += (f"; vs the fastest fp32 dense {h.fastest_fp32_dense} ({_fmt(h.fp32_dense_total_ms)} ms): "
                 f"{h.speedup_vs_fp32_dense:.2f}x")
    line += " (total ms per frame; > 1: sparse faster)"
    if h.excluded:
        line += "; left out of the picks (AP guard): " + "; ".join(h.excluded)
    return line


def _notes(result: BenchResult) -> list[str]:
    """The lines under the tables: protocol, machine, allocator, density, then each model's weights and counts."""
    bench, dens, prot = result.machine, result.density, result.protocol
    mach = bench.machine
    env = ", ".join(f"{k}={v}" for k, v in mach.malloc_env.items() if v is not None) or "unset"
    grid = dens.geometry.output_shape
    notes = [
        f"ms per frame, mean ± std over {prot.trials} trials of {prot.frames} frames ({prot.split} split), "
        f"{prot.warmup} warm-up frames, batch 1, models interleaved per frame, precision "
        f"{prot.precision or 'fp32'}",
        machine_line(mach),
        f"allocator: {mach.allocator} ({env})",
        # runs before the key existed had every eager fp32 GEMM in MKL (torch.mm): BenchMachine's default
        f"eager fp32 GEMMs: {bench.gemm} (convolutions: oneDNN; detector.ops.gemm)",
        f"density D (pillars / {grid[0]}x{grid[1]}): median "
        f"{dens.median:.5f}, min {dens.min:.5f}, max {dens.max:.5f} over {dens.frames} frames",
    ]
    if bench.precision_flags is not None:
        have = ", ".join(f"{p}: {' / '.join(f) if f else 'none'}" for p, f in bench.precision_flags.items())
        notes.append(f"native precisions (CPU flags): {have}")
    if any(m.runtime != "torch" for m in result.models):
        notes.append("deployed rows (onnxruntime / openvino): Feature Net = the graph's inputs (the NCHW canvas, or "
                     "the sparse rulebook tables), Backbone = the graph (backbone + neck + head in one call), Head = "
                     "the head maps from its output (docs/deployment.md)")
    for m in result.models:
        what = (f"Open3D-ML {bench.versions.get('open3d', '')}'s own PointPillars, the architecture and grid of "
                f"{result.models[0].name} (detector/bench/peer.py); " if m.peer else "")
        by = m.page_faults_per_frame_by_component
        split = "" if not by else " (" + ", ".join(
            f"{TITLES[k]} {by[k]:.0f}" for k in ("feature_extract", "feature_net", "backbone", "head") if k in by) + ")"
        notes.append(f"{m.name}: {what}weights {m.weights}; {m.page_faults_per_frame:.0f} page faults/frame"
                     f"{split}; {m.detections_per_frame:.1f} detections/frame")
    for sk in result.skipped:
        notes.append(f"skipped {sk.name} ({sk.runtime} {sk.precision}): {sk.reason}")
    return notes


def _table(result: BenchResult, section: str, keys: Sequence[str], markdown: bool) -> list[str]:
    """Rows of one section (mean ± std ms per model that has it, then its ratio rows), as text or Markdown lines.

    Markdown is one table (the docs keep it whole). Text with several runtimes / precisions is one table per runtime x
    precision under its own heading line, the group's suffix left out of the names and the numbers to the decimals a
    reader compares (:func:`_compact`), so that it fits a terminal (one table of 21 rows was ~170 columns wide); the
    JSON and ``--markdown`` keep every digit."""
    models = [m for m in result.models if getattr(m, section)]

    def stat(m: ModelResult, k: str) -> Stat:
        return getattr(m, section)[k]

    if markdown:
        header = ["model", *(TITLES[k] for k in keys)]
        rows = [[m.name, *(f"{_fmt(stat(m, k).mean_ms)} ± {_fmt(stat(m, k).std_ms)}" for k in keys)] for m in models]
        rows += [[name, *(f"{r[k]:.2f}x" for k in keys)] for name, r in ratio_rows(result, section)]
        cells = ["| " + " | ".join(r) + " |" for r in [header, *rows]]
        return [cells[0], "|" + "---|" * len(header), *cells[1:]]
    groups = list(dict.fromkeys(_group(m) for m in models))
    if len(groups) <= 1:
        rows = [[m.name, *(f"{_fmt(stat(m, k).mean_ms)} ± {_fmt(stat(m, k).std_ms)}" for k in keys)] for m in models]
        rows += [[name, *(f"{r[k]:.2f}x" for k in keys)] for name, r in ratio_rows(result, section)]
        return _text_table(["model", *(TITLES[k] for k in keys)], rows)
    lines: list[str] = []
    ratios = ratio_rows(result, section)
    for group in groups:
        suffix = f" ({group[0]} {group[1]})"
        members = [m for m in models if _group(m) == group]
        rows = [[_short_name(m.name, suffix), *(_compact(stat(m, k).mean_ms, stat(m, k).std_ms) for k in keys)]
                for m in members]
        names = {m.name for m in members}
        rows += [[" / ".join(_short_name(n, suffix) for n in name.split(" / ")), *(f"{r[k]:.2f}x" for k in keys)]
                 for name, r in ratios if set(name.split(" / ")) <= names]
        lines += ([""] if lines else []) + [f"{group[0]} {group[1]}:"] + _text_table(
            ["model", *(TITLES[k] for k in keys)], rows)
    # ratios between groups (ours against the peer) after the groups
    rest = [[name, *(f"{r[k]:.2f}x" for k in keys)] for name, r in ratios
            if not any(set(name.split(" / ")) <= {m.name for m in models if _group(m) == g} for g in groups)]
    if rest:
        lines += [""] + _text_table(["ratio", *(TITLES[k] for k in keys)], rest)
    return lines


def _group(m: ModelResult) -> tuple[str, str]:
    """A model row's runtime x precision."""
    return m.runtime, m.precision


def _short_name(name: str, suffix: str) -> str:
    """A row's name without its group's `` (runtime precision)`` suffix (the group's heading says it)."""
    return name[: -len(suffix)] if name.endswith(suffix) else name


def _compact(mean: float, std: float) -> str:
    """``mean±std`` in ms to the decimals a reader compares (0 from 100 ms, 1 from 10, 2 from 1, else 3), the std to
    the mean's decimals: ``290.8, 1.593`` -> ``291±2``, ``0.751, 0.011`` -> ``0.751±0.011``."""
    decimals = 0 if mean >= 100 else 1 if mean >= 10 else 2 if mean >= 1 else 3
    return f"{mean:,.{decimals}f}±{std:,.{decimals}f}"


def _text_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Rows under a header, the first column left-aligned, the others right-aligned, two spaces between columns."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
    return [fmt.format(*header)] + [fmt.format(*r) for r in rows]


def format_budget(result: dict, markdown: bool = False) -> str:
    """The CPU-budget table of :func:`detector.bench.budget.run_budget`'s result: one row per model x runtime x
    precision (CPU share, frame cost, deadline misses, latency, peak memory, the highest rate within 25 % of the CPU),
    then notes."""
    header = ["model", "rate Hz", "threads", "CPU share", "CPU ms/frame", "missed / processed", "dropped",
              "latency p50 / p95 ms", "peak RSS MB", "max Hz at 25 % CPU"]
    rows = [[b["name"], f"{b['rate_hz']:g}", str(b["threads"]), f"{100 * b['cpu_share']:.1f} %",
             _fmt(b["cpu_ms_per_frame"]), f"{b['deadline_misses']} / {b['processed']}", str(b["dropped"]),
             f"{_fmt(b['latency_ms']['p50'])} / {_fmt(b['latency_ms']['p95'])}",
             "-" if b["peak_rss_mb"] is None else f"{b['peak_rss_mb']:,.0f}", f"{b['max_rate_hz_at_25pct']:.2f}"]
            for b in result["budget"]]
    if markdown:
        cells = ["| " + " | ".join(r) + " |" for r in [header, *rows]]
        lines = [cells[0], "|" + "---|" * len(header), *cells[1:]]
    else:
        widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
        fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
        lines = [fmt.format(*header)] + [fmt.format(*r) for r in rows]
    prot, mach, dens = result["protocol"], result["machine"], result["density"]
    notes = [
        f"each row in a fresh process: {prot['warmup']} warm-up frames, then a sensor at {prot['rate_hz']:g} Hz for "
        f"{prot['duration_s']:g} s over the first {prot['frames']} frames of the {prot['split']} split (cycled); the "
        "newest released frame is processed, older unstarted ones dropped",
        "CPU share = process CPU time (all threads) / wall / usable cores; latency = frame release to detections; "
        "max Hz at 25 % CPU = 0.25 x cores / CPU s per frame, capped at 1 / service p95",
        machine_line(Machine.from_json(mach)),
        f"density D (pillars / {dens['geometry']['output_shape'][0]}x{dens['geometry']['output_shape'][1]}): median "
        f"{dens['median']:.5f} over {dens['frames']} frames",
    ]
    weights = {b["weights"] for b in result["budget"]}
    notes += ([f"weights of every row: {weights.pop()}"] if len(weights) == 1 else
              [f"{b['name']}: weights {b['weights']}" for b in result["budget"]])
    notes += [f"skipped {s['name']} ({s['runtime']} {s['precision']}): {s['reason']}" for s in result["skipped"]]
    prefix = "- " if markdown else ""
    return "\n".join(lines) + "\n\n" + "\n".join(prefix + n for n in notes)
