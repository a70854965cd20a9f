"""The streaming reproduction's command lines: ``mpchair stream`` per sweep point, ``detector stream-eval`` measuring
each model's latency and saving its outputs, scoring them raw and ego, and the oracle at each model's latency.

Each step's output file marks it done (skipped unless ``force``); paths are those of the work folder
(:func:`~detector.reproduce.stream.sweep.stream_dir`, :func:`~detector.reproduce.stream.sweep.eval_dir`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from detector.reproduce.runner import BIN, Runner
from detector.reproduce.stream.results import read_summary
from detector.reproduce.stream.sweep import HEADLINE, MODELS, MODES, Scale, eval_dir, stream_dir

STEPS = ("streams", "measure", "score", "report")


@dataclass(frozen=True)
class StreamPlan:
    """One invocation's choices: work folder, scale, steps asked for, houses root and ids, each model's config and
    checkpoint, the sweep points, torch threads, the allocator environment while measuring, workers, seed, force,
    dry run."""

    out: Path
    scale: Scale
    steps: tuple[str, ...]
    houses_root: Path
    houses: tuple[str, ...]
    configs: dict[str, Path]
    checkpoints: dict[str, Path]
    points: tuple[tuple[float, float], ...]
    threads: int = 2
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


def run_streams(plan: StreamPlan, r: Runner) -> None:
    """``mpchair stream``: one stream per sweep point, of the plan's houses."""
    for v, f in plan.points:
        s = stream_dir(plan.out, v, f)
        if plan.todo("streams", s / "stream.json"):
            cmd = [str(BIN / "mpchair"), "stream", "--root", str(plan.houses_root), "--episodes",
                   str(plan.scale.episodes), "--rate", f"{f:g}", "--speed", f"{v:g}", "--duration",
                   f"{plan.scale.duration:g}", "--seed", str(plan.seed), "--out", str(s), "--workers",
                   str(plan.workers), "--quiet"]
            for h in plan.houses:
                cmd += ["--house", h]
            r.run(cmd)


def _measure_command(plan: StreamPlan, point: tuple[float, float], model: str) -> list[str]:
    """``detector stream-eval`` measuring ``model``'s latency per processed frame and saving its outputs."""
    ev = eval_dir(plan.out, *point, model)
    cmd = [str(BIN / "detector"), "stream-eval", "--data", str(stream_dir(plan.out, *point)), "--config",
           str(plan.configs[model]), "--checkpoint", str(plan.checkpoints[model]), "--threads", str(plan.threads),
           "--repeats", str(plan.scale.repeats), "--warmup", str(plan.scale.warmup), "--latency-log",
           str(ev / "latency.json"), "--json", str(ev / "measure.json"), "--quiet"]
    # the offline AP (every frame through the model) only where the table needs it; elsewhere the outputs of the
    # processed frames are enough to replay the schedule
    return cmd + ["--save-results", str(ev / "outputs")] + ([] if point == HEADLINE else ["--no-offline"])


def run_measure_and_score(plan: StreamPlan, r: Runner) -> None:
    """Per point and model: measure (latency log and saved outputs), then score raw and ego from those outputs,
    replaying the measured latencies exactly."""
    for point in plan.points:
        for m in MODELS:
            ev = eval_dir(plan.out, *point, m)
            if plan.todo("measure", ev / "latency.json"):
                r.run(_measure_command(plan, point, m), env=plan.env or None)
            for mode in MODES:
                if plan.todo("score", ev / f"{mode}.json"):
                    r.run([str(BIN / "detector"), "stream-eval", "--data", str(stream_dir(plan.out, *point)),
                           "--results", str(ev / "outputs"), "--latency", str(ev / "latency.json"), "--mode", mode,
                           "--json", str(ev / f"{mode}.json"), "--quiet"])


def run_oracle(plan: StreamPlan, r: Runner) -> None:
    """The oracle (each frame's own labels) at each model's median latency on the headline stream: what that latency
    alone costs."""
    s = stream_dir(plan.out, *HEADLINE)
    for m in MODELS:
        measured = eval_dir(plan.out, *HEADLINE, m) / "measure.json"
        for mode in MODES:
            target = eval_dir(plan.out, *HEADLINE, f"oracle-at-{m}") / f"{mode}.json"
            if plan.todo("score", target) and (plan.dry_run or measured.exists()):
                summary = read_summary(measured)
                ms = summary.latency_ms.median if summary is not None else f"<{m} median latency>"
                r.run([str(BIN / "detector"), "stream-eval", "--data", str(s), "--oracle", "--latency-ms", str(ms),
                       "--mode", mode, "--json", str(target), "--quiet"])


#: The steps before the report, in the order they run.
COMMAND_STEPS = (run_streams, run_measure_and_score, run_oracle)
