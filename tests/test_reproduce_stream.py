"""tools/reproduce_stream.py: the commands it runs (dry run), the crossover speed, and the report it writes between
the markers of docs/streaming.md without touching the rest."""

from __future__ import annotations

import pytest
from helpers_tools import load_tool


@pytest.fixture(scope="module")
def tool():
    return load_tool("reproduce_stream")


def _summary(sap: float, offline: float | None = None, latency: float = 100.0) -> dict:
    ap = lambda x: {"Chair": {"3d": {"R40": x, "R11": x}, "bev": {"R40": x + 1, "R11": x + 1}}}  # noqa: E731
    return {"sAP": ap(sap), "offline_AP": None if offline is None else ap(offline),
            "latency_ms": {"median": latency, "p95": latency * 1.2}, "staleness_ms": {"mean": 150.0, "p95": 200.0},
            "staleness_frames": {"mean": 1.5, "p95": 2.0}, "frames_processed": 0.5, "repeats": 3,
            "machine": {"cpu": "Test CPU", "torch_threads": 2, "torch": "2.x", "allocator": "reuse"}}


def test_crossover(tool):
    xs = [0.25, 0.5, 1.0]
    assert tool.crossover(xs, [50, 40, 20], [45, 42, 30]) == pytest.approx(0.25 + 0.25 * 5 / 7)
    assert tool.crossover(xs, [50, 40, 20], [60, 50, 30]) == 0.25
    assert tool.crossover(xs, [50, 40, 20], [40, 30, 10]) is None


def test_report_section_and_markers(tool, tmp_path):
    speeds, rates = [0.25, 0.5, 1.0], [5.0, 10.0, 20.0]
    runs = {}
    for v, f in tool.sweep_points(speeds, rates):
        for m, base in (("dense", 60.0), ("sparse", 50.0)):
            slow = 40.0 * v if m == "dense" else 10.0 * v  # dense loses more with speed
            for mode, loss in (("raw", 2 * slow), ("ego", slow)):
                off = base + 20 if (v, f) == tool.HEADLINE else None
                runs[(m, v, f, mode)] = _summary(base + 20 - loss, off, 800.0 if m == "dense" else 80.0)
    for m, lat, raw, ego in (("dense", 800.0, 1.0, 60.0), ("sparse", 80.0, 40.0, 95.0)):
        for mode, ap in (("raw", raw), ("ego", ego)):
            runs[(f"oracle@{m}", *tool.HEADLINE, mode)] = _summary(ap, 100.0, lat)
    text = tool.results_section(runs, speeds, rates, {"speed": "img/s.png", "rate": "img/r.png"}, "note")
    assert "| oracle at sparse's latency | 100.00 / 101.00 | 40.00 / 41.00 | 95.00 / 96.00 | 80.0 (constant) |" in text
    assert "| dense | 80.00 / 81.00 | 40.00 / 41.00 | 60.00 / 61.00 | 800.0 / 960.0 |" in text
    assert "| sparse | 70.00 / 71.00 | 60.00 / 61.00 | 65.00 / 66.00 | 80.0 / 96.0 |" in text
    # ego: dense 80 - 40 v, sparse 70 - 10 v: equal at v = 1/3 m/s; raw: sparse is ahead from 0.25 m/s on
    assert "- ego: sparse overtakes dense at about 0.33 m/s" in text
    assert "- raw: sparse is ahead of dense already at 0.25 m/s" in text
    assert "GPU column: not measured" in text and "![sAP against speed](img/s.png)" in text
    doc = tmp_path / "streaming.md"
    doc.write_text(f"# Title\n\nprotocol text\n\n{tool.BEGIN}\nold\n{tool.END}\n\nafter\n")
    tool.write_report(doc, text)
    out = doc.read_text()
    assert out.startswith("# Title\n\nprotocol text\n\n") and out.endswith(f"{tool.END}\n\nafter\n")
    assert "old" not in out and text in out
    paths = tool.plot_curves(runs, speeds, rates, tmp_path / "img")
    assert all(p.stat().st_size > 1000 for p in paths.values())


def test_dry_run_lists_the_commands(tool, tmp_path, capsys):
    assert tool.main(["--scale", "small", "--dry-run", "--out", str(tmp_path), "--house", "H1",
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


def test_repeats_flag_overrides_the_scale(tool, tmp_path, capsys):
    """--repeats sets the measured runs per processed frame of every measuring command; below 1 is refused."""
    args = ["--dry-run", "--out", str(tmp_path), "--house", "H1", "--houses", str(tmp_path / "houses")]
    assert tool.main(args) == 0
    measure = [ln for ln in capsys.readouterr().out.splitlines() if "--latency-log" in ln]
    assert len(measure) == 10 and all("--repeats 2 " in ln for ln in measure)  # the full scale's
    assert tool.main([*args, "--repeats", "1"]) == 0
    measure = [ln for ln in capsys.readouterr().out.splitlines() if "--latency-log" in ln]
    assert len(measure) == 10 and all("--repeats 1 " in ln for ln in measure)
    assert tool.main([*args, "--repeats", "0"]) == 2
    assert "--repeats must be >= 1" in capsys.readouterr().err
