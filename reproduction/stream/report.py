"""The results section of ``docs/streaming.md`` (between its markers): the headline table of both models under every
setting (grid x thread budget) and of the oracle at each measured latency, the highest sensor rate each model keeps up
with, the machine line, sAP against speed and rate under the headline setting (tables and PNG curves), and the speed
at which sparse overtakes dense. AP in percent (R40, Chair, IoU 0.5), times in ms."""

from __future__ import annotations

from pathlib import Path

from detector.eval.bootstrap import GapEstimate
from mpchair.core.atomic import atomic_open, write_text
from mpchair.core.doctable import replace_block
from mpchair.paper import ROBOT_CORES, TABLE_II
from reproduction.runner import logged_commands
from reproduction.stream.gaps import StreamGap
from reproduction.stream.results import HouseCheck, RunKey, StreamSummary
from reproduction.stream.sweep import HEADLINE, MODELS, MODES, Setting

BEGIN, END = "<!-- reproduce-stream results: begin -->", "<!-- reproduce-stream results: end -->"
Runs = dict[RunKey, StreamSummary]
#: The paper's conclusion this page tests: Sparse PointPillars at 1 Hz on the robot's 4-core CPU (its Table II total)
#: "with more than 75 % of the CPU left".
PAPER_ROBOT_SPARSE_MS = TABLE_II["robot"]["sparse"].total.mean_ms


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


def keeps_up_hz(p95_ms: float | None) -> float | None:
    """The highest sensor rate (Hz) at which a detector of this p95 latency keeps up: 95 % of its frames finish
    within one sensor period, so the one worker takes (nearly) every frame, one frame stale."""
    return None if not p95_ms else 1000.0 / p95_ms


def _f(x: float | None, nd: int = 1) -> str:
    return "n/a" if x is None else f"{x:.{nd}f}"


def logged_text(log: Path) -> str:
    """"N commands, M min in all" from the runner's commands.log (every finished command with its wall time)."""
    cmds = logged_commands(log.read_text() if log.exists() else "")
    return f"{len(cmds)} commands in commands.log, {sum(s for s, _ in cmds) / 60:.1f} min in all"


def houses_text(check: HouseCheck | None, heldout_seed: int | None) -> str:
    """Which houses the streams drive through and whether the models were trained on any of them."""
    if check is None:
        return "Houses: not streamed yet."
    made = (f"held-out houses made for these streams (`mpchair synth --seed {heldout_seed}`)"
            if heldout_seed is not None else "the houses given with --houses")
    said = f"Houses ({len(check.streamed)}): {made}: {', '.join(check.streamed)}"
    if check.dataset is None:
        return said + ("; the training dataset's manifest.json (--dataset) was not found, so whether the models saw "
                       "them is not checked.")
    if check.overlap:
        return (said + f". **Not held out:** {', '.join(check.overlap)} also gave the models' train / val frames "
                f"({check.dataset.name}), so these streams are not on unseen houses.")
    return (said + f"; none of them (by id or by file checksums) is among the {len(check.trained)} houses of the "
            "training dataset's train and val frames, so the models never saw them.")


def _row(label: str, setting: Setting, raw: StreamSummary, ego: StreamSummary, offline: StreamSummary | None,
         latency: str) -> str:
    """A headline table row: offline AP, sAP raw and ego (3D / BEV), ``latency``, staleness, frames processed."""
    st, sf = ego.staleness_ms, ego.staleness_frames
    off = offline or ego
    return (f"| {label} | {setting.text} | {_f(off.ap(offline=True), 2)} / {_f(off.ap('bev', offline=True), 2)} "
            f"| {_f(raw.ap(), 2)} / {_f(raw.ap('bev'), 2)} "
            f"| {_f(ego.ap(), 2)} / {_f(ego.ap('bev'), 2)} "
            f"| {latency} | {_f(st.mean)} / {_f(st.p95)} "
            f"| {_f(sf.mean, 2)} / {_f(sf.p95, 2)} | {100 * ego.frames_processed:.1f} % |")


