"""detector.reproduce.stream (``tools/reproduce_stream.py``): the commands it runs (dry run), the crossover speed, and
the report it writes between the markers of docs/streaming.md without touching the rest."""

from __future__ import annotations

import pytest

from detector.reproduce.stream.cli import main
from detector.reproduce.stream.report import BEGIN, END, crossover, plot_curves, results_section, write_section
from detector.reproduce.stream.results import StreamSummary, read_runs, stream_frames
from detector.reproduce.stream.sweep import HEADLINE, eval_dir, stream_dir, sweep_points


def _summary(sap: float, offline: float | None = None, latency: float = 100.0) -> dict:
    """A stream-eval ``--json`` summary as the measuring run writes it (AP percent, times ms)."""
    ap = lambda x: {"Chair": {"3d": {"R40": x, "R11": x}, "bev": {"R40": x + 1, "R11": x + 1}}}  # noqa: E731
    return {"sAP": ap(sap), "offline_AP": None if offline is None else ap(offline),
            "latency_ms": {"median": latency, "p95": latency * 1.2}, "staleness_ms": {"mean": 150.0, "p95": 200.0},
            "staleness_frames": {"mean": 1.5, "p95": 2.0}, "frames_processed": 0.5, "repeats": 3,
            "machine": {"cpu": "Test CPU", "torch_threads": 2, "torch": "2.x", "allocator": "reuse"}}


def test_crossover():
    xs = [0.25, 0.5, 1.0]
    assert crossover(xs, [50, 40, 20], [45, 42, 30]) == pytest.approx(0.25 + 0.25 * 5 / 7)
    assert crossover(xs, [50, 40, 20], [60, 50, 30]) == 0.25
    assert crossover(xs, [50, 40, 20], [40, 30, 10]) is None


def test_report_section_and_markers(tmp_path):
    speeds, rates = [0.25, 0.5, 1.0], [5.0, 10.0, 20.0]
    runs = {}
    for v, f in sweep_points(speeds, rates):
        for m, base in (("dense", 60.0), ("sparse", 50.0)):
            slow = 40.0 * v if m == "dense" else 10.0 * v  # dense loses more with speed
            for mode, loss in (("raw", 2 * slow), ("ego", slow)):
                off = base + 20 if (v, f) == HEADLINE else None
                summary = _summary(base + 20 - loss, off, 800.0 if m == "dense" else 80.0)
                runs[(m, v, f, mode)] = StreamSummary.from_json(summary)
    for m, lat, raw, ego in (("dense", 800.0, 1.0, 60.0), ("sparse", 80.0, 40.0, 95.0)):
        for mode, ap in (("raw", raw), ("ego", ego)):
            runs[(f"oracle@{m}", *HEADLINE, mode)] = StreamSummary.from_json(_summary(ap, 100.0, lat))
    text = results_section(runs, speeds, rates, {"speed": "img/s.png", "rate": "img/r.png"}, "note")
    assert "| oracle at sparse's latency | 100.00 / 101.00 | 40.00 / 41.00 | 95.00 / 96.00 | 80.0 (constant) |" in text
    assert "| dense | 80.00 / 81.00 | 40.00 / 41.00 | 60.00 / 61.00 | 800.0 / 960.0 |" in text
    assert "| sparse | 70.00 / 71.00 | 60.00 / 61.00 | 65.00 / 66.00 | 80.0 / 96.0 |" in text
    # ego: dense 80 - 40 v, sparse 70 - 10 v: equal at v = 1/3 m/s; raw: sparse is ahead from 0.25 m/s on
    assert "- ego: sparse overtakes dense at about 0.33 m/s" in text
    assert "- raw: sparse is ahead of dense already at 0.25 m/s" in text
    assert "GPU column: not measured" in text and "![sAP against speed](img/s.png)" in text
    doc = tmp_path / "streaming.md"
    doc.write_text(f"# Title\n\nprotocol text\n\n{BEGIN}\nold\n{END}\n\nafter\n")
    write_section(doc, text)
    out = doc.read_text()
    assert out.startswith("# Title\n\nprotocol text\n\n") and out.endswith(f"{END}\n\nafter\n")
    assert "old" not in out and text in out
    paths = plot_curves(runs, speeds, rates, tmp_path / "img")
    assert all(p.stat().st_size > 1000 for p in paths.values())


