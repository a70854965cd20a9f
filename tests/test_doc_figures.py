"""The figures docs/results.md, benchmarks.md, sparse.md, evaluation.md, deployment.md, streaming.md and the README
quote agree with the tables they come from (the Markdown tables in the same docs), with the committed run record
(docs/results-data: the deployed ratios and AP, the Open3D-ML example, the run's command times) and with the code that
makes them (``reproduction.report`` for the metric notes, the KITTI protocol for the half-found example), and a
figure with no JSON in the record says it is a one-off, so a number copied from an older run fails here.

Each ``check_*`` returns the problems it finds in the docs' text; every test runs it on the docs as they are (no
problem) and on a copy with the stale figure the docs once quoted (a problem), so a check cannot pass vacuously."""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from pathlib import Path

import pytest

from mpchair.paper import MATTERPORT_CHAIR_AP
from reproduction.deploy import DeployRow, like_for_like_pairs, read_deploy
from reproduction.report import half_found_r40, half_found_text, paper_gap_verdict, recall_blind_note
from reproduction.results import EvalOutputs, Open3dMlMetrics
from reproduction.stream.report import BEGIN as STREAM_BEGIN
from reproduction.stream.report import END as STREAM_END
from reproduction.stream.report import no_record_section

ROOT = Path(__file__).resolve().parents[1]
DOCS = {name: ROOT / path for name, path in (("results", "docs/results.md"), ("benchmarks", "docs/benchmarks.md"),
                                              ("sparse", "docs/sparse.md"), ("evaluation", "docs/evaluation.md"),
                                              ("readme", "README.md"), ("deployment", "docs/deployment.md"),
                                              ("streaming", "docs/streaming.md"))}
#: The committed run record every runtime and AP figure of these docs comes from (or says it does not).
RECORD = ROOT / "docs" / "results-data"
Docs = Mapping[str, str]


@pytest.fixture(scope="module")
def docs() -> dict[str, str]:
    return {name: path.read_text(encoding="utf-8") for name, path in DOCS.items()}


def flat(text: str) -> str:
    """``text`` with every run of whitespace one space (a quoted sentence may wrap anywhere)."""
    return " ".join(text.split())


def number(cell: str) -> float:
    """The leading number of a table cell: ``458.0 ± 22.471`` -> 458.0, ``11.77x`` -> 11.77, ``3,325.3`` -> 3325.3."""
    return float(re.match(r"[-+]?[\d,]*\.?\d+", cell.strip()).group(0).replace(",", ""))


def tables(text: str) -> list[list[list[str]]]:
    """Every Markdown table of ``text`` as rows of cells (header first, the ``|---|`` line dropped)."""
    found, current = [], []
    for line in text.splitlines() + [""]:
        if line.startswith("|"):
            if not set(line) <= set("|-: "):
                current.append([c.strip() for c in line.strip().strip("|").split("|")])
        elif current:
            found.append(current)
            current = []
    return found


def cell(table: list[list[str]], row: str, column: str) -> str:
    """The cell of the row whose first cell is ``row`` under the header ``column``."""
    (match,) = [r for r in table[1:] if r[0] == row]
    return match[table[0].index(column)]


def section(text: str, heading: str) -> str:
    """The text under the ``## heading`` line (its start), up to the next ``## `` heading."""
    return text.split(f"\n## {heading}", 1)[1].split("\n", 1)[1].split("\n## ", 1)[0]


def runtime_tables(text: str) -> list[list[list[str]]]:
    """The per-component runtime tables (``detector bench --markdown``) of ``text``."""
    return [t for t in tables(text) if t[0][:2] == ["model", "To Device"]]


def quoted(pattern: str, text: str) -> tuple[str, ...] | None:
    m = re.search(pattern, flat(text))
    return None if m is None else m.groups()


def results_runtime(d: Docs, alloc: str) -> list[list[str]]:
    (table,) = runtime_tables(section(d["results"], f"Runtime at 768 x 512, allocator {alloc}"))
    return table


