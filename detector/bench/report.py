"""The benchmark result as the paper's runtime tables: mean ± std ms per model, ratio rows, notes (text or Markdown).

Reads only the JSON-ready result of :func:`detector.bench.run.run_bench` (a dict, or the same loaded back from
``detector bench --json``), so a saved result can be re-printed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from detector.bench.timing import COMPONENTS, SHARED, TITLES


def _fmt(x: float) -> str:
    return f"{x:,.3f}" if x < 100 else f"{x:,.1f}"


def ratio_rows(result: dict, section: str = "components") -> list[tuple[str, dict[str, float]]]:
    """Per-component speed-ups: ``first / other`` for every one of our models after the first (dense / sparse: > 1
    means sparse faster), then ``peer / ours`` for every one of our models (> 1 means ours is faster than the peer).
    ``section="back_to_back"``: the same for the :data:`SHARED` components timed back to back (ours only)."""
    ours = [m for m in result["models"] if not m.get("peer")]
    peers = [m for m in result["models"] if m.get("peer")]
    pairs = [(ours[0], m) for m in ours[1:]]
    if section == "components":
        pairs += [(p, m) for p in peers for m in ours]
    rows = []
    for a, b in pairs:
        if not a.get(section) or not b.get(section):
            continue
        r = {}
        for key in a[section]:
            ta, tb = a[section][key]["mean_ms"], b[section][key]["mean_ms"]
            r[key] = ta / tb if tb > 0 else math.inf
        rows.append((f"{a['name']} / {b['name']}", r))
    return rows


def machine_line(mach: dict) -> str:
    """One line describing the machine of a result (its ``"machine"``, :func:`detector.device.machine_info`)."""
    line = (f"machine: {mach['cpu']}, {mach['torch_threads']} torch threads of {mach['logical_cpus']} CPUs, "
            f"torch {mach['torch']}, device {mach['device']}")
    if mach.get("gpu"):
        line += f" ({mach['gpu']})"
    if mach.get("loadavg_1m") is not None:
        line += f", load average {mach['loadavg_1m']:.2f} when it ended"
    return line


def format_table(result: dict, markdown: bool = False) -> str:
    """The paper-shaped table: one row per model (mean ± std ms), one ratio row per further model; then the shared
    components timed back to back (same shape), then notes."""
    lines = _table(result, "components", COMPONENTS, markdown)
    if any(m.get("back_to_back") for m in result["models"]):
        title = (f"{' and '.join(TITLES[k] for k in SHARED)} timed back to back (every model's, on its own maps, order "
                 "rotated per frame; the components' own cost, to compare between models):")
        lines += ["", title, ""] + _table(result, "back_to_back", SHARED, markdown)
    prefix = "- " if markdown else ""
    return "\n".join(lines) + "\n\n" + "\n".join(prefix + n for n in _notes(result))


def _notes(result: dict) -> list[str]:
    """The lines under the tables: protocol, machine, allocator, density, then each model's weights and counts."""
    mach, dens, prot = result["machine"], result["density"], result["protocol"]
    env = ", ".join(f"{k}={v}" for k, v in mach["malloc_env"].items() if v is not None) or "unset"
    notes = [
        f"ms per frame, mean ± std over {prot['trials']} trials of {prot['frames']} frames ({prot['split']} split), "
        f"{prot['warmup']} warm-up frames, batch 1, models interleaved per frame, precision "
        f"{prot.get('precision', 'fp32')}",
        machine_line(mach),
        f"allocator: {mach['allocator']} ({env})",
        f"density D (pillars / {dens['geometry']['output_shape'][0]}x{dens['geometry']['output_shape'][1]}): median "
        f"{dens['median']:.5f}, min {dens['min']:.5f}, max {dens['max']:.5f} over {dens['frames']} frames",
    ]
    for m in result["models"]:
        what = (f"Open3D-ML {mach.get('open3d', '')}'s own PointPillars, the architecture and grid of "
                f"{result['models'][0]['name']} (detector/bench/peer.py); " if m.get("peer") else "")
        by = m.get("page_faults_per_frame_by_component")
        split = "" if not by else " (" + ", ".join(
            f"{TITLES[k]} {by[k]:.0f}" for k in ("feature_extract", "feature_net", "backbone", "head") if k in by) + ")"
        notes.append(f"{m['name']}: {what}weights {m['weights']}; {m['page_faults_per_frame']:.0f} page faults/frame"
                     f"{split}; {m['detections_per_frame']:.1f} detections/frame")
    return notes


def _table(result: dict, section: str, keys: Sequence[str], markdown: bool) -> list[str]:
    """Rows of one section (mean ± std ms per model that has it, then its ratio rows), as text or Markdown lines."""
    header = ["model", *(TITLES[k] for k in keys)]
    rows = [[m["name"], *(f"{_fmt(m[section][k]['mean_ms'])} ± {_fmt(m[section][k]['std_ms'])}" for k in keys)]
            for m in result["models"] if m.get(section)]
    rows += [[name, *(f"{r[k]:.2f}x" for k in keys)] for name, r in ratio_rows(result, section)]
    if markdown:
        cells = ["| " + " | ".join(r) + " |" for r in [header, *rows]]
        return [cells[0], "|" + "---|" * len(header), *cells[1:]]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
    return [fmt.format(*header)] + [fmt.format(*r) for r in rows]
