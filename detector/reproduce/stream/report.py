"""The results section of ``docs/streaming.md`` (between its markers): the headline table of both models and of the
oracle at each model's latency, the machine line, sAP against speed and rate (tables and PNG curves), and the speed at
which sparse overtakes dense. AP in percent (R40, Chair, IoU 0.5), times in ms."""

from __future__ import annotations

from pathlib import Path

from detector.reproduce.runner import logged_commands
from detector.reproduce.stream.results import RunKey, StreamSummary
from detector.reproduce.stream.sweep import HEADLINE, MODELS, MODES
from mpchair.core.atomic import atomic_open, write_text

BEGIN, END = "<!-- reproduce-stream results: begin -->", "<!-- reproduce-stream results: end -->"
Runs = dict[RunKey, StreamSummary]


def crossover(xs: list[float], dense: list[float], sparse: list[float]) -> float | None:
    """The smallest x where sparse sAP reaches dense sAP, linear between sweep points (``None``: it never does; the
    first x when sparse is ahead from the start)."""
    d = [s - q for s, q in zip(sparse, dense)]
    if d and d[0] >= 0:
        return xs[0]
    for i in range(1, len(xs)):
        if d[i] >= 0:
            return xs[i - 1] + (xs[i] - xs[i - 1]) * (-d[i - 1]) / (d[i] - d[i - 1])
    return None


def _f(x: float | None, nd: int = 1) -> str:
    return "n/a" if x is None else f"{x:.{nd}f}"


def logged_text(log: Path) -> str:
    """"N commands, M min in all" from the runner's commands.log (every finished command with its wall time)."""
    cmds = logged_commands(log.read_text() if log.exists() else "")
    return f"{len(cmds)} commands in commands.log, {sum(s for s, _ in cmds) / 60:.1f} min in all"


def _row(label: str, raw: StreamSummary, ego: StreamSummary, latency: str) -> str:
    """A headline table row: offline AP, sAP raw and ego (3D / BEV), ``latency``, staleness, frames processed."""
    st, sf = ego.staleness_ms, ego.staleness_frames
    return (f"| {label} | {_f(ego.ap(offline=True), 2)} / {_f(ego.ap('bev', offline=True), 2)} "
            f"| {_f(raw.ap(), 2)} / {_f(raw.ap('bev'), 2)} "
            f"| {_f(ego.ap(), 2)} / {_f(ego.ap('bev'), 2)} "
            f"| {latency} | {_f(st.mean)} / {_f(st.p95)} "
            f"| {_f(sf.mean, 2)} / {_f(sf.p95, 2)} | {100 * ego.frames_processed:.1f} % |")


def _headline_rows(runs: Runs) -> list[str]:
    """Both models on the headline stream, then the oracle at each model's latency (what that latency alone costs a
    perfect detector: the upper bound of the model's sAP)."""
    v0, f0 = HEADLINE
    lines = []
    for m in MODELS:
        raw, ego = runs.get((m, v0, f0, "raw")), runs.get((m, v0, f0, "ego"))
        if raw is None or ego is None:
            lines.append(f"| {m} | not measured | | | | | | |")
            continue
        lines.append(_row(m, raw, ego, f"{_f(ego.latency_ms.median)} / {_f(ego.latency_ms.p95)}"))
    for m in MODELS:
        raw, ego = runs.get((f"oracle@{m}", v0, f0, "raw")), runs.get((f"oracle@{m}", v0, f0, "ego"))
        if raw is not None and ego is not None:
            lines.append(_row(f"oracle at {m}'s latency", raw, ego, f"{_f(ego.latency_ms.median)} (constant)"))
    return lines


def _machine_lines(runs: Runs) -> list[str]:
    """The machine the latencies were measured on (the first run that names one), and the GPU column's absence."""
    machine = next((r.machine for r in runs.values() if r.machine), None)
    if not machine:
        return []
    repeats = next(r.repeats for r in runs.values() if r.repeats is not None)
    return ["", f"Latency measured end to end per processed frame on {machine.cpu}, "
            f"{machine.torch_threads} torch threads, torch {machine.torch}, allocator "
            f"{machine.allocator}; median of {repeats} "
            "runs after warm-up. GPU column: not measured — this machine has no GPU (`detector stream-eval "
            "--device cuda` on one)."]


def _axis_point(axis: str, x: float) -> tuple[float, float]:
    """The (speed, rate) of sweep value ``x`` on ``axis``: a speed at the headline rate, a rate at its speed."""
    return (x, HEADLINE[1]) if axis == "speed" else (HEADLINE[0], x)