# --- results.md: the opening note's figures ---------------------------------------------------------------------------
def check_opening_note(d: Docs) -> list[str]:
    """results.md's opening note quotes its own tables: "D has median M" is the stats summary's median, "the backbone
    ratio (Rx default / Sx reuse allocator)" each runtime table's dense / sparse Backbone, "the total-time ratio (Tx)"
    the default table's dense / sparse Total, "with the reference's three-conv head it is Hx" the reference-head
    table's."""
    text = d["results"]
    got = quoted(r"density D has median ([\d.]+) against the paper's 0\.0075.*?the backbone ratio "
                 r"\(([\d.]+)x default / ([\d.]+)x reuse allocator\).*?the total-time ratio \(([\d.]+)x\).*?"
                 r"with the reference's three-conv head it is ([\d.]+)x", text)
    if got is None:
        return ["results.md: no opening note with 'density D has median ... the backbone ratio (Rx default / ...'"]
    problems = []
    (median,) = quoted(r'`mpchair stats` summary: `\{"median": ([\d.e-]+)', text)
    if f"{float(median):.5f}" != got[0]:
        problems.append(f"opening note: median {got[0]}, stats summary {median}")
    for alloc, quoted_ratio in (("default", got[1]), ("reuse", got[2])):
        ratio = f"{number(cell(results_runtime(d, alloc), 'dense / sparse', 'Backbone')):.1f}"
        if ratio != quoted_ratio:
            problems.append(f"opening note: backbone ratio {quoted_ratio}x, {alloc} table {ratio}x")
    total = f"{number(cell(results_runtime(d, 'default'), 'dense / sparse', 'Total')):.1f}"
    if total != got[3]:
        problems.append(f"opening note: total-time ratio {got[3]}x, default table {total}x")
    ref_section = section(text, "Total time with the reference's head layout")
    (ref,) = [t for t in tables(ref_section) if "Total, reference head (ms)" in t[0]]
    head = f"{number(cell(ref, 'dense / sparse', 'Total, reference head (ms)')):.1f}"
    if head != got[4]:
        problems.append(f"opening note: reference-head total ratio {got[4]}x, its table {head}x")
    return problems


# --- the half-found example: R40 for this val set's chairs ------------------------------------------------------------
def check_half_found(d: Docs) -> list[str]:
    """"Finding half of the chairs perfectly" scores, on the KITTI level, what the protocol's threshold rule gives for
    the val set's chair count (results.md's "Overall N"), as the report writes it; evaluation.md quotes the same."""
    (n_gt,) = quoted(r"Valid GT chairs: Easy \d+, Moderate \d+, Hard \d+, Overall (\d+)", d["results"]) or ("0",)
    problems = []
    if half_found_text(int(n_gt)) not in flat(d["results"]):
        problems.append(f"results.md does not say {half_found_text(int(n_gt))!r}")
    got = quoted(r"Finding half of the chairs perfectly scores 100; KITTI Overall gives R40 (\d+) there with many "
                 r"chairs \(([\d,]+) in the val split of docs/results.md\) and R40 (\d+) with 10 ground-truth boxes",
                 d["evaluation"])
    if got is None:
        return problems + ["evaluation.md: no 'KITTI Overall gives R40 N there with many chairs (...)' sentence"]
    if int(got[1].replace(",", "")) != int(n_gt) or f"{half_found_r40(int(n_gt)):.0f}" != got[0]:
        problems.append(f"evaluation.md: R40 {got[0]} with {got[1]} chairs; results.md's {n_gt} give "
                        f"{half_found_r40(int(n_gt)):.0f}")
    if f"{half_found_r40(10):.0f}" != got[2]:
        problems.append(f"evaluation.md: R40 {got[2]} with 10 GT; the protocol gives {half_found_r40(10):.0f}")
    return problems


# --- sparse.md: the ratios on trained weights are results.md's --------------------------------------------------------
def check_sparse_md_ratios(d: Docs) -> list[str]:
    """sparse.md's "backbone A× (default allocator) and B× (reuse), end to end with the exact sparse head C× and D×"
    are results.md's dense / sparse Backbone and dense / sparse+sparse_head Total cells."""
    got = quoted(r"backbone ([\d.]+)× \(default allocator\) and ([\d.]+)× \(reuse\), end to end with the exact sparse "
                 r"head ([\d.]+)× and ([\d.]+)×", d["sparse"])
    if got is None:
        return ["sparse.md: no 'backbone A× (default allocator) and B× (reuse), end to end ...' sentence"]
    problems = []
    for i, alloc in enumerate(("default", "reuse")):
        table = results_runtime(d, alloc)
        for value, row, column in ((got[i], "dense / sparse", "Backbone"),
                                   (got[2 + i], "dense / sparse+sparse_head", "Total")):
            if f"{number(cell(table, row, column)):.1f}" != value:
                problems.append(f"sparse.md: {alloc} {row} {column} {value}× is not results.md's "
                                f"{cell(table, row, column)}")
    return problems


