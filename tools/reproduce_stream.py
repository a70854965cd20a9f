"""``make reproduce-stream``: the paper's open question measured — streaming AP of dense vs sparse PointPillars on a
robot driving through the test houses, with latencies measured on this CPU (``docs/streaming.md``).

Steps (each a list of exact ``mpchair`` / ``detector`` command lines, run as subprocesses and recorded):

    streams   mpchair stream          one stream per (speed, rate): the speeds at 10 Hz, the rates at 0.5 m/s (the
                                      headline stream, 0.5 m/s at 10 Hz, is shared)
    measure   detector stream-eval    per model and stream: latency measured per processed frame (--latency-log),
                                      2 torch threads, and the outputs (--save-results): of every frame on the
                                      headline stream (for the offline AP), of the processed frames elsewhere
    score     detector stream-eval    ego and raw from the saved outputs, replaying the measured latencies exactly
                                      (--results, --latency LOG); and the oracle (a perfect detector) at each
                                      model's median latency on the headline stream: what the latency alone costs
    report    docs/streaming.md       the results section between its markers: the table, the curves (PNG), the
                                      speed at which sparse overtakes dense

A step whose outputs exist is skipped (``--force`` redoes it). ``--scale full`` (the default) replaces the results
section of ``docs/streaming.md``; ``--scale small`` is a few-minute end-to-end check that writes
``<work folder>/streaming.md`` instead. The trained models default to ``make reproduce``'s
(``out/reproduce-full/runs/{dense,sparse}/last.pt``), the houses to its synthetic houses.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tools"):
    if str(p) not in sys.path:  # run as a script from a fresh checkout
        sys.path.insert(0, str(p))

from reproduce import BIN, CONFIGS, REUSE_ENV, Runner, house_ids, logged_commands  # noqa: E402

STEPS = ("streams", "measure", "score", "report")
MODELS = ("dense", "sparse")
MODES = ("raw", "ego")
HEADLINE = (0.5, 10.0)  # m/s, Hz
BEGIN, END = "<!-- reproduce-stream results: begin -->", "<!-- reproduce-stream results: end -->"


@dataclasses.dataclass(frozen=True)
class Scale:
    """Sizes of one scale: houses (None = all), episodes per house, episode cap (s), latency repeats and warm-up."""

    houses: int | None
    episodes: int
    duration: float
    repeats: int
    warmup: int


SCALES = {
    "small": Scale(houses=2, episodes=1, duration=8.0, repeats=1, warmup=2),
    # every reproduction house, one 20 s episode each (look-around included): ~1,600 frames at 10 Hz per stream;
    # about 45 min on 2 idle AVX2 cores, most of it the dense model's measured latencies (2 repeats per frame)
    "full": Scale(houses=None, episodes=1, duration=20.0, repeats=2, warmup=10),
}


def stream_name(speed: float, rate: float) -> str:
    """Folder name of the stream of one (speed m/s, rate Hz) point."""
    return f"v{speed:g}-f{rate:g}"


def sweep_points(speeds: list[float], rates: list[float]) -> list[tuple[float, float]]:
    """Every (speed, rate) needed, headline first: the speeds at 10 Hz and the rates at 0.5 m/s."""
    pts = [HEADLINE] + [(v, HEADLINE[1]) for v in speeds] + [(HEADLINE[0], f) for f in rates]
    return list(dict.fromkeys(pts))


# --- report ---------------------------------------------------------------------------------------------------------
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


def _ap(summary: dict, key: str = "sAP", metric: str = "3d") -> float | None:
    block = summary.get(key)
    return None if block is None else block["Chair"][metric]["R40"]


def _logged(log: Path) -> str:
    """"N commands, M min in all" from the runner's commands.log (every finished command with its wall time)."""
    cmds = logged_commands(log.read_text() if log.exists() else "")
    return f"{len(cmds)} commands in commands.log, {sum(s for s, _ in cmds) / 60:.1f} min in all"