def _offline_runs(runs: Runs, settings: list[Setting]) -> dict[tuple[str, str], StreamSummary]:
    """{(model, grid): the headline-stream summary with an offline AP} (threads do not change a model's outputs, so
    a grid's offline pass serves every thread budget)."""
    found = {}
    for s in settings:
        for m in MODELS:
            ego = runs.get((m, *HEADLINE, s.name, "ego"))
            if ego is not None and ego.offline_ap is not None and (m, s.grid) not in found:
                found[(m, s.grid)] = ego
    return found


def _headline_rows(runs: Runs, settings: list[Setting]) -> list[str]:
    """Both models on the headline stream under every setting, then the oracle at each measured latency (what that
    latency alone costs a perfect detector: the upper bound of the model's sAP)."""
    v0, f0 = HEADLINE
    offline = _offline_runs(runs, settings)
    lines = []
    for s in settings:
        for m in MODELS:
            raw, ego = runs.get((m, v0, f0, s.name, "raw")), runs.get((m, v0, f0, s.name, "ego"))
            if raw is None or ego is None:
                lines.append(f"| {m} | {s.text} | not measured | | | | | | |")
                continue
            lines.append(_row(m, s, raw, ego, offline.get((m, s.grid)),
                              f"{_f(ego.latency_ms.median)} / {_f(ego.latency_ms.p95)}"))
    for s in settings:
        for m in MODELS:
            raw, ego = (runs.get((f"oracle@{m}", v0, f0, s.name, mode)) for mode in MODES)
            if raw is not None and ego is not None:
                lines.append(_row(f"oracle at {m}'s latency", s, raw, ego, None,
                                  f"{_f(ego.latency_ms.median)} (constant)"))
    return lines


def _keep_up_lines(runs: Runs, settings: list[Setting]) -> list[str]:
    """Per model and setting: its latency on the headline stream, the highest sensor rate it keeps up with, and the
    share of its threads and of this machine's CPU it leaves idle at 1 Hz, the paper's 1 Hz claim beside."""
    rows = []
    for s in settings:
        for m in MODELS:
            ego = runs.get((m, *HEADLINE, s.name, "ego"))
            if ego is None or ego.latency_ms.median is None:
                continue
            med, p95 = ego.latency_ms.median, ego.latency_ms.p95
            cpus = ego.machine.logical_cpus if ego.machine else None
            if med > 1000:  # slower than one frame a second: it cannot run at 1 Hz at all
                busy, left = "all (slower than 1 Hz)", "none"
            else:
                busy = f"{100 * med / 1000:.0f} %"
                left = "n/a" if not cpus else f"{100 * (1 - s.threads * med / 1000 / cpus):.0f} % of {cpus}"
            rows.append(f"| {m} | {s.text} | {_f(med)} / {_f(p95)} | {_f(keeps_up_hz(p95))} | {busy} | {left} |")
    if not rows:
        return []
    paper_left = 100 * (1 - PAPER_ROBOT_SPARSE_MS / 1000)
    return ["", "Highest sensor rate each model keeps up with (1000 / p95 latency: 95 % of its frames finish within a "
            "sensor period, so the one worker takes nearly every frame) and the CPU it leaves at 1 Hz:", "",
            "| model | grid, threads | latency median / p95 (ms) | keeps up to (Hz) | its threads busy at 1 Hz | "
            "CPU left at 1 Hz (logical CPUs) |", "|---|---|---|---|---|---|", *rows, "",
            f"Paper: Sparse PointPillars takes {PAPER_ROBOT_SPARSE_MS} ms per frame on the robot's "
            f"{ROBOT_CORES}-core CPU (Table II), so at 1 Hz it keeps the CPU {paper_left:.0f} % idle "
            "(\"1 Hz with more than 75 % of the CPU left\")."]


def _machine_lines(runs: Runs) -> list[str]:
    """The machine the latencies were measured on (the first run that names one), and the GPU column's absence."""
    machine = next((r.machine for r in runs.values() if r.machine), None)
    if not machine:
        return []

    def repeats(headline: bool) -> str:
        """The latency repeats of the runs on the headline stream (or on the others), "n/a" for none."""
        found = {r.repeats for k, r in runs.items() if r.repeats is not None and (k[1:3] == HEADLINE) == headline}
        return " / ".join(map(str, sorted(found))) or "n/a"

    return ["", f"Latency measured end to end per processed frame on {machine.cpu}, torch {machine.torch}, allocator "
            f"{machine.allocator}, at each row's thread budget; median of {repeats(True)} timed runs per frame on the "
            f"headline stream, {repeats(False)} on the sweep's other streams, after warm-up. GPU column: not measured "
            "— this machine has no GPU (`detector stream-eval --device cuda` on one)."]