# --- benchmarks.md: our dense backbone + neck against Open3D-ML's -----------------------------------------------------
def check_backbone_against_open3d_ml(d: Docs) -> list[str]:
    """benchmarks.md's "the dense backbone + neck A-Bx faster than Open3D-ML's ... C-Dx on the loaded AVX2 EPYC": A-B
    the range of the Backbone cells of every ``open3d-ml / dense`` row of the runtime tables (benchmarks.md and
    results.md), C-D that of Open3D-ML's over our dense Backbone in the EPYC table of "Numbers"."""
    got = quoted(r"the dense backbone \+ neck ([\d.]+)-([\d.]+)x faster than Open3D-ML's same layers.*?; "
                 r"([\d.]+)-([\d.]+)x on the loaded AVX2 EPYC", d["benchmarks"])
    if got is None:
        return ["benchmarks.md: no 'the dense backbone + neck A-Bx faster than Open3D-ML's ...' sentence"]
    cells = [number(cell(t, "open3d-ml / dense", "Backbone"))
             for name in ("benchmarks", "results") for t in runtime_tables(d[name])
             if any(r[0] == "open3d-ml / dense" for r in t)]  # the deployed table has no peer row
    (epyc,) = [t for t in tables(section(d["benchmarks"], "Numbers")) if t[0][:2] == ["allocator", "model"]]
    backbone = {(r[0], r[1]): number(r[epyc[0].index("Backbone")]) for r in epyc[1:]}
    peer = [backbone[(a, "open3d-ml")] / backbone[(a, "dense")] for a in ("reuse", "default")]
    want = [f"{min(cells):.2f}", f"{max(cells):.2f}", f"{min(peer):.2f}", f"{max(peer):.2f}"]
    return [] if list(got) == want and len(cells) >= 4 else [
        f"benchmarks.md quotes {got[0]}-{got[1]}x / {got[2]}-{got[3]}x; the tables give {want[0]}-{want[1]}x "
        f"({len(cells)} rows) / {want[2]}-{want[3]}x"]


# --- Open3D-ML's mAP: recall-blind wherever it is quoted --------------------------------------------------------------
def _detection_outputs(d: Docs) -> tuple[EvalOutputs, float]:
    """results.md's detection table as the report's records (Open3D-ML mAP per model), and its sparse - dense 3D."""
    (table,) = [t for t in tables(section(d["results"], "Detection")) if "3D AP Open3D-ML mAP" in t[0]]
    o3d = {m: Open3dMlMetrics({"bev": number(cell(table, m, "BEV AP Open3D-ML mAP")),
                               "3d": number(cell(table, m, "3D AP Open3D-ML mAP"))}) for m in ("dense", "sparse")}
    return EvalOutputs(kitti={}, open3d_ml=o3d), number(cell(table, "sparse - dense", "3D AP Open3D-ML mAP"))


def check_open3d_ml_notes(d: Docs) -> list[str]:
    """results.md carries the report's recall-blind note and its verdict on the paper's gap, made from its own
    detection table; the README's rounded mAPs are that table's; every prose paragraph of these docs that quotes an
    Open3D-ML mAP number says that the metric is recall-blind; none calls the paper's -4.61 gap reproduced."""
    problems = []
    ev, gap = _detection_outputs(d)
    dense_3d = ev.open3d_ml["dense"].get("3d")
    with_gap = EvalOutputs(kitti={}, open3d_ml={"dense": ev.open3d_ml["dense"],
                                                "sparse": Open3dMlMetrics({"3d": dense_3d + gap})})
    for line in (recall_blind_note(ev), paper_gap_verdict(with_gap)):
        if line not in d["results"]:
            problems.append(f"results.md lacks the report's {line!r}")
    o3d = {m: ev.open3d_ml[m] for m in ("dense", "sparse")}
    above = [m for m in ("dense", "sparse") if o3d[m].get("3d") > o3d[m].get("bev")]  # impossible if monotone
    which = {2: "above", 1: f"the {above[0] if above else ''} one above", 0: "below"}[len(above)]
    readme = (f"dense {o3d['dense'].get('3d'):.1f} / sparse {o3d['sparse'].get('3d'):.1f} 3D AP, {which} its BEV AP "
              f"({o3d['dense'].get('bev'):.1f} / {o3d['sparse'].get('bev'):.1f})")
    if readme not in flat(d["readme"]):
        problems.append(f"README does not quote results.md's Open3D-ML mAP as {readme!r}")
    for name, text in d.items():
        for para in text.split("\n\n"):
            if para.lstrip().startswith(("|", "```")) or not re.search(r"Open3D-ML (3D |BEV )?mAP\b", para):
                continue
            if re.search(r"\d\d\.\d\d?\b", para) and "recall-blind" not in para:
                problems.append(f"{name}: a paragraph quotes Open3D-ML's mAP without 'recall-blind': {para[:80]!r}")
            for sentence in re.split(r"(?<=[.;:])\s", flat(para)):
                if str(MATTERPORT_CHAIR_AP.sparse_3d_delta) in sentence and re.search(r"(?<!not )reproduced", sentence):
                    problems.append(f"{name}: calls the paper's gap reproduced: {sentence!r}")
    return problems