def results_section(runs: dict, speeds: list[float], rates: list[float], figures: dict[str, str], note: str) -> str:
    """The markdown between the markers: ``runs[(model, speed, rate, mode)]`` = stream-eval summaries."""
    v0, f0 = HEADLINE
    lines = [note, "", f"Headline: {v0:g} m/s, {f0:g} Hz (Chair, AP R40 in percent over every labelled chair, "
             "IoU 0.5; sAP = streaming AP):", "",
             "| model | offline AP 3D / BEV | sAP raw 3D / BEV | sAP ego 3D / BEV | latency median / p95 (ms) | "
             "staleness mean / p95 (ms) | staleness mean / p95 (frames) | frames processed |",
             "|---|---|---|---|---|---|---|---|"]
    for m in MODELS:
        raw, ego = runs.get((m, v0, f0, "raw")), runs.get((m, v0, f0, "ego"))
        if raw is None or ego is None:
            lines.append(f"| {m} | not measured | | | | | | |")
            continue
        lat, st, sf = ego["latency_ms"], ego["staleness_ms"], ego["staleness_frames"]
        lines.append(
            f"| {m} | {_f(_ap(ego, 'offline_AP'), 2)} / {_f(_ap(ego, 'offline_AP', 'bev'), 2)} "
            f"| {_f(_ap(raw), 2)} / {_f(_ap(raw, metric='bev'), 2)} "
            f"| {_f(_ap(ego), 2)} / {_f(_ap(ego, metric='bev'), 2)} "
            f"| {_f(lat['median'])} / {_f(lat['p95'])} | {_f(st['mean'])} / {_f(st['p95'])} "
            f"| {_f(sf['mean'], 2)} / {_f(sf['p95'], 2)} | {100 * ego['frames_processed']:.1f} % |")
    for m in MODELS:  # what the same latency costs a perfect detector: the upper bound of each model's sAP
        raw, ego = runs.get((f"oracle@{m}", v0, f0, "raw")), runs.get((f"oracle@{m}", v0, f0, "ego"))
        if raw is not None and ego is not None:
            lat, st, sf = ego["latency_ms"], ego["staleness_ms"], ego["staleness_frames"]
            lines.append(
                f"| oracle at {m}'s latency | {_f(_ap(ego, 'offline_AP'), 2)} / {_f(_ap(ego, 'offline_AP', 'bev'), 2)} "
                f"| {_f(_ap(raw), 2)} / {_f(_ap(raw, metric='bev'), 2)} "
                f"| {_f(_ap(ego), 2)} / {_f(_ap(ego, metric='bev'), 2)} | {_f(lat['median'])} (constant) "
                f"| {_f(st['mean'])} / {_f(st['p95'])} | {_f(sf['mean'], 2)} / {_f(sf['p95'], 2)} "
                f"| {100 * ego['frames_processed']:.1f} % |")
    machine = next((r["machine"] for r in runs.values() if r.get("machine")), None)
    if machine:
        lines += ["", f"Latency measured end to end per processed frame on {machine['cpu']}, "
                  f"{machine['torch_threads']} torch threads, torch {machine['torch']}, allocator "
                  f"{machine['allocator']}; median of {next(r['repeats'] for r in runs.values() if 'repeats' in r)} "
                  "runs after warm-up. GPU column: not measured — this machine has no GPU (`detector stream-eval "
                  "--device cuda` on one)."]
    for axis, xs, key in (("speed", speeds, lambda x: (x, f0)), ("rate", rates, lambda x: (v0, x))):
        unit = "m/s" if axis == "speed" else "Hz"
        what = "robot speed (at 10 Hz)" if axis == "speed" else "sensor rate (at 0.5 m/s)"
        lines += ["", f"sAP 3D R40 against {what}:", "",
                  f"| {axis} ({unit}) | " + " | ".join(f"{m} {mode}" for m in MODELS for mode in MODES) + " |",
                  "|---|" + "---|" * (len(MODELS) * len(MODES))]
        for x in xs:
            cells = [_f(_ap(runs[(m, *key(x), mode)]), 2) if (m, *key(x), mode) in runs else "n/a"
                     for m in MODELS for mode in MODES]
            lines.append(f"| {x:g} | " + " | ".join(cells) + " |")
        if axis == "speed":
            for mode in MODES:
                try:
                    d = [_ap(runs[("dense", x, f0, mode)]) for x in xs]
                    s = [_ap(runs[("sparse", x, f0, mode)]) for x in xs]
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
        if axis in figures:
            lines += ["", f"![sAP against {axis}]({figures[axis]})"]
    return "\n".join(lines) + "\n"


