"""``detector bench --runs N``: the same bench run N times, each in a process of its own, and every ratio reported as
the median with its min-max over the runs.

One bench run is one draw of this machine's state (what else ran, where the allocator and the caches stood, how the
kernel placed the threads): the same day, the same weights and the same machine gave dense / sparse backbone ratios
from 18.3x to 27.4x depending on the harness and what ran beside it (issue 48). Separate processes start from a cold
allocator and fresh kernels each time, so the spread over runs shows how much of a ratio is the run. The runs follow
each other (never at the same time: they would compete for the cores); the ratios are those of
:func:`detector.bench.report.ratio_rows` (within each runtime x precision, the first model / each other, and the peer /
each of ours) and the headline's speed-ups where the bench has one.

The result is the first run's :class:`~detector.bench.result.BenchResult` (every reader of ``detector bench --json``
reads it as before; its tables are that run's) with a ``repeated`` entry (:class:`Repeated`): per ratio and component
the value of every run, their median, min and max; and every row's total ms per run.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from detector.bench.result import BenchResult
from mpchair.core.errors import InputError, RunError


@dataclass(frozen=True)
class Spread:
    """One quantity over the runs: every run's value (in run order), their median, min and max."""

    values: tuple[float, ...]

    @property
    def median(self) -> float:
        return float(statistics.median(self.values))

    def to_json(self) -> dict[str, Any]:
        return {"median": self.median, "min": min(self.values), "max": max(self.values), "values": list(self.values)}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Spread:
        return cls(values=tuple(float(v) for v in d["values"]))

    def text(self, unit: str = "x") -> str:
        """``12.70x [12.10-13.20]``: the median and the min-max."""
        return f"{self.median:.2f}{unit} [{min(self.values):.2f}-{max(self.values):.2f}]"


@dataclass(frozen=True)
class Repeated:
    """The spread of a bench over ``runs`` separate processes: ``ratios[row][component]`` (the ratio rows'
    speed-ups), ``headline`` (``speedup``, ``speedup_vs_fp32_dense``; empty without a headline) and ``totals[row]``
    (each row's total ms per frame)."""

    runs: int
    ratios: Mapping[str, Mapping[str, Spread]]
    headline: Mapping[str, Spread]
    totals: Mapping[str, Spread]

    def to_json(self) -> dict[str, Any]:
        return {"runs": self.runs, "processes": "one per run, one after another",
                "ratios": {r: {k: s.to_json() for k, s in c.items()} for r, c in self.ratios.items()},
                "headline": {k: s.to_json() for k, s in self.headline.items()},
                "totals_ms": {r: s.to_json() for r, s in self.totals.items()}}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Repeated:
        return cls(runs=int(d["runs"]),
                   ratios={r: {k: Spread.from_json(s) for k, s in c.items()} for r, c in d["ratios"].items()},
                   headline={k: Spread.from_json(s) for k, s in d["headline"].items()},
                   totals={r: Spread.from_json(s) for r, s in d["totals_ms"].items()})


def repeated(results: Sequence[BenchResult]) -> Repeated:
    """The spread of ``results`` (one per run, the same bench): a ratio, headline speed-up or row total is kept only
    where every run has it (a run that timed other rows is not the same bench: an :class:`InputError`)."""
    from detector.bench.report import ratio_rows

    if not results:
        raise InputError("no bench run to summarize")
    names = [tuple(m.name for m in r.models) for r in results]
    if len(set(names)) != 1:
        raise InputError(f"the runs timed different rows ({names[0]} vs {next(n for n in names if n != names[0])})")
    per_run = [dict(ratio_rows(r)) for r in results]
    ratios = {row: {k: Spread(tuple(run[row][k] for run in per_run)) for k in per_run[0][row]}
              for row in per_run[0]}
    headline = {}
    if all(r.headline is not None for r in results):
        headline = {k: Spread(tuple(getattr(r.headline, k) for r in results))
                    for k in ("speedup", "speedup_vs_fp32_dense")}
    totals = {m.name: Spread(tuple(r.models[i].components["total"].mean_ms for r in results))
              for i, m in enumerate(results[0].models) if "total" in m.components}
    return Repeated(runs=len(results), ratios=ratios, headline=headline, totals=totals)


def child_args(params: Mapping[str, Any], options: Sequence[Any], json_out: Path) -> list[str]:
    """The ``detector bench`` arguments of one run: this invocation's options as given (``params`` by name,
    ``options`` click's parameters) with ``--runs 1``, no progress bars and the result to ``json_out``."""
    skip = {"runs", "json_out", "as_json", "markdown", "no_progress"}
    args = []
    for opt in options:
        value = params.get(opt.name)
        if opt.name in skip or value is None:
            continue
        flag = opt.opts[0]
        if getattr(opt, "is_flag", False):
            args += [flag] if value else []
        elif getattr(opt, "multiple", False):
            for v in value:
                args += [flag, str(v)]
        else:
            args += [flag, str(value)]
    return [*args, "--runs", "1", "--no-progress", "--json-out", str(json_out)]


def run_repeated(args: Sequence[str], runs: int, echo=print) -> tuple[BenchResult, Repeated, dict]:
    """Run ``detector bench ARGS`` (:func:`child_args`, its ``--json-out`` replaced per run) ``runs`` times, each in
    a new process, one after another; the first run's result, the spread, and the first run's JSON with the
    ``repeated`` entry. A run that fails is a :class:`RunError` naming it (its own messages are above)."""
    if runs < 2:
        raise InputError(f"--runs must be >= 2 to repeat (got {runs})")
    results, first = [], None
    with tempfile.TemporaryDirectory(prefix="bench-runs-") as tmp:
        for i in range(runs):
            out = Path(tmp) / f"run{i}.json"
            argv = [*args[:-1], str(out)] if args and args[-2] == "--json-out" else [*args, "--json-out", str(out)]
            echo(f"bench run {i + 1} of {runs} (a process of its own)")
            done = subprocess.run([sys.executable, "-m", "detector", "bench", *argv], stdout=subprocess.DEVNULL)
            if done.returncode != 0:
                raise RunError(f"bench run {i + 1} of {runs} failed with exit status {done.returncode}")
            data = json.loads(out.read_text())
            first = data if first is None else first
            results.append(BenchResult.from_json(data))
    rep = repeated(results)
    return results[0], rep, {**first, "repeated": rep.to_json()}


def format_repeated(rep: Repeated, markdown: bool = False) -> str:
    """The spread as lines: each ratio row's components and the headline's speed-ups as median [min-max] over the
    runs, then each row's total ms (``markdown``: as a list, so that a page keeps one line each)."""
    item = "- " if markdown else "  "
    lines = [f"Over {rep.runs} runs, each in a process of its own: median [min-max]" + (":\n" if markdown else "")]
    for row, comps in rep.ratios.items():
        lines.append(f"{item}{row}: " + ", ".join(f"{k} {s.text()}" for k, s in comps.items()))
    for k, s in rep.headline.items():
        lines.append(f"{item}headline {k}: {s.text()}")
    for row, s in rep.totals.items():
        lines.append(f"{item}{row} total: {s.text(' ms')}")
    return "\n".join(lines)