# --- the differences table of results.md ------------------------------------------------------------------------------
def check_differences(d: Docs) -> list[str]:
    """results.md's differences table has the rows of the report, and their figures are the same doc's: the density
    median of its stats summary, the sparsity frame's D in its op-count table, the head ratio of its runtime tables,
    the training grid of its grid row."""
    text = d["results"]
    (table,) = [t for t in tables(section(text, "Differences from the paper's experiment"))]
    rows = {r[0]: r[2] for r in table[1:]}
    need = ("realism model", "sparse down-conv", "gradient clipping", "sensor height", "robot radius",
            "head at inference", "bench weights", "density D (test split)", "sparsity figures (Figs. 3-4)")
    problems = [f"differences table: no {a!r} row" for a in need if a not in rows]
    if problems:
        return problems
    (median,) = quoted(r'`mpchair stats` summary: `\{"median": ([\d.e-]+)', text)
    if rows["density D (test split)"] != f"median {float(median):.5f} (`mpchair stats`)":
        problems.append(f"density row {rows['density D (test split)']!r}, summary median {median}")
    frame, dens = quoted(r"test frame (\d{6}), a Matterport-Chair frame of D = ([\d.]+)", rows[need[-1]]) or ("", "")
    ops = [t for t in tables(section(text, "Operation counts")) if t[0][:2] == ["frame", "D"]]
    if not ops or [r[1] for r in ops[0][1:] if r[0] == frame] != [dens]:
        problems.append(f"sparsity row: frame {frame!r} D {dens!r} is not the op-count table's")
    head = [f"{number(cell(results_runtime(d, a), 'open3d-ml / dense', 'Head')):.1f}x" for a in ("default", "reuse")]
    if f"Open3D-ML's three convs take {head[0]} / {head[1]} its time" not in rows["head at inference"]:
        problems.append(f"head row {rows['head at inference']!r}; the runtime tables give {head}")
    grid = re.search(r"(\d+ x \d+) pillars of 5 cm over", rows["training grid"])
    if grid is None or f"trained on the {grid.group(1)} crop" not in rows["bench weights"]:
        problems.append(f"bench weights row {rows['bench weights']!r} is not the training grid's")
    if "Targets (issue)" in text:
        problems.append("results.md: 'Targets (issue)' is the issue's wording, not the report's")
    return problems


# --- README: what has been measured where -----------------------------------------------------------------------------
def check_readme_machines(d: Docs) -> list[str]:
    """The README's opening promises no machine the docs have no measurement of: it names the CPUs benchmarks.md
    measured on and the record's (the AVX512-BF16 AMD EPYC), and says "no GPU run yet" while benchmarks.md's GPU
    check says no GPU has been lent."""
    top = flat(d["readme"].split("\n## ", 1)[0])
    problems = [f"README's opening does not name {cpu!r}" for cpu in ("Intel Xeon", "AMD EPYC") if cpu not in top]
    # the machine of every current number: the record's deploy bench ran on an AMD EPYC with AVX512-BF16
    import json

    mach = json.loads((RECORD / "results" / "deploy_bench.json").read_text())["machine"]
    if mach["cpu"] == "AMD EPYC" and "avx512_bf16" in mach["precision_flags"]["bf16"] and (
            "AMD EPYC with AVX512-BF16" not in top.replace("*", "")):
        problems.append("README's opening does not name the record's machine, the AMD EPYC with AVX512-BF16")
    problems += [f"benchmarks.md does not name {cpu!r}" for cpu in ("Xeon", "AMD EPYC") if cpu not in d["benchmarks"]]
    if "a robot CPU or a GPU" in top:
        problems.append("README promises 'a robot CPU or a GPU'")
    no_gpu = "No GPU has been lent to this project yet" in flat(section(d["benchmarks"], "GPU check"))
    if no_gpu != ("no GPU run yet" in top) or "tools/device_check.sh" not in top:
        problems.append("README's GPU sentence does not match benchmarks.md's GPU check section")
    return problems


# --- the committed record: deployed ratios, AP, run times -------------------------------------------------------------
def same(quoted: str, value: float) -> bool:
    """Whether ``quoted`` is ``value`` written to the quoted figure's own decimals (``12.7`` for 12.69...)."""
    decimals = len(quoted.split(".", 1)[1]) if "." in quoted else 0
    return f"{value:.{decimals}f}" == quoted


