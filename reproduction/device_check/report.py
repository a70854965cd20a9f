"""The GPU check's report: ``summary.json`` (every result file in one document) and ``summary.md`` (the tables, the
paper's Desktop runtimes beside ours)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from detector.bench.timing import TITLES
from mpchair.core.atomic import write_text
from mpchair.paper import TABLE_II, TABLE_IV, ComponentTimes
from reproduction.device_check.files import read_json, write_json
from reproduction.device_check.jobs import WARMUP_STEPS

if TYPE_CHECKING:
    from detector.bench.result import BenchResult

#: The paper's runtimes on its Desktop (an NVIDIA 2080 Ti with an AMD Ryzen 7 3700X): Table II's Desktop rows
#: (Matterport-Chair, 768 x 512) and Table IV's dense / sparse rows (KITTI, 504 x 440), from ``mpchair.paper``.
PAPER_DESKTOP: dict[str, dict[str, ComponentTimes]] = {
    "mpchair": dict(TABLE_II["desktop"]),
    "kitti": {m: TABLE_IV[m] for m in ("dense", "sparse")},
}
#: The section title of each geometry's bench.
GEOMETRY: dict[str, str] = {"mpchair": "Matterport-Chair geometry",
                            "kitti": "KITTI geometry (tests/data/kitti's frames)"}
#: Table order of the training runs.
MODEL_ORDER = ("dense", "sparse", "sparse_exact")
PRECISION_ORDER = ("fp32", "autocast")


def _md_table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows)]


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:,.3f}" if x < 100 else f"{x:,.1f}"


def paper_rows(bench: BenchResult, geometry: str) -> list[list[str]]:
    """Per component: the paper's Desktop dense / sparse (ms) beside ours (dense, sparse, sparse+sparse_head)."""
    ours = {name: m.mean_ms for name, m in bench.ours().items()}
    paper = PAPER_DESKTOP[geometry]
    rows = []
    for key, title in TITLES.items():
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
    steps = [read_json(p) for p in sorted((res / "steps").glob("*.json"), key=lambda p: p.stat().st_mtime)]
    steps = [s for s in steps if s]
    machine = read_json(res / "machine.json")
    bench = {g: read_json(res / f"bench_{g}.json") for g in GEOMETRY}
    train = [r for p in (res / "train").glob("*.json") if (r := read_json(p))]
    train.sort(key=lambda r: (MODEL_ORDER.index(r["model"]) if r["model"] in MODEL_ORDER else len(MODEL_ORDER),
                              r["model"], PRECISION_ORDER.index(r["precision"])))
    paper = {g: {m: t.to_json() for m, t in rows.items()} for g, rows in PAPER_DESKTOP.items()}
    summary = {"dry_run": bool(machine and machine.get("dry_run")), "machine": machine, "steps": steps,
               "tests": read_json(res / "tests.json"), "bench": bench, "paper_desktop": paper, "train": train,
               "eval": read_json(res / "eval.json"), "ddp": read_json(res / "ddp.json"),
               "failed": [s["name"] for s in steps if s["status"] == "failed"]}
    write_json(out / "summary.json", summary)
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