def _axis_point(axis: str, x: float) -> tuple[float, float]:
    """The (speed, rate) of sweep value ``x`` on ``axis``: a speed at the headline rate, a rate at its speed."""
    return (x, HEADLINE[1]) if axis == "speed" else (HEADLINE[0], x)


def _crossover_lines(runs: Runs, xs: list[float], setting: Setting) -> list[str]:
    """Per mode, where sparse overtakes dense on the speed sweep (none when a point was not scored)."""
    lines = []
    for mode in MODES:
        try:
            d = [runs[("dense", x, HEADLINE[1], setting.name, mode)].ap() for x in xs]
            s = [runs[("sparse", x, HEADLINE[1], setting.name, mode)].ap() for x in xs]
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


def _sweep_lines(runs: Runs, axis: str, xs: list[float], setting: Setting, figure: str | None) -> list[str]:
    """sAP 3D R40 of both models and modes against ``axis`` (``speed`` at 10 Hz, ``rate`` at 0.5 m/s) under
    ``setting``, with the fraction of frames each model processed."""
    unit = "m/s" if axis == "speed" else "Hz"
    what = "robot speed (at 10 Hz)" if axis == "speed" else "sensor rate (at 0.5 m/s)"
    if len(xs) < 2:
        # a sweep of one point is the headline stream again: say it was not run rather than draw a one-point curve
        return ["", f"sAP against {what}: not measured in this run (`--{axis}s` gave one point)."]
    lines = ["", f"sAP 3D R40 against {what}, {setting.text}:", "",
             f"| {axis} ({unit}) | " + " | ".join(f"{m} {mode}" for m in MODELS for mode in MODES)
             + " | frames processed dense / sparse |", "|---|" + "---|" * (len(MODELS) * len(MODES) + 1)]
    for x in xs:
        keys = [(m, *_axis_point(axis, x), setting.name, mode) for m in MODELS for mode in MODES]
        done = [runs.get((m, *_axis_point(axis, x), setting.name, "ego")) for m in MODELS]
        processed = " / ".join("n/a" if r is None else f"{100 * r.frames_processed:.0f} %" for r in done)
        lines.append(f"| {x:g} | " + " | ".join(_f(runs[k].ap(), 2) if k in runs else "n/a" for k in keys)
                     + f" | {processed} |")
    if axis == "speed":
        lines += _crossover_lines(runs, xs, setting)
    if figure is not None:
        lines += ["", f"![sAP against {axis}]({figure})"]
    return lines


#: What sAP cannot see, said in every results block (a property of the metric, true of any run).
SAP_BLIND_SPOT = (
    "What sAP cannot see: **latency below one sensor period.** A model that finishes a frame within the period is "
    "scored against the next frame whatever its latency (staleness exactly one frame, {period:g} ms at {rate:g} Hz), "
    "so every latency under the period gives the same sAP: sAP measures whether a model keeps up and how stale its "
    "outputs are in whole frames, not how much faster than the period it is or how much CPU it leaves free (the "
    "keeps-up table's).")


def _keeps_up(ego: StreamSummary | None) -> bool | None:
    """Whether a model kept up with the headline stream: 95 % of its frames within one sensor period (p95 latency at
    most the period); None when not measured."""
    if ego is None or ego.latency_ms.p95 is None:
        return None
    return ego.latency_ms.p95 <= 1000.0 / HEADLINE[1]


def _ahead(dense: float | None, sparse: float | None) -> str:
    if dense is None or sparse is None:
        return "not scored"
    return "dense" if dense > sparse else "sparse" if sparse > dense else "neither (level)"