def prose(text: str) -> str:
    """``text`` without its table lines, whitespace flattened (a table row is checked by the record test)."""
    return flat("\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("|")))


#: The min-max over runs a repeated deploy bench's ratios carry ("12.69x (per run 12.10-13.20x)",
#: reproduction.deploy.ratio_text): the ratio before it is still the one checked.
PER_RUN = r"(?: \(per run [\d.]+-[\d.]+x\))?"


def _rows() -> list[DeployRow]:
    return read_deploy(RECORD / "results")


def _ratio(pair: tuple[str, DeployRow | None, DeployRow | None]) -> float:
    return pair[1].total_ms / pair[2].total_ms


def _ap3d(rows: list[DeployRow], model: str, runtime: str, precision: str, kind: str = "3d") -> float:
    (row,) = [r for r in rows if (r.model, r.runtime, r.precision) == (model, runtime, precision)]
    return row.metrics.ap[kind].overall["R40"]


def check_deployed_ratios(d: Docs) -> list[str]:
    """Every ratio README, benchmarks.md and deployment.md set against "the fastest dense" (or "fastest fp32 dense")
    deployment is the record's like-for-like one (fastest sparse / fastest dense, any precision; fastest sparse /
    fastest fp32 dense, a mixed-precision pair), every "fp32 on both sides" ratio the record's fp32 pair, and every
    ratio of "the paper's architecture (sparse backbone + dense head)" at its fastest / deployed the record's, each to
    the decimals it is quoted with; the README opening quotes all three beside its headline."""
    pairs = like_for_like_pairs(_rows())
    fp32, anyp, _, paper, deployed = (_ratio(p) for p in pairs)
    mixed, precision = pairs[0][1].total_ms / pairs[1][2].total_ms, pairs[1][2].precision
    problems = []
    for name in ("readme", "benchmarks", "deployment"):
        text = prose(d[name])
        # a target ("≥ 5x against the fastest dense") is no measurement
        for m in re.finditer(r"(?<!≥ )(?<![\d.])([\d.]+)x(?:\*\*)?" + PER_RUN
                             + r" (?:faster(?:\*\*)? )?(?:than|against|vs) the fastest (fp32 )?dense", text):
            if not same(m.group(1), mixed if m.group(2) else anyp):
                problems.append(f"{name}: {m.group(0)!r}; the record gives {mixed if m.group(2) else anyp:.2f}x")
            # a fastest sparse row that is not fp32 against the fastest fp32 dense one: say it mixes precisions
            says = (f"{precision} against dense fp32", f"{precision} / dense fp32")
            if m.group(2) and precision != "fp32" and not any(w in text[m.start(): m.end() + 200] for w in says):
                problems.append(f"{name}: {m.group(0)!r} does not say it sets sparse {precision} against dense fp32")
        for m in re.finditer(r"vs (?:the )?fastest (fp32 )?dense \([^)]*\): ([\d.]+)x", text):
            if not same(m.group(2), mixed if m.group(1) else anyp):
                    problems.append(f"{name}: {m.group(0)!r}; the record gives {mixed if m.group(1) else anyp:.2f}x")
        for m in re.finditer(r"(?:fp32 on both sides|fp32 pair)\W.{0,160}?\**([\d.-]+)x", text):
            if not same(m.group(1), fp32):
                problems.append(f"{name}: {m.group(0)!r}; the record's fp32 pair is {fp32:.2f}x")
        for m in re.finditer(r"paper's architecture\** \(sparse backbone \+ dense head\).{0,200}?\**([\d.]+)x\**"
                             + PER_RUN + r" at its fastest.{0,80}?\**([\d.]+)x" + PER_RUN + " deployed", text):
            if not (same(m.group(1), paper) and same(m.group(2), deployed)):
                problems.append(f"{name}: {m.group(0)!r}; the record gives {paper:.2f}x / {deployed:.2f}x deployed")
    top = prose(d["readme"].split("\n## ", 1)[0])
    got = quoted(r"with the exact sparse head\*\* \(our addition to the paper's architecture\) is \*\*([\d.]+)x "
                 r"faster\*\* than the fastest dense deployment.*?The paper's architecture\*\* \(sparse backbone \+ "
                 r"dense head\).*?fp32 on both sides", top)
    if got is None or not same(got[0], anyp):
        problems.append(f"README's headline ({got}) does not name its row (the exact sparse head, the record's "
                        f"{anyp:.2f}x) with the paper's architecture and the fp32 pair beside it")
    return problems


def check_deployed_ap(d: Docs) -> list[str]:
    """deployment.md's int8 AP quote and sparse.md's bf16 AP sentence are the record's evaluations (3D AP Overall R40,
    val), and deployment.md's test tolerance is the one tests/test_deploy_eval.py applies."""
    rows, problems = _rows(), []
    got = quoted(r"dense ONNX Runtime int8 (\d+\.\d+) and OpenVINO int8 (\d+\.\d+) against eager fp32 (\d+\.\d+)",
                 d["deployment"])
    want = [_ap3d(rows, "dense", r, p) for r, p in (("onnxruntime", "int8"), ("openvino", "int8"), ("torch", "fp32"))]
    if got is None or not all(same(g, w) for g, w in zip(got, want)):
        problems.append(f"deployment.md quotes int8 AP {got}; the record gives {[f'{w:.2f}' for w in want]}")
    got = quoted(r"sparse ([\d.]+) 3D / ([\d.]+) BEV against ([\d.]+) / ([\d.]+) in fp32 \(([-+\d.]+) / ([-+\d.]+)\), "
                 r"dense ([\d.]+) / ([\d.]+) against ([\d.]+) / ([\d.]+) \(([-+\d.]+) / ([-+\d.]+)\)", d["sparse"])
    want = []
    for model in ("sparse", "dense"):
        bf16 = [_ap3d(rows, model, "torch", "bf16", k) for k in ("3d", "bev")]
        fp = [_ap3d(rows, model, "torch", "fp32", k) for k in ("3d", "bev")]
        want += [*bf16, *fp, *(b - f for b, f in zip(bf16, fp))]
    if got is None or not all(same(g.lstrip("+"), w) for g, w in zip(got, want)):
        problems.append(f"sparse.md's bf16 AP {got}; the record gives {[f'{w:.2f}' for w in want]}")
    (boxes,) = re.findall(r"^BOXES_OF_SLACK = (\d+)$", (ROOT / "tests" / "test_deploy_eval.py").read_text(), re.M)
    if f"is within {boxes} ground-truth boxes of eager fp32" not in flat(d["deployment"]):
        problems.append(f"deployment.md does not give the test's tolerance ({boxes} ground-truth boxes)")
    return problems


def check_record_examples(d: Docs) -> list[str]:
    """evaluation.md's "dense 3D above BEV" example is the record's Open3D-ML mAP of the dense model; sparse.md's
    allocator sentence quotes the dense backbone of its own 2026-12-03 table."""
    import json

    o3d = json.loads((RECORD / "results" / "eval_dense" / "open3d_ml.json").read_text())["Chair"]
    problems = []
    got = quoted(r"\(results\.md: dense 3D ([\d.]+) above BEV ([\d.]+)\)", d["evaluation"])
    if got is None or not (same(got[0], o3d["3d"]) and same(got[1], o3d["bev"])):
        problems.append(f"evaluation.md's example {got}; the record gives {o3d['3d']:.2f} / {o3d['bev']:.2f}")
    got = quoted(r"the dense backbone measured ([\d.,-]+) ms with the default allocator and ([\d.,-]+) ms with the "
                 r"reuse allocator in the 2026-12-03 runs below", d["sparse"])
    (table,) = [t for t in tables(d["sparse"]) if t[0][:2] == ["run", "dense backbone"]]
    want = [cell(table, f"this branch, 2 threads, {a}", "dense backbone") for a in (
        "default (load 0.8 / 1.3)", "reuse allocator (load 1.3 / 1.5)")]
    if got is None or list(got) != want:
        problems.append(f"sparse.md's allocator sentence {got}; its table gives {want}")
    return problems


def check_run_times(d: Docs) -> list[str]:
    """README's and benchmarks.md's "its steps up to the record took M min, training dense D / sparse S min, the first
    N lines of commands.log": M the sum of those lines' seconds, D / S results.md's training times."""
    lines = (RECORD / "commands.log").read_text().splitlines()
    (dense, sparse), problems = quoted(r"training took dense ([\d.]+) min, sparse ([\d.]+) min", d["results"]), []
    for name in ("readme", "benchmarks"):
        got = quoted(r"its steps up to the record took ([\d.]+) min(?: of wall time)?, training dense ([\d.]+) / "
                     r"sparse ([\d.]+) min,? \(?the first (\d+) lines of `docs/results-data/commands.log`", d[name])
        if got is None:
            problems.append(f"{name}: no 'its steps up to the record took M min, training dense D / sparse S' sentence")
            continue
        minutes = sum(float(ln.split()[0]) for ln in lines[: int(got[3])]) / 60
        if not same(got[0], minutes) or (got[1], got[2]) != (dense, sparse):
            problems.append(f"{name}: {got[0]} min, training {got[1]} / {got[2]}; the record gives {minutes:.1f}, "
                            f"{dense} / {sparse}")
    return problems


#: Figures with no JSON in the record: (doc, a string of the figure); its paragraph or the one before it (a table's
#: caption) says it is a one-off.
ONE_OFFS = (("sparse", "| sparse SubM block 1 (1200 x 576 x 64) |"), ("sparse", "| **3.15x** |"),
            ("benchmarks", "3.14-3.35x at fp32"), ("benchmarks", "1.92x faster dense steps"),
            ("readme", "1.92x faster dense steps"), ("deployment", "4.9x its fp32"),
            ("deployment", "| dense | 754 | 718 |"), ("sparse", "lost -0.98 3D in bf16"))


def check_streaming_block(text: str) -> list[str]:
    """streaming.md's results block is generated from the streaming record (docs/results-data/stream): without one it
    is exactly the block that says so (no result quoted); with one it says what sAP cannot see and states the
    288 x 144 outcome as its table has it."""
    block = text.split(STREAM_BEGIN, 1)[1].split(STREAM_END, 1)[0].strip()
    if not (RECORD / "stream" / "record.json").is_file():
        if block != no_record_section("docs/results-data/stream").strip():
            return ["streaming.md's results block is not the generated no-record block, but there is no streaming "
                    "record (tools/reproduce_stream.py --from-record docs/results-data/stream --steps report)"]
        return []
    problems = []
    if "so every latency under the period gives the same sAP:" not in flat(block):
        problems.append("streaming.md's block does not say what sAP cannot see (latency below one sensor period)")
    (table,) = [t for t in tables(block) if t[0][:3] == ["model", "grid, threads", "offline AP 3D / BEV"]]
    row = {r[0]: r for r in table[1:] if r[1] == "288 x 144, 2 threads"}
    raw, ego = (table[0].index(c) for c in ("sAP raw 3D / BEV", "sAP ego 3D / BEV"))
    want = tuple(row[m][k].split(" / ")[0] for k in (raw, ego) for m in ("dense", "sparse"))
    got = quoted(r"\*\*288 x 144, 2 threads\*\*: .*? Raw sAP 3D dense ([\d.]+) against sparse ([\d.]+) .*? ego sAP 3D "
                 r"dense ([\d.]+) against sparse ([\d.]+)", block)
    if got != (want[0], want[2], want[1], want[3]):
        problems.append(f"streaming.md's 288 x 144 outcome {got}; its table gives {want}")
    return problems


def check_one_offs(d: Docs) -> list[str]:
    """Each of :data:`ONE_OFFS` sits in (or right under) a paragraph that says "one-off"; streaming.md's results
    block is the one generated from the streaming record (:func:`check_streaming_block`)."""
    problems = []
    for name, figure in ONE_OFFS:
        paras = d[name].split("\n\n")
        (i,) = [j for j, para in enumerate(paras) if figure in para]
        if not any("one-off" in para.lower() for para in paras[max(0, i - 1): i + 1]):
            problems.append(f"{name}: {figure!r} is not marked as a one-off")
    problems += check_streaming_block(d["streaming"])
    return problems


def _swap(name: str, old: str, new: str) -> Callable[[Docs], dict[str, str]]:
    def stale(d: Docs) -> dict[str, str]:
        assert old in d[name], (name, old)
        return {**d, name: d[name].replace(old, new, 1)}
    return stale


CHECKS = [
    (check_opening_note, _swap("results", "density D has median 0.00788", "density D has median 0.00565")),
    (check_opening_note, _swap("results", "the backbone ratio (27.4x default", "the backbone ratio (16.4x default")),
    (check_opening_note, _swap("results", "27.4x default / 26.9x reuse", "27.4x default / 16.4x reuse")),
    (check_opening_note, _swap("results", "the total-time ratio (14.6x)", "the total-time ratio (7.9x)")),
    (check_opening_note, _swap("results", "three-conv head it is 4.8x", "three-conv head it is 5.3x")),
    (check_half_found, _swap("results", "R40 50 on the KITTI level", "R40 10 on the KITTI level")),
    (check_half_found, _swap("evaluation", "KITTI Overall gives R40 50 there", "KITTI Overall gives R40 10 there")),
    (check_sparse_md_ratios, _swap("sparse", "backbone 27.4×\n(default", "backbone 16.4×\n(default")),
    (check_sparse_md_ratios, _swap("sparse", "head 22.8× and 23.0×", "head 14.3× and 15.9×")),
    (check_backbone_against_open3d_ml, _swap("benchmarks", "neck 1.15-1.88x faster", "neck 1.16-2.14x faster")),
    (check_open3d_ml_notes, _swap("readme", "that mAP is recall-blind (", "that mAP is the paper's (")),
    (check_open3d_ml_notes, _swap("results", "| dense | 55.45 | 53.75 | 56.59 | 55.94 | 77.28 | 77.68 |",
                                  "| dense | 55.45 | 53.75 | 56.59 | 55.94 | 77.28 | 77.78 |")),
    (check_open3d_ml_notes, _swap("readme", "Whether the paper's -4.61 gap holds is\n**inconclusive** from these runs",
                                  "The paper's -4.61 gap is\nreproduced on it")),
    (check_differences, _swap("results", "median 0.00788 (`mpchair stats`)", "median 0.00565 (`mpchair stats`)")),
    (check_differences, _swap("results", "Open3D-ML's three convs take 16.4x", "Open3D-ML's three convs take 9.2x")),
    (check_differences, _swap("results", "## Targets and this run", "## Targets (issue) and this run")),
    (check_readme_machines, _swap("readme", "yet: `tools/device_check.sh` is the", "yet: a script is the")),
    (check_readme_machines, _swap("readme", "no robot CPU and no GPU run yet", "a robot CPU or a GPU")),
    (check_readme_machines, _swap("readme", "**AMD EPYC with AVX512-BF16 / VNNI**", "**AMD EPYC**")),
    # issue 48's stale figures, each as the docs quoted it
    (check_deployed_ratios, _swap("benchmarks", "is 12.69x faster than the fastest dense", "is 22.4x faster than the "
                                  "fastest dense")),
    (check_deployed_ratios, _swap("benchmarks", "33.36x faster than the fastest fp32", "63.6x faster than the fastest "
                                  "fp32")),
    (check_deployed_ratios, _swap("deployment", "The fastest rows were the ones", "**Headline: fastest sparse (exact "
                                  "head, ONNX Runtime int8, 10.2 ms) vs fastest dense (OpenVINO int8, 227 ms):\n22.4x; "
                                  "vs the fastest fp32 dense (OpenVINO fp32, 646 ms): 63.6x.** The fastest rows were "
                                  "the ones")),
    (check_deployed_ratios, _swap("deployment", "the same fastest rows.", "headline 25.6x against the fastest dense "
                                  "(OpenVINO int8), 66.9x against the fastest fp32 dense (OpenVINO fp32).")),
    (check_deployed_ratios, _swap("deployment", "OpenVINO fp32, 261.1 ms: 20.25x", "OpenVINO fp32, 646 ms: 33-44x")),
    (check_deployed_ratios, _swap("readme", "33.4x faster than the fastest fp32 dense one (OpenVINO, 261.1 ms), but\n"
                                  "that sets sparse int8 against dense fp32:", "about 33x faster than the fastest fp32 "
                                  "dense one (OpenVINO, 261.1 ms);")),
    (check_deployed_ratios, _swap("readme", "is **12.7x faster** than", "is **22.4x faster** than")),
    (check_deployed_ratios, _swap("readme", "**5.7x** at its fastest", "**12.7x** at its fastest")),
    (check_deployed_ratios, _swap("readme", "**The paper's architecture** (sparse backbone + dense head) against the "
                                  "same dense row", "The dense row")),
    (check_deployed_ap, _swap("deployment", "dense ONNX Runtime int8 53.85", "dense ONNX Runtime int8 51.32")),
    (check_deployed_ap, _swap("deployment", "against eager fp32\n  53.75", "against eager fp32\n  51.73")),
    (check_deployed_ap, _swap("deployment", "is within 3 ground-truth boxes", "is within 5 points")),
    (check_deployed_ap, _swap("sparse", "sparse 51.28 3D / 53.06 BEV", "sparse 51.44 3D / 52.95 BEV")),
    (check_deployed_ap, _swap("sparse", "dense 53.78 / 55.44", "dense 51.62 / 53.56")),
    (check_record_examples, _swap("evaluation", "dense 3D 77.68 above BEV 77.28", "dense 3D 78.54 above BEV 77.93")),
    (check_record_examples, _swap("sparse", "measured 475.9 ms", "measured 458-502 ms")),
    (check_record_examples, _swap("sparse", "and 436.9 ms with the reuse", "and 522 ms with the reuse")),
    (check_run_times, _swap("benchmarks", "took 76.7 min, training dense 19.0 / sparse 15.8 min",
                            "took 113 min, training dense 30.8 / sparse 29.2 min")),
    (check_run_times, _swap("readme", "took 76.7 min of wall time", "took 113 min of wall time")),
    (check_one_offs, _swap("deployment", "a one-off measurement filed with", "a measurement filed with")),
    (check_one_offs, _swap("sparse", "A one-off: the tool printed these tables", "The tool printed these tables")),
    (check_one_offs, _swap("readme", "in a one-off `tools/bench_train_step.py`", "in a `tools/bench_train_step.py`")),
    (check_one_offs, _swap("streaming", "**No record yet.**", "**No record yet.** Sparse raw sAP 18.31.")),
    (check_one_offs, _swap("streaming", "so every latency under the period gives the same sAP:", "so sAP ranks it:")),
]


@pytest.mark.parametrize("check", sorted({c for c, _ in CHECKS}, key=lambda c: c.__name__),
                         ids=lambda c: c.__name__)
def test_docs_quote_their_tables(docs, check) -> None:
    assert check(docs) == []


@pytest.mark.parametrize(("check", "stale"), CHECKS, ids=[f"{c.__name__}-{i}" for i, (c, _) in enumerate(CHECKS)])
def test_a_stale_figure_fails_its_check(docs, check, stale) -> None:
    assert check(stale(docs)) != []