def plot_curves(runs: dict, speeds: list[float], rates: list[float], out_dir: Path) -> dict[str, Path]:
    """``{"speed": png, "rate": png}``: sAP 3D R40 of both models, raw and ego, against speed and rate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v0, f0 = HEADLINE
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    for axis, xs, key, unit in (("speed", speeds, lambda x: (x, f0), "m/s"), ("rate", rates, lambda x: (v0, x), "Hz")):
        fig, ax = plt.subplots(figsize=(5.5, 3.8), dpi=110)
        for m, color in zip(MODELS, ("tab:red", "tab:blue")):
            for mode, style in zip(MODES, ("--", "-")):
                pts = [(x, _ap(runs[(m, *key(x), mode)])) for x in xs if (m, *key(x), mode) in runs]
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
        fig.savefig(paths[axis])
        plt.close(fig)
    return paths


def write_report(doc: Path, section: str) -> None:
    """Replace the text between the markers of ``doc`` with ``section`` (markers appended if absent)."""
    text = doc.read_text(encoding="utf-8") if doc.exists() else ""
    block = f"{BEGIN}\n{section}{END}"
    if BEGIN in text and END in text:
        text = text[: text.index(BEGIN)] + block + text[text.index(END) + len(END):]
    else:
        text = text.rstrip("\n") + ("\n\n" if text else "") + block + "\n"
    doc.parent.mkdir(parents=True, exist_ok=True)
    tmp = doc.with_name(f".{doc.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, doc)


# --- the run --------------------------------------------------------------------------------------------------------
def _floats(text: str) -> list[float]:
    return sorted(float(x) for x in text.split(",") if x.strip())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scale", choices=sorted(SCALES), default="full")
    p.add_argument("--steps", default=",".join(STEPS), help=f"comma-separated subset of {','.join(STEPS)}")
    p.add_argument("--out", type=Path, default=None, help="work folder (default out/reproduce-stream-<scale>)")
    p.add_argument("--houses", type=Path, default=ROOT / "out" / "reproduce-full" / "houses",
                   help="houses root (default: make reproduce's synthetic houses)")
    p.add_argument("--house", action="append", default=None, help="house id (repeatable; default: every house)")
    for m in MODELS:
        p.add_argument(f"--{m}-config", type=Path, default=CONFIGS / f"mpchair_{m}_cpu.yaml")
        p.add_argument(f"--{m}-checkpoint", type=Path, default=ROOT / "out" / "reproduce-full" / "runs" / m / "last.pt")
    p.add_argument("--speeds", default="0.25,0.5,1.0", help="robot speeds of the speed sweep, m/s (at 10 Hz)")
    p.add_argument("--rates", default="5,10,20", help="sensor rates of the rate sweep, Hz (at 0.5 m/s)")
    p.add_argument("--episodes", type=int, default=None, help="episodes per house instead of the scale's")
    p.add_argument("--duration", type=float, default=None, help="episode cap, seconds, instead of the scale's")
    p.add_argument("--repeats", type=int, default=None,
                   help="measured latency: median of this many runs per processed frame instead of the scale's "
                        "(full: 2); 1 halves the measuring time")
    p.add_argument("--threads", type=int, default=2, help="torch threads of the measured detectors")
    p.add_argument("--allocator", choices=["reuse", "default"], default="reuse",
                   help="glibc allocator setting while measuring (docs/benchmarks.md; reuse = what a deployment sets)")
    p.add_argument("--workers", type=int, default=2, help="mpchair stream worker processes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--docs", type=Path, default=None,
                   help="report file (default: docs/streaming.md for --scale full, <work folder>/streaming.md else)")
    p.add_argument("--note", action="append", default=[],
                   help="a sentence for the report's opening line, e.g. how the run deviated (repeatable)")
    p.add_argument("--force", action="store_true", help="redo steps whose outputs exist")
    p.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = p.parse_args(argv)
    steps = [s.strip() for s in args.steps.split(",") if s.strip()]
    if [s for s in steps if s not in STEPS]:
        print(f"error: unknown step(s) in {args.steps!r}; choose from {list(STEPS)}", file=sys.stderr)
        return 2
    sc = SCALES[args.scale]
    sc = dataclasses.replace(sc, episodes=args.episodes or sc.episodes, duration=args.duration or sc.duration,
                             repeats=sc.repeats if args.repeats is None else args.repeats)
    if sc.repeats < 1:
        print("error: --repeats must be >= 1", file=sys.stderr)
        return 2
    speeds, rates = _floats(args.speeds), _floats(args.rates)
    out = (args.out or ROOT / "out" / f"reproduce-stream-{args.scale}").resolve()
    out.mkdir(parents=True, exist_ok=True)
    r = Runner(args.dry_run, out / "commands.log")
    mp, det = str(BIN / "mpchair"), str(BIN / "detector")
    houses = args.house or house_ids(args.houses) or [f"<house ids from {args.houses}>"]
    houses = houses[: sc.houses] if sc.houses else houses
    env = REUSE_ENV if args.allocator == "reuse" else {}
    points = sweep_points(speeds, rates)
    t0 = time.perf_counter()
    missing = [c for m in MODELS for c in (getattr(args, f"{m}_checkpoint"),) if not c.exists()]
    if missing and not args.dry_run and ({"measure", "score"} & set(steps)):
        print(f"error: checkpoint(s) not found: {', '.join(map(str, missing))} (run make reproduce first, or pass "
              "--dense-checkpoint / --sparse-checkpoint)", file=sys.stderr)
        return 2

    def todo(step: str, output: Path) -> bool:
        if step not in steps:
            return False
        if not args.force and output.exists():
            print(f"[{step}] {output} exists, skipped")
            return False
        return True

    for v, f in points:
        s = out / "streams" / stream_name(v, f)
        if todo("streams", s / "stream.json"):
            cmd = [mp, "stream", "--root", str(args.houses), "--episodes", str(sc.episodes), "--rate", f"{f:g}",
                   "--speed", f"{v:g}", "--duration", f"{sc.duration:g}", "--seed", str(args.seed), "--out", str(s),
                   "--workers", str(args.workers), "--quiet"]
            for h in houses:
                cmd += ["--house", h]
            r.run(cmd)
    for v, f in points:
        s = out / "streams" / stream_name(v, f)
        for m in MODELS:
            ev = out / "eval" / stream_name(v, f) / m
            model = ["--config", str(getattr(args, f"{m}_config")),
                     "--checkpoint", str(getattr(args, f"{m}_checkpoint"))]
            if todo("measure", ev / "latency.json"):
                cmd = [det, "stream-eval", "--data", str(s), *model, "--threads", str(args.threads), "--repeats",
                       str(sc.repeats), "--warmup", str(sc.warmup), "--latency-log", str(ev / "latency.json"),
                       "--json", str(ev / "measure.json"), "--quiet"]
                # the offline AP (every frame through the model) only where the table needs it; elsewhere the
                # outputs of the processed frames are enough to replay the schedule
                cmd += ["--save-results", str(ev / "outputs")] + ([] if (v, f) == HEADLINE else ["--no-offline"])
                r.run(cmd, env=env or None)
            for mode in MODES:
                if todo("score", ev / f"{mode}.json"):
                    r.run([det, "stream-eval", "--data", str(s), "--results", str(ev / "outputs"), "--latency",
                           str(ev / "latency.json"), "--mode", mode, "--json", str(ev / f"{mode}.json"), "--quiet"])
    # the oracle (each frame's own labels) at each model's median latency: what that latency alone costs
    s = out / "streams" / stream_name(*HEADLINE)
    for m in MODELS:
        measured = out / "eval" / stream_name(*HEADLINE) / m / "measure.json"
        for mode in MODES:
            target = out / "eval" / stream_name(*HEADLINE) / f"oracle-at-{m}" / f"{mode}.json"
            if todo("score", target) and (args.dry_run or measured.exists()):
                ms = (json.loads(measured.read_text())["latency_ms"]["median"] if measured.exists()
                      else f"<{m} median latency>")
                r.run([det, "stream-eval", "--data", str(s), "--oracle", "--latency-ms", str(ms), "--mode", mode,
                       "--json", str(target), "--quiet"])
    if "report" in steps and not args.dry_run:
        runs = {}
        for v, f in points:
            for m in MODELS:
                for mode in MODES:
                    path = out / "eval" / stream_name(v, f) / m / f"{mode}.json"
                    if path.exists():
                        summary = json.loads(path.read_text())
                        measured = out / "eval" / stream_name(v, f) / m / "measure.json"
                        if measured.exists():  # the machine the latencies were measured on
                            summary.setdefault("machine", json.loads(measured.read_text()).get("machine"))
                        runs[(m, v, f, mode)] = summary
        for m in MODELS:
            for mode in MODES:
                path = out / "eval" / stream_name(*HEADLINE) / f"oracle-at-{m}" / f"{mode}.json"
                if path.exists():
                    runs[(f"oracle@{m}", *HEADLINE, mode)] = json.loads(path.read_text())
        doc = args.docs or (ROOT / "docs" / "streaming.md" if args.scale == "full" else out / "streaming.md")
        img_dir = doc.parent / "img" / ("streaming" if args.scale == "full" else "streaming-" + args.scale)
        figures = plot_curves(runs, speeds, rates, img_dir)
        rel = {k: os.path.relpath(v, doc.parent) for k, v in figures.items()}
        metas = {stream_name(v, f): out / "streams" / stream_name(v, f) / "stream.json" for v, f in points}
        frames = {k: json.loads(p.read_text())["totals"]["frames"] for k, p in metas.items() if p.exists()}
        note = (f"Written by `tools/reproduce_stream.py --scale {args.scale}` ({len(houses)} house(s) x "
                f"{sc.episodes} episode(s), episodes cut at {sc.duration:g} s; frames per stream: "
                + ", ".join(f"{k} {n}" for k, n in frames.items()) + f"; {_logged(out / 'commands.log')}; "
                "latencies are this machine's under its load at the time, see the machine line)."
                + "".join(" " + n.strip() for n in args.note))
        write_report(doc, results_section(runs, speeds, rates, rel, note))
        print(f"wrote {doc}")
    print(f"total time {(time.perf_counter() - t0) / 60:.1f} min ({args.scale} scale, steps {','.join(steps)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
