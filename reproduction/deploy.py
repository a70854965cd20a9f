"""The reproduction's ``deploy`` step and its report section: the trained models exported and run in ONNX Runtime and
OpenVINO at every precision this CPU computes natively, "AP drop vs speed".

After ``train`` / ``eval`` / ``bench``, three kinds of command (all in ``results/``):

- ``detector eval --runtime R --precision P`` of each trained model on the val split (the eval step's configs and
  weights; eager bf16 included; int8 calibrated on :data:`CALIBRATION_FRAMES` train frames) →
  ``deploy_eval/<model>_<R>_<P>/metrics.json``; the sparse weights with the exact sparse head too
  (``deploy_eval/sparse_exact_<R>_<P>``, eager fp32 included: the exported exact head is a graph of its own and
  int8 / bf16 change its numbers, so the fastest sparse row's AP is measured, not inferred from the dense head's);
- ``detector bench`` of dense / sparse / sparse with the exact head at 768 x 512, every runtime x precision, one
  process, interleaved per frame, the reuse allocator (a robot's long-running process) → ``deploy_bench.json``;
- ``detector bench --rate`` at :data:`BUDGET_RATE_HZ` Hz, each row alone in its own process → ``deploy_budget.json`` /
  ``.md``.

:func:`deploy_section` reads them back into the report's table (3D / BEV AP Overall R40 and their drop against eager
fp32, total ms per frame and the speed-up against eager dense fp32, CPU share at the sensor rate and the highest rate
within 25 % of the CPU). A combination the CPU cannot compute natively is left out (:mod:`detector.deploy.cpu`).
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from pathlib import Path

from detector.bench.pick import AP_TOLERANCE, ap_exclusion, fastest_within_ap
from detector.deploy.cpu import cpu_flags, skip_reason
from reproduction.results import MODELS, KittiMetrics, _read_json, read_bench, read_bench_repeated, read_text
from reproduction.runner import BIN, REUSE_ENV, Runner
from reproduction.scales import bench_run_args

#: (runtime, precision) of the deployed evaluations and bench rows, eager fp32 first.
VARIANTS: tuple[tuple[str, str], ...] = (("torch", "fp32"), ("torch", "bf16"), ("onnxruntime", "fp32"),
                                        ("onnxruntime", "int8"), ("openvino", "fp32"), ("openvino", "bf16"),
                                        ("openvino", "int8"))
#: The evaluated models: table name → (eval folder prefix, CPU config, trained weights of). The exact sparse head
#: loads the sparse model's weights (``mpchair_sparse_exact_cpu.yaml``); the eval step evaluates the first two in
#: eager fp32, the deploy step everything else.
EVALUATED: dict[str, tuple[str, str, str]] = {
    "dense": ("dense", "mpchair_dense_cpu", "dense"),
    "sparse": ("sparse", "mpchair_sparse_cpu", "sparse"),
    "sparse+sparse_head": ("sparse_exact", "mpchair_sparse_exact_cpu", "sparse"),
}
CALIBRATION_FRAMES = 32
BUDGET_RATE_HZ = 1.0  # the paper's conclusion: "1 Hz with more than 75 % of the CPU left"


def deployed_variants() -> list[tuple[str, str]]:
    """:data:`VARIANTS` less those this CPU does not compute natively."""
    flags = cpu_flags()
    return [(r, p) for r, p in VARIANTS if skip_reason(r, p, flags) is None]


def eval_dir(res: Path, model: str, runtime: str, precision: str) -> Path:
    """Where ``detector eval`` of a deployed model writes (``results/deploy_eval/<model>_<runtime>_<precision>``)."""
    return res / "deploy_eval" / f"{model}_{runtime}_{precision}"


def _eval_step_has(model: str, runtime: str, precision: str) -> bool:
    """Whether the eval step (not the deploy step) evaluates ``model`` in ``runtime`` / ``precision``."""
    return model in MODELS and (runtime, precision) == ("torch", "fp32")


def metrics_path(res: Path, model: str, runtime: str, precision: str) -> Path:
    """The ``metrics.json`` of table model ``model`` (a key of :data:`EVALUATED`) in ``runtime`` / ``precision``."""
    if _eval_step_has(model, runtime, precision):
        return res / f"eval_{model}" / "metrics.json"
    return eval_dir(res, EVALUATED[model][0], runtime, precision) / "metrics.json"


def deploy_outputs(res: Path) -> dict[str, Path]:
    """The files that mark the deploy step done (the bench tables; every evaluation's metrics)."""
    out = {"bench": res / "deploy_bench.json", "budget": res / "deploy_budget.json"}
    for m in EVALUATED:
        for r, p in deployed_variants():
            if not _eval_step_has(m, r, p):
                out[f"{m} {r} {p}"] = metrics_path(res, m, r, p)
    return out


def _variant_args(variants: list[tuple[str, str]]) -> list[str]:
    args: list[str] = []
    for r in dict.fromkeys(r for r, _ in variants):
        args += ["--runtime", r]
    for p in dict.fromkeys(p for _, p in variants):
        args += ["--precision", p]
    return args


def run_deploy(plan, r: Runner, config) -> None:
    """The step (``plan``: :class:`reproduction.steps.Plan`; ``config``: its config-path function)."""
    outputs = deploy_outputs(plan.res)
    variants = deployed_variants()
    threads = ["--threads", str(plan.threads)]
    for m, (folder, cfg, weights) in EVALUATED.items():
        for runtime, precision in variants:
            key = f"{m} {runtime} {precision}"
            if _eval_step_has(m, runtime, precision) or not plan.todo("deploy", outputs[key]):
                continue
            r.run([str(BIN / "detector"), "eval", "--config", config(cfg), "--data", str(plan.data),
                   "--checkpoint", str(plan.runs / weights / "last.pt"), "--split", "val", "--out",
                   str(eval_dir(plan.res, folder, runtime, precision)), *threads, "--runtime", runtime, "--precision",
                   precision, "--calibration-frames", str(CALIBRATION_FRAMES)])
    models = ["--config", config("mpchair_dense"), "--config", config("mpchair_sparse"), "--config",
              config("mpchair_sparse_exact")]
    ckpts = [str(plan.runs / m / "last.pt") for m in MODELS]
    weights = [a for c in (*ckpts, ckpts[1]) for a in ("--checkpoint", c)] if all(
        Path(c).exists() for c in ckpts) else []
    common = [*models, "--data", str(plan.data), "--split", "test", *weights, *threads, *_variant_args(variants),
              "--calibration-frames", str(CALIBRATION_FRAMES)]
    if plan.todo("deploy", outputs["bench"]):
        # --runs as the bench step's: the like-for-like table's ratios are headline figures too (the budget rows,
        # each alone in its own process already, run once: detector bench refuses --runs with --rate)
        r.run([str(BIN / "detector"), "bench", *common, "--frames", str(plan.scale.bench_frames), "--trials",
               str(plan.scale.bench_trials), *bench_run_args(plan.scale), "--json-out", str(outputs["bench"]),
               "--markdown", "--no-progress"],
              env=REUSE_ENV, stdout=plan.res / "deploy_bench.md")
    if plan.todo("deploy", outputs["budget"]):
        # each row also pays a fresh process and its export (10-30 s) beside the scale's budget_seconds
        r.run([str(BIN / "detector"), "bench", *common, "--frames", str(plan.scale.bench_frames), "--rate",
               str(BUDGET_RATE_HZ), "--duration", str(plan.scale.budget_seconds), "--json-out", str(outputs["budget"]),
               "--markdown"],
              env=REUSE_ENV, stdout=plan.res / "deploy_budget.md")


# --- reading back ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DeployRow:
    """One row of the AP-drop-vs-speed table: a model (``dense``, ``sparse``, ``sparse+sparse_head``) in a runtime and
    precision, its val AP (None: not evaluated), its bench total ms and its budget record (None where not run).

    ``runs``: the row's total ms in every run of a ``detector bench --runs N`` (N >= 2), in run order, whose median
    ``total_ms`` then is; empty for a one-run bench, where ``total_ms`` is that run's."""

    model: str
    runtime: str
    precision: str
    metrics: KittiMetrics | None
    total_ms: float | None
    cpu_share: float | None
    max_rate_hz: float | None
    runs: tuple[float, ...] = ()


def read_deploy(res: Path) -> list[DeployRow]:
    """The deploy step's outputs under ``res`` as table rows (empty when the step has not run)."""
    bench = read_bench(res / "deploy_bench.json")
    budget = _read_json(res / "deploy_budget.json") or {}
    spread = read_bench_repeated(res / "deploy_bench.json")
    # a repeated bench's JSON is its first run's result: each row's median over the runs replaces that run's total, as
    # the report's bench ratios do (reproduction.report.spread_text), so that no headline rests on one draw
    per_run = {name: s.values for name, s in (spread.totals.items() if spread else ()) if len(s.values) > 1}
    totals, runs = {}, {}
    for m in (bench.models if bench else ()):
        if m.peer:
            continue
        key = (m.name.split(" (")[0], m.runtime, m.precision)
        runs[key] = per_run.get(m.name, ())
        totals[key] = float(statistics.median(runs[key])) if runs[key] else m.components["total"].mean_ms
    shares = {(b["name"].split(" (")[0], b["runtime"], b["precision"]): b for b in budget.get("budget", [])}
    keys = list(dict.fromkeys([*totals, *shares]))
    rows = []
    for name, runtime, precision in keys:
        d = _read_json(metrics_path(res, name, runtime, precision)) if name in EVALUATED else None
        b = shares.get((name, runtime, precision))
        rows.append(DeployRow(name, runtime, precision, KittiMetrics.from_json(d) if d else None,
                              totals.get((name, runtime, precision)), b["cpu_share"] if b else None,
                              b["max_rate_hz_at_25pct"] if b else None, runs.get((name, runtime, precision), ())))
    return rows


def bench_runs(rows: list[DeployRow]) -> int:
    """How many bench runs the rows' totals are the median of (1 for a one-run bench)."""
    return max((len(r.runs) for r in rows), default=0) or 1


def ratio_text(dense: DeployRow, sparse: DeployRow) -> str:
    """``dense`` / ``sparse`` total time as the table and headline quote it: ``12.69x`` from a one-run bench;
    ``12.69x (per run 12.10-13.20x)`` from a repeated one, the ratio of the rows' medians with the min-max of the
    ratio within each run (both rows of a run were timed interleaved, so their ratio is that run's draw)."""
    text = f"{dense.total_ms / sparse.total_ms:.2f}x"
    if len(dense.runs) > 1 and len(dense.runs) == len(sparse.runs):
        per_run = [d / s for d, s in zip(dense.runs, sparse.runs)]
        text += f" (per run {min(per_run):.2f}-{max(per_run):.2f}x)"
    return text


def _ap(metrics: KittiMetrics | None, kind: str) -> float | None:
    if metrics is None or kind not in metrics.ap:
        return None
    return metrics.ap[kind].overall.get("R40")


def _cell(v: float | None, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


#: The like-for-like table's rows: (label, the sparse side's models, fp32 only on both sides, deployed runtimes only on
#: both sides). The sparse side of the first two is either head (the fastest is the exact sparse head, our addition);
#: the last three are the paper's architecture, the sparse backbone with the dense head.
PAIRS: tuple[tuple[str, tuple[str, ...], bool, bool], ...] = (
    ("fp32 (the fair pair on a CPU without native bf16 / int8, e.g. the paper's AVX2 robot)",
     ("sparse", "sparse+sparse_head"), True, False),
    ("any precision this CPU computes natively", ("sparse", "sparse+sparse_head"), False, False),
    ("the paper's architecture (sparse backbone + dense head), fp32", ("sparse",), True, False),
    ("the paper's architecture, any precision", ("sparse",), False, False),
    ("the paper's architecture, deployed (ONNX Runtime / OpenVINO), any precision", ("sparse",), False, True),
)
#: What the headline sentence calls each sparse model.
SPARSE_NAMES = {"sparse+sparse_head": "the sparse model with the exact sparse head, our addition to the paper's "
                                      "architecture",
                "sparse": "the sparse model with the paper's dense head"}


def _exclusion(r: DeployRow, rows: list[DeployRow]) -> str | None:
    """Why ``r`` may not be its side's fastest: its 3D AP against its own model's eager fp32 evaluation
    (:func:`detector.bench.pick.ap_exclusion`); None when it may (within the tolerance, or either not evaluated)."""
    eager = next((e for e in rows if e.model == r.model and (e.runtime, e.precision) == ("torch", "fp32")), None)
    return ap_exclusion(_ap(r.metrics, "3d"), _ap(eager.metrics if eager else None, "3d"))


def _fastest(rows: list[DeployRow], models: tuple[str, ...], fp32_only: bool,
             deployed_only: bool = False) -> DeployRow | None:
    """The row of ``models`` with the lowest bench total (fp32 rows only when ``fp32_only``, ONNX Runtime / OpenVINO
    rows only when ``deployed_only``) among those the AP guard keeps (:func:`_exclusion`); None if none is left."""
    timed = [r for r in rows if r.model in models and r.total_ms is not None and (r.precision == "fp32" or not
                                                                                  fp32_only)
             and (r.runtime != "torch" or not deployed_only)]
    return fastest_within_ap(timed, lambda r: r.total_ms, lambda r: _exclusion(r, rows))


def _row_text(r: DeployRow) -> str:
    ap = _ap(r.metrics, "3d")
    return f"{r.model}, {r.runtime} {r.precision}: {r.total_ms:.1f} ms, 3D AP {_cell(ap, '.2f')}"


def _where(r: DeployRow) -> str:
    return f"{r.runtime} {r.precision}, {r.total_ms:.1f} ms"


def headline_sentence(pairs: list[tuple[str, DeployRow | None, DeployRow | None]], threads: int | None = None,
                      cpu: str | None = None) -> str:
    """The headline the README quotes, from the like-for-like ``pairs`` (:data:`PAIRS`' order; the first two picked)
    timed on ``threads`` threads of ``cpu``: which sparse model the fastest sparse row is, the paper's architecture
    against the same dense row beside it (where picked), and, where the fastest sparse row is not fp32, the fp32 pair
    (a ratio against the fastest fp32 dense row would set that precision against fp32)."""
    (_, fp32_d, fp32_s), (_, dense, sparse), _, (_, _, paper), (_, paper_d, paper_deployed) = pairs
    on = f" on {threads or '?'} threads of the {cpu or 'CPU'} above" if threads or cpu else ""
    n = bench_runs([r for pair in pairs for r in pair[1:] if r is not None])
    # a repeated bench: every ms is its row's median over the runs (read_deploy); a one-run record reads as before
    medians = f", each ms the row's median over {n} bench runs" if n > 1 else ""
    text = (f"Headline: {SPARSE_NAMES[sparse.model]}, at its fastest ({_where(sparse)}), is "
            f"{ratio_text(dense, sparse)} faster than the fastest dense deployment ({_where(dense)}){on}{medians}. ")
    if sparse.model != "sparse" and paper is not None:
        text += (f"The paper's architecture (sparse backbone + dense head) against the same dense row: "
                 f"{ratio_text(dense, paper)} at its fastest ({_where(paper)})")
        if paper_d is not None and paper_deployed is not None:
            against = "" if paper_d == dense else f" against {_where(paper_d)}"
            text += f", {ratio_text(paper_d, paper_deployed)} deployed ({_where(paper_deployed)}{against})"
        text += ". "
    if sparse.precision != "fp32":
        text += (f"Against the fastest fp32 dense row ({_where(fp32_d)}) the same sparse row is "
                 f"{ratio_text(fp32_d, sparse)}, but that sets sparse {sparse.precision} against dense "
                 f"fp32; fp32 on both sides it is {ratio_text(fp32_d, fp32_s)} (the first row).")
    return text.rstrip()


def guard_note(rows: list[DeployRow]) -> str:
    """Which timed rows the AP guard left out of every pick, and which had no evaluation to guard them by."""
    timed = [r for r in rows if r.total_ms is not None]
    out = [f"{r.model} {r.runtime} {r.precision} ({_exclusion(r, rows)})" for r in timed if _exclusion(r, rows)]
    blind = [f"{r.model} {r.runtime} {r.precision}" for r in timed if _ap(r.metrics, "3d") is None]
    text = (f"AP guard: a row is its side's fastest only within {AP_TOLERANCE:.1f} 3D AP of its own model's eager fp32 "
            "evaluation; left out: " + ("; ".join(out) if out else "none (every evaluated row is within it)"))
    if blind:
        text += "; not evaluated, so picked on speed alone: " + ", ".join(blind)
    return text + "."


def like_for_like_pairs(rows: list[DeployRow]) -> list[tuple[str, DeployRow | None, DeployRow | None]]:
    """(label, the fastest dense row, the fastest sparse row) of each of :data:`PAIRS`, AP-guarded; None where a side
    has no row to pick."""
    return [(label, _fastest(rows, ("dense",), fp32, deployed), _fastest(rows, sparse, fp32, deployed))
            for label, sparse, fp32, deployed in PAIRS]


def like_for_like(res: Path, rows: list[DeployRow] | None = None) -> list[str]:
    """The like-for-like table: the fastest dense deployment against the fastest sparse one (either head), at fp32 (the
    fair comparison on a CPU without native bf16 / int8, such as the paper's AVX2 robot CPU) and at any precision
    this CPU computes natively, then the paper's architecture (sparse backbone + dense head) against the fastest dense
    at fp32, at any precision and deployed (:data:`PAIRS`); every pick AP-guarded (:func:`guard_note`); with what both
    sides ran under and the headline sentence (:func:`headline_sentence`); no lines before the deploy step has run.
    ``rows``: :func:`read_deploy`'s, when the caller has them."""
    rows = read_deploy(res) if rows is None else rows
    bench = read_bench(res / "deploy_bench.json")
    pairs = like_for_like_pairs(rows)
    # the first two pairs are the headline's; a paper's-architecture pair with no timed (or no deployed) sparse model
    # with the dense head is left out of the table
    if not all(d and sp for _, d, sp in pairs[:2]):
        return []
    mach = bench.machine if bench else None
    flags = sorted(mach.native_flags()) if mach else []
    median = bench.density.median if bench and bench.density else None
    cpu, threads, cpus = (mach.machine.cpu, mach.machine.torch_threads, mach.machine.logical_cpus) if mach else (
        None, None, None)
    lines = ["| fastest of each side | dense | sparse | dense / sparse |", "|---|---|---|---|"]
    for label, d, sp in (p for p in pairs if p[1] and p[2]):
        lines.append(f"| {label} | {_row_text(d)} | {_row_text(sp)} | {ratio_text(d, sp)} |")
    n = bench_runs(rows)
    lines += ["", f"Both sides: {cpu or 'this CPU'}, {threads or '?'} threads of {cpus or '?'} CPUs, allocator reuse, "
              "768 x 512 test frames"
              + (f" of density D median {median:.5f}" if median is not None else "")
              + ", trained weights, every row interleaved per frame in one process (`detector bench --runtime "
              "--precision"
              + (f" --runs {n}`: {n} such processes one after another; each row's ms is its median over the runs, "
                 "each ratio that of the medians with its min-max over the runs" if n > 1 else "`")
              + "); 3D AP Overall R40 on val. Native bf16 / int8 flags of this CPU: "
              + (", ".join(flags) if flags else "none")
              + ": AMX (and, less, AVX512-BF16 / VNNI) is what makes the dense bf16 / int8 rows fast; where a CPU "
              "has none of them the fp32 row is the fair one. " + guard_note(rows),
              "", headline_sentence(pairs, threads, cpu)]
    return lines


#: The docs that lead with the like-for-like table, between ``<!-- like-for-like:begin -->`` / ``end`` markers (the
#: report step fills them: :func:`mpchair.core.doctable.write_doc_table`).
LIKE_FOR_LIKE_DOCS = ("README.md", "docs/benchmarks.md", "docs/deployment.md")
LIKE_FOR_LIKE_MARKER = "like-for-like"


def deploy_section(res: Path) -> list[str]:
    """The report's "Deployed" section: the AP-drop-vs-speed table, then the bench and budget tables as measured."""
    rows = read_deploy(res)
    lines = ["## Deployed: ONNX Runtime and OpenVINO, AP drop vs speed", ""]
    if not rows:
        return [*lines, "not run (step `deploy`)", ""]
    eager = {r.model: r for r in rows if (r.runtime, r.precision) == ("torch", "fp32")}
    dense_ms = eager["dense"].total_ms if "dense" in eager else None
    lines += ["| model | runtime | precision | 3D AP (Overall R40, val) | Δ vs eager fp32 | BEV AP | Δ | total ms "
              "(768 x 512) | vs eager dense fp32 | CPU at 1 Hz | max Hz at 25 % CPU |", "|" + "---|" * 11]
    for r in rows:
        base = eager.get(r.model)
        cells = [r.model, r.runtime, r.precision]
        for kind in ("3d", "bev"):
            ap, ap0 = _ap(r.metrics, kind), _ap(base.metrics if base else None, kind)
            cells += [_cell(ap, ".2f"), _cell(None if ap is None or ap0 is None else ap - ap0, "+.2f")]
        speed = None if r.total_ms is None or dense_ms is None else dense_ms / r.total_ms
        cells += [_cell(r.total_ms, ".1f"), _cell(speed, ".2f") + ("x" if speed else ""),
                  _cell(None if r.cpu_share is None else 100 * r.cpu_share, ".1f") + (" %" if r.cpu_share else ""),
                  _cell(r.max_rate_hz, ".2f")]
        lines.append("| " + " | ".join(cells) + " |")
    n = bench_runs(rows)
    runs = f", the median of {n} runs, each a process of its own (`--runs {n}`)" if n > 1 else ""
    lines += ["", "AP: `detector eval --runtime R --precision P` of the trained CPU-config models on the val split "
              "(sparse+sparse_head: the sparse weights in `mpchair_sparse_exact_cpu.yaml`); ms: `detector bench` "
              f"at 768 x 512, every row interleaved per frame in one process (reuse allocator){runs}; CPU: `detector "
              f"bench --rate {BUDGET_RATE_HZ:g}`, each row alone in its own process.", ""]
    table = like_for_like(res, rows)
    if table:
        lines += ["### Like for like: the fastest dense deployment against the fastest sparse one", "", *table, ""]
    for name, title in (("deploy_bench.md", "Deployed runtime at 768 x 512 (ms per frame)"),
                        ("deploy_budget.md", f"CPU budget at {BUDGET_RATE_HZ:g} Hz")):
        text = read_text(res / name)
        if text:
            lines += [f"### {title}", "", text.rstrip(), ""]
    return lines