def _crossover_lines(runs: Runs, xs: list[float]) -> list[str]:
    """Per mode, where sparse overtakes dense on the speed sweep (none when a point was not scored)."""
    lines = []
    for mode in MODES:
        try:
            d = [runs[("dense", x, HEADLINE[1], mode)].ap() for x in xs]
            s = [runs[("sparse", x, HEADLINE[1], mode)].ap() for x in xs]
        except KeyError:
            continue
        c = crossover(xs, d, s)
        if c is None:
            said = f"sparse does not overtake dense between {xs[0]:g} and {xs[-1]:g} m/s"
        elif s[0] == d[0]:
            said = f"sparse and dense are level already at {xs[0]:g} m/s"
        elif s[0] > d[0]:
            said = f"sparse is ahead of dense already at {xs[0]:g} m/s"
        else:
            said = f"sparse overtakes dense at about {c:.2f} m/s"
        lines += ["", f"- {mode}: {said}"]
    return lines


def _sweep_lines(runs: Runs, axis: str, xs: list[float], figure: str | None) -> list[str]:
    """sAP 3D R40 of both models and modes against ``axis`` (``speed`` at 10 Hz, ``rate`` at 0.5 m/s)."""
    unit = "m/s" if axis == "speed" else "Hz"
    what = "robot speed (at 10 Hz)" if axis == "speed" else "sensor rate (at 0.5 m/s)"
    lines = ["", f"sAP 3D R40 against {what}:", "",
             f"| {axis} ({unit}) | " + " | ".join(f"{m} {mode}" for m in MODELS for mode in MODES) + " |",
             "|---|" + "---|" * (len(MODELS) * len(MODES))]
    for x in xs:
        keys = [(m, *_axis_point(axis, x), mode) for m in MODELS for mode in MODES]
        lines.append(f"| {x:g} | " + " | ".join(_f(runs[k].ap(), 2) if k in runs else "n/a" for k in keys) + " |")
    if axis == "speed":
        lines += _crossover_lines(runs, xs)
    if figure is not None:
        lines += ["", f"![sAP against {axis}]({figure})"]
    return lines


def results_section(runs: Runs, speeds: list[float], rates: list[float], figures: dict[str, str], note: str) -> str:
    """The markdown between the markers: ``runs[(model, speed, rate, mode)]`` = stream-eval summaries; ``figures``:
    the curves' paths relative to the page, by axis; ``note``: the opening line."""
    v0, f0 = HEADLINE
    lines = [note, "", f"Headline: {v0:g} m/s, {f0:g} Hz (Chair, AP R40 in percent over every labelled chair, "
             "IoU 0.5; sAP = streaming AP):", "",
             "| model | offline AP 3D / BEV | sAP raw 3D / BEV | sAP ego 3D / BEV | latency median / p95 (ms) | "
             "staleness mean / p95 (ms) | staleness mean / p95 (frames) | frames processed |",
             "|---|---|---|---|---|---|---|---|", *_headline_rows(runs), *_machine_lines(runs)]
    for axis, xs in (("speed", speeds), ("rate", rates)):
        lines += _sweep_lines(runs, axis, xs, figures.get(axis))
    return "\n".join(lines) + "\n"


def plot_curves(runs: Runs, speeds: list[float], rates: list[float], out_dir: Path) -> dict[str, Path]:
    """``{"speed": png, "rate": png}``: sAP 3D R40 of both models, raw and ego, against speed and rate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = {}
    for axis, xs, unit in (("speed", speeds, "m/s"), ("rate", rates, "Hz")):
        fig, ax = plt.subplots(figsize=(5.5, 3.8), dpi=110)
        for m, color in zip(MODELS, ("tab:red", "tab:blue")):
            for mode, style in zip(MODES, ("--", "-")):
                keys = [(x, (m, *_axis_point(axis, x), mode)) for x in xs]
                pts = [(x, runs[k].ap()) for x, k in keys if k in runs]
                if pts:
                    ax.plot(*zip(*pts), style, marker="o", color=color, label=f"{m} {mode}")
        ax.set_xlabel(f"{'robot speed' if axis == 'speed' else 'sensor rate'} ({unit})")
        ax.set_ylabel("sAP 3D, R40 (%)")
        ax.set_xticks(xs)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title(f"streaming AP vs {axis} ({'10 Hz' if axis == 'speed' else '0.5 m/s'})", fontsize=10)
        fig.tight_layout()
        paths[axis] = out_dir / f"stream-sap-vs-{axis}.png"
        with atomic_open(paths[axis], "wb") as f:
            fig.savefig(f, format="png")
        plt.close(fig)
    return paths


def write_section(doc: Path, section: str) -> None:
    """Replace the text between the markers of ``doc`` with ``section`` (markers appended if absent)."""
    text = doc.read_text(encoding="utf-8") if doc.exists() else ""
    block = f"{BEGIN}\n{section}{END}"
    if BEGIN in text and END in text:
        text = text[: text.index(BEGIN)] + block + text[text.index(END) + len(END):]
    else:
        text = text.rstrip("\n") + ("\n\n" if text else "") + block + "\n"
    write_text(doc, text)