def test_dry_run_lists_the_commands(tmp_path, capsys):
    assert main(["--scale", "small", "--dry-run", "--out", str(tmp_path), "--house", "H1",
                      "--houses", str(tmp_path / "houses")]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ")]
    streams = [ln for ln in lines if " stream " in ln]
    assert len(streams) == 5 and all("--house H1" in ln and "--duration 8" in ln for ln in streams)
    measure = [ln for ln in lines if "--latency-log" in ln]
    assert len(measure) == 10 and all("MALLOC_MMAP_MAX_=0" in ln and "--threads 2" in ln for ln in measure)
    assert all("--save-results" in ln for ln in measure)
    assert sum("--no-offline" not in ln for ln in measure) == 2  # the offline pass only on the headline stream
    assert all("--results" in ln and "--latency " in ln for ln in lines if "--mode" in ln and "--oracle" not in ln)
    oracle = [ln for ln in lines if "--oracle" in ln]
    assert len(oracle) == 4 and all("v0.5-f10" in ln and "median latency>" in ln for ln in oracle)
    assert sum("--mode raw" in ln for ln in lines) == sum("--mode ego" in ln for ln in lines) == 12


def test_repeats_flag_overrides_the_scale(tmp_path, capsys):
    """--repeats sets the measured runs per processed frame of every measuring command; below 1 is refused."""
    args = ["--dry-run", "--out", str(tmp_path), "--house", "H1", "--houses", str(tmp_path / "houses")]
    assert main(args) == 0
    measure = [ln for ln in capsys.readouterr().out.splitlines() if "--latency-log" in ln]
    assert len(measure) == 10 and all("--repeats 2 " in ln for ln in measure)  # the full scale's
    assert main([*args, "--repeats", "1"]) == 0
    measure = [ln for ln in capsys.readouterr().out.splitlines() if "--latency-log" in ln]
    assert len(measure) == 10 and all("--repeats 1 " in ln for ln in measure)
    assert main([*args, "--repeats", "0"]) == 2
    assert "--repeats must be >= 1" in capsys.readouterr().err


def test_runs_are_read_from_the_work_folder_with_the_machine_of_their_measuring_run(tmp_path):
    """A score summary (replayed from saved outputs) names no machine: the report takes its measuring run's; the oracle
    runs are keyed ``oracle@<model>``; a stream without its stream.json has no frame count."""
    import json

    points = sweep_points([0.25, 0.5], [10.0])
    scored = {k: v for k, v in _summary(42.0, 50.0).items() if k not in ("machine", "repeats")}
    for m in ("dense", "sparse"):
        ev = eval_dir(tmp_path, *HEADLINE, m)
        ev.mkdir(parents=True)
        (ev / "measure.json").write_text(json.dumps(_summary(40.0, 50.0, 123.0)))
        (ev / "ego.json").write_text(json.dumps(scored))
    oracle = eval_dir(tmp_path, *HEADLINE, "oracle-at-sparse")
    oracle.mkdir(parents=True)
    (oracle / "raw.json").write_text(json.dumps({**scored, "latency_ms": {"median": 80.0, "p95": 80.0}}))
    stream_dir(tmp_path, *HEADLINE).mkdir(parents=True)
    (stream_dir(tmp_path, *HEADLINE) / "stream.json").write_text(json.dumps({"totals": {"frames": 77}}))
    runs = read_runs(tmp_path, points)
    v0, f0 = HEADLINE
    assert list(runs) == [("dense", v0, f0, "ego"), ("sparse", v0, f0, "ego"), ("oracle@sparse", v0, f0, "raw")]
    ego = runs[("dense", v0, f0, "ego")]
    assert ego.machine is not None and ego.machine.cpu == "Test CPU" and ego.repeats is None
    assert ego.ap() == 42.0 and ego.ap("bev") == 43.0 and ego.ap(offline=True) == 50.0
    assert ego.latency_ms.median == 100.0 and ego.staleness_frames.p95 == 2.0 and ego.frames_processed == 0.5
    assert runs[("oracle@sparse", v0, f0, "raw")].machine is None
    assert runs[("oracle@sparse", v0, f0, "raw")].latency_ms.median == 80.0
    assert stream_frames(tmp_path, points) == {"v0.5-f10": 77}