def outcome_lines(runs: Runs, settings: list[Setting]) -> list[str]:
    """Per grid, under the first thread budget, on the headline stream: which model keeps up, and both models' raw
    and ego sAP 3D with who is ahead (the outcome the tables hold, in words)."""
    lines = []
    budget = settings[0].threads if settings else None
    for s in [s for s in settings if s.threads == budget]:
        got = {(m, mode): runs.get((m, *HEADLINE, s.name, mode)) for m in MODELS for mode in MODES}
        if any(v is None for v in got.values()):
            continue
        kept = []
        for m in MODELS:
            ego = got[(m, "ego")]
            said = {True: "keeps up", False: "does not keep up", None: "was not timed"}[_keeps_up(ego)]
            kept.append(f"{m} {said} (p95 {_f(ego.latency_ms.p95)} ms, {100 * ego.frames_processed:.0f} % of frames "
                        "processed)")
        sap = {k: v.ap() for k, v in got.items()}
        lines.append(
            f"- **{s.text}**: {'; '.join(kept)}. Raw sAP 3D dense {_f(sap[('dense', 'raw')], 2)} against sparse "
            f"{_f(sap[('sparse', 'raw')], 2)} ({_ahead(sap[('dense', 'raw')], sap[('sparse', 'raw')])} ahead), ego "
            f"sAP 3D dense {_f(sap[('dense', 'ego')], 2)} against sparse {_f(sap[('sparse', 'ego')], 2)} "
            f"({_ahead(sap[('dense', 'ego')], sap[('sparse', 'ego')])} ahead).")
    if not lines:
        return []
    v0, f0 = HEADLINE
    return ["", f"Outcome on the headline stream ({v0:g} m/s, {f0:g} Hz; keeps up = p95 latency within the "
            f"{1000 / f0:g} ms sensor period), per grid at {budget} thread{'s' * (budget != 1)}:", "", *lines]


def blind_spot_lines(runs: Runs, settings: list[Setting]) -> list[str]:
    """:data:`SAP_BLIND_SPOT`, with this run's evidence: each model and grid measured under several thread budgets
    that all keep up, its raw sAP 3D at each latency."""
    v0, f0 = HEADLINE
    evidence = []
    for grid in dict.fromkeys(s.grid for s in settings):
        for m in MODELS:
            kept = [(s, runs[(m, v0, f0, s.name, "raw")]) for s in settings if s.grid == grid
                    and (m, v0, f0, s.name, "raw") in runs and _keeps_up(runs.get((m, v0, f0, s.name, "ego")))]
            if len(kept) > 1:
                evidence.append(f"{m} at {grid.replace('x', ' x ')} scores raw sAP 3D "
                                + ", ".join(f"{_f(r.ap(), 2)} at {_f(r.latency_ms.median)} ms ({s.threads} "
                                            f"thread{'s' * (s.threads != 1)})" for s, r in kept))
    text = SAP_BLIND_SPOT.format(period=1000 / f0, rate=f0)
    if evidence:
        text += " In this run: " + "; ".join(evidence) + "."
    return ["", text]


def gap_lines(gaps: dict[str, StreamGap], settings: list[Setting]) -> list[str]:
    """The sparse - dense sAP gap per setting and mode with its 95 % interval over episodes (whole episodes
    resampled)."""
    found = [(s, gaps[s.name]) for s in settings if s.name in gaps]
    if not found:
        return ["", "Sparse - dense sAP gap with an interval over episodes: not computed in this run (the gaps step)."]
    first = found[0][1]

    def cell(g: GapEstimate | None) -> str:
        if g is None:
            return "n/a"
        lo, hi = g.ci95
        return f"{g.mean:+.2f} [{lo:+.2f}, {hi:+.2f}]"

    rows = [f"| {s.text} | {cell(g.gaps.get('raw'))} | {cell(g.gaps.get('ego'))} |" for s, g in found]
    return ["", f"Sparse - dense sAP gap ({first.metric.upper()} R40, points) on the headline stream, with its 95 % "
            f"interval over episodes: {first.resamples} resamples of the {first.episodes} episodes ({first.frames} "
            "frames), whole episodes drawn with replacement, the same ones for both models (an interval that holds "
            "0: the two models cannot be told apart on these episodes):", "",
            "| grid, threads | raw sAP gap [95 % CI] | ego sAP gap [95 % CI] |", "|---|---|---|", *rows]


