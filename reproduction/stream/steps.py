"""The streaming reproduction's command lines: ``mpchair synth`` of the held-out houses, ``mpchair stream`` per sweep
point, ``detector stream-eval`` measuring each model's latency under each setting and saving its outputs, scoring them
raw and ego, and the oracle at each measured latency.

Each step's output file marks it done (skipped unless ``force``); paths are those of the work folder
(:func:`~reproduction.stream.sweep.stream_dir`, :func:`~reproduction.stream.sweep.eval_dir`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from reproduction.runner import BIN, Runner
from reproduction.steps import house_ids
from reproduction.stream.results import read_summary
from reproduction.stream.sweep import GRIDS, HEADLINE, MODELS, MODES, Scale, Setting, eval_dir, stream_dir

STEPS = ("houses", "streams", "measure", "score", "gaps", "report", "record")


@dataclass(frozen=True)
class StreamPlan:
    """One invocation's choices: work folder, scale, steps asked for, the houses root and ids (empty: every house of
    the root when the streams are made), the seed of the held-out houses to synthesize into the root (None: the root
    is given and not made here), the configs folder, each model's checkpoint, the sweep points, the settings
    (headline first), the allocator environment while measuring, workers, seed, force, dry run."""

    out: Path
    scale: Scale
    steps: tuple[str, ...]
    houses_root: Path
    houses: tuple[str, ...]
    heldout_seed: int | None
    configs: Path
    checkpoints: dict[str, Path]
    points: tuple[tuple[float, float], ...]
    settings: tuple[Setting, ...]
    env: dict[str, str] | None = None
    workers: int = 2
    seed: int = 0
    force: bool = False
    dry_run: bool = False

    def todo(self, step: str, output: Path) -> bool:
        """Whether ``step`` makes ``output`` now (asked for, and not there unless forced); says when skipped."""
        if step not in self.steps:
            return False
        if not self.force and output.exists():
            print(f"[{step}] {output} exists, skipped")
            return False
        return True

    def config(self, setting: Setting, model: str) -> Path:
        """The experiment config of ``model`` at ``setting``'s grid."""
        return self.configs / GRIDS[setting.grid].format(m=model)

    def stream_houses(self) -> list[str]:
        """The houses to stream: the given ids, else every house of the root (a placeholder before it exists)."""
        return list(self.houses) or house_ids(self.houses_root) or [f"<house ids from {self.houses_root}>"]


@dataclass(frozen=True)
class MeasuredRun:
    """One latency measurement: a point's stream, a setting, whether it also runs the offline pass (every frame, for
    the offline AP: once per grid, on the headline stream) and its latency repeats."""

    point: tuple[float, float]
    setting: Setting
    offline: bool
    repeats: int


def measured_runs(plan: StreamPlan) -> list[MeasuredRun]:
    """Every measurement of the plan: every setting on the headline stream (the offline pass under the first thread
    budget of each grid), the headline setting on the sweep's other streams."""
    runs, grids_done = [], set()
    for s in plan.settings:
        runs.append(MeasuredRun(HEADLINE, s, s.grid not in grids_done, plan.scale.repeats))
        grids_done.add(s.grid)
    runs += [MeasuredRun(p, plan.settings[0], False, plan.scale.sweep_repeats) for p in plan.points if p != HEADLINE]
    return runs


def run_houses(plan: StreamPlan, r: Runner) -> None:
    """``mpchair synth``: the held-out houses the streams drive through (none of them in the training data)."""
    if plan.heldout_seed is not None and plan.todo("houses", plan.houses_root / "v1" / "scans"):
        r.run([str(BIN / "mpchair"), "synth", "--out", str(plan.houses_root), "--houses",
               str(plan.scale.heldout_houses), "--seed", str(plan.heldout_seed)])


def run_streams(plan: StreamPlan, r: Runner) -> None:
    """``mpchair stream``: one stream per sweep point, of the plan's houses."""
    for v, f in plan.points:
        s = stream_dir(plan.out, v, f)
        if plan.todo("streams", s / "stream.json"):
            cmd = [str(BIN / "mpchair"), "stream", "--root", str(plan.houses_root), "--episodes",
                   str(plan.scale.episodes), "--rate", f"{f:g}", "--speed", f"{v:g}", "--duration",
                   f"{plan.scale.duration:g}", "--seed", str(plan.seed), "--out", str(s), "--workers",
                   str(plan.workers), "--quiet"]
            for h in plan.stream_houses():
                cmd += ["--house", h]
            r.run(cmd)


def _measure_command(plan: StreamPlan, run: MeasuredRun, model: str) -> list[str]:
    """``detector stream-eval`` measuring ``model``'s latency per processed frame under ``run``'s setting and saving
    its outputs (of every frame with the offline pass, else of the processed frames)."""
    ev = eval_dir(plan.out, *run.point, run.setting, model)
    cmd = [str(BIN / "detector"), "stream-eval", "--data", str(stream_dir(plan.out, *run.point)), "--config",
           str(plan.config(run.setting, model)), "--checkpoint", str(plan.checkpoints[model]), "--threads",
           str(run.setting.threads), "--repeats", str(run.repeats), "--warmup", str(plan.scale.warmup),
           "--latency-log", str(ev / "latency.json"), "--json-out", str(ev / "measure.json"), "--quiet"]
    return cmd + ["--save-results", str(ev / "outputs")] + ([] if run.offline else ["--no-offline"])


def run_measure_and_score(plan: StreamPlan, r: Runner) -> None:
    """Per measurement and model: measure (latency log and saved outputs), then score raw and ego from those outputs,
    replaying the measured latencies exactly."""
    for run in measured_runs(plan):
        for m in MODELS:
            ev = eval_dir(plan.out, *run.point, run.setting, m)
            if plan.todo("measure", ev / "latency.json"):
                r.run(_measure_command(plan, run, m), env=plan.env or None)
            for mode in MODES:
                if plan.todo("score", ev / f"{mode}.json"):
                    r.run([str(BIN / "detector"), "stream-eval", "--data", str(stream_dir(plan.out, *run.point)),
                           "--results", str(ev / "outputs"), "--latency", str(ev / "latency.json"), "--mode", mode,
                           "--json-out", str(ev / f"{mode}.json"), "--quiet"])


def run_oracle(plan: StreamPlan, r: Runner) -> None:
    """The oracle (each frame's own labels) at each model's median latency under each setting on the headline
    stream: what that latency alone costs."""
    s = stream_dir(plan.out, *HEADLINE)
    for setting in plan.settings:
        for m in MODELS:
            measured = eval_dir(plan.out, *HEADLINE, setting, m) / "measure.json"
            for mode in MODES:
                target = eval_dir(plan.out, *HEADLINE, setting, f"oracle-at-{m}") / f"{mode}.json"
                if plan.todo("score", target) and (plan.dry_run or measured.exists()):
                    summary = read_summary(measured)
                    ms = summary.latency_ms.median if summary is not None else f"<{m} median latency>"
                    r.run([str(BIN / "detector"), "stream-eval", "--data", str(s), "--oracle", "--latency-ms",
                           str(ms), "--mode", mode, "--json-out", str(target), "--quiet"])


#: The steps before the report, in the order they run.
COMMAND_STEPS = (run_houses, run_streams, run_measure_and_score, run_oracle)