def results_section(runs: Runs, settings: list[Setting], speeds: list[float], rates: list[float],
                    figures: dict[str, str], note: str, gaps: dict[str, StreamGap] | None = None) -> str:
    """The markdown between the markers: ``runs[(model, speed, rate, setting name, mode)]`` = stream-eval summaries;
    ``settings``: headline first; ``figures``: the curves' paths relative to the page, by axis; ``note``: the opening
    lines; ``gaps``: the episode-bootstrap gaps by setting name."""
    v0, f0 = HEADLINE
    lines = [note, "", f"Headline stream: {v0:g} m/s, {f0:g} Hz, every setting (Chair, AP R40 in percent over every "
             "labelled chair, IoU 0.5; sAP = streaming AP; the offline AP is each grid's, whatever the threads):", "",
             "| model | grid, threads | offline AP 3D / BEV | sAP raw 3D / BEV | sAP ego 3D / BEV | latency median / "
             "p95 (ms) | staleness mean / p95 (ms) | staleness mean / p95 (frames) | frames processed |",
             "|---|---|---|---|---|---|---|---|---|", *_headline_rows(runs, settings),
             *outcome_lines(runs, settings), *blind_spot_lines(runs, settings), *gap_lines(gaps or {}, settings),
             *_keep_up_lines(runs, settings), *_machine_lines(runs)]
    for axis, xs in (("speed", speeds), ("rate", rates)):
        lines += _sweep_lines(runs, axis, xs, settings[0], figures.get(axis))
    return "\n".join(lines) + "\n"


def plot_curves(runs: Runs, setting: Setting, speeds: list[float], rates: list[float],
                out_dir: Path) -> dict[str, Path]:
    """``{"speed": png, "rate": png}``: sAP 3D R40 of both models, raw and ego, against speed and rate under
    ``setting`` (an axis of fewer than two points has no curve)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = {}
    for axis, xs, unit in (("speed", speeds, "m/s"), ("rate", rates, "Hz")):
        if len(xs) < 2:  # no sweep along this axis (_sweep_lines says so)
            continue
        fig, ax = plt.subplots(figsize=(5.5, 3.8), dpi=110)
        for m, color in zip(MODELS, ("tab:red", "tab:blue")):
            for mode, style in zip(MODES, ("--", "-")):
                keys = [(x, (m, *_axis_point(axis, x), setting.name, mode)) for x in xs]
                pts = [(x, runs[k].ap()) for x, k in keys if k in runs]
                if pts:
                    ax.plot(*zip(*pts), style, marker="o", color=color, label=f"{m} {mode}")
        ax.set_xlabel(f"{'robot speed' if axis == 'speed' else 'sensor rate'} ({unit})")
        ax.set_ylabel("sAP 3D, R40 (%)")
        ax.set_xticks(xs)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title(f"streaming AP vs {axis} ({'10 Hz' if axis == 'speed' else '0.5 m/s'}; {setting.text})",
                     fontsize=10)
        fig.tight_layout()
        paths[axis] = out_dir / f"stream-sap-vs-{axis}.png"
        with atomic_open(paths[axis], "wb") as f:
            fig.savefig(f, format="png")
        plt.close(fig)
    return paths


def write_section(doc: Path, section: str) -> None:
    """Replace the text between the markers of ``doc`` with ``section`` (markers appended if both are absent; one
    without the other is an :class:`~mpchair.core.errors.InputError` naming the doc, which stays as it was)."""
    text = doc.read_text(encoding="utf-8") if doc.exists() else ""
    if BEGIN not in text and END not in text:
        text = text.rstrip("\n") + ("\n\n" if text else "") + f"{BEGIN}\n{END}\n"
    write_text(doc, replace_block(text, BEGIN, END, section, doc))


def no_record_section(record: str) -> str:
    """The results block where no streaming record exists (``record``: its folder as the docs name it): it says so and
    how a quiet session fills it, and quotes no result."""
    v0, f0 = HEADLINE
    return "\n".join([
        f"**No record yet.** `{record}` holds no streaming record, so this block quotes no result. A session on an "
        "otherwise idle machine (the latencies are measured, not simulated) fills it with `make reproduce-stream` "
        "(after `make reproduce`, whose trained models it streams): its record step writes the results JSON, the "
        f"command log and the machine record into `{record}` and this block from them; "
        f"`tools/reproduce_stream.py --from-record {record} --steps report` writes the block again from the record "
        "alone.", "", SAP_BLIND_SPOT.format(period=1000 / f0, rate=f0)]) + "\n"
