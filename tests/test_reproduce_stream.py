"""reproduction.stream (``tools/reproduce_stream.py``): the commands it runs (dry run: held-out houses, every
setting on the headline stream, the headline setting on the sweep), the crossover speed, the highest rate a model keeps
up with, the check that the streamed houses are not the training data's, and the report it writes between the markers
of docs/streaming.md without touching the rest."""

from __future__ import annotations

import json

import pytest
from helpers_detector import stream_summary as _summary
from helpers_detector import write_manifest

from mpchair.core.errors import InputError
from reproduction.stream.cli import main
from reproduction.stream.report import (
    BEGIN,
    END,
    crossover,
    houses_text,
    keeps_up_hz,
    plot_curves,
    results_section,
    write_section,
)
from reproduction.stream.results import StreamSummary, check_houses, read_runs, stream_frames
from reproduction.stream.sweep import HEADLINE, Setting, eval_dir, settings, stream_dir, sweep_points

T2, T1 = Setting("768x512", 2), Setting("768x512", 1)


def test_crossover():
    xs = [0.25, 0.5, 1.0]
    assert crossover(xs, [50, 40, 20], [45, 42, 30]) == pytest.approx(0.25 + 0.25 * 5 / 7)
    assert crossover(xs, [50, 40, 20], [60, 50, 30]) == 0.25
    assert crossover(xs, [50, 40, 20], [40, 30, 10]) is None


def test_keeps_up_is_the_rate_at_which_95_percent_of_frames_finish_within_a_period():
    assert keeps_up_hz(250.0) == 4.0 and keeps_up_hz(40.0) == 25.0
    assert keeps_up_hz(None) is None


def _runs(speeds: list[float], rates: list[float]) -> dict:
    """Scored runs of both models: every point under T2, the headline stream under T1 too (slower, no offline AP);
    dense 800 ms (T2) / 1,600 ms (T1), sparse 80 / 120 ms; and the oracle at each of those latencies."""
    runs = {}
    for v, f in sweep_points(speeds, rates):
        for m, base in (("dense", 60.0), ("sparse", 50.0)):
            slow = 40.0 * v if m == "dense" else 10.0 * v  # dense loses more with speed
            for mode, loss in (("raw", 2 * slow), ("ego", slow)):
                off = base + 20 if (v, f) == HEADLINE else None
                summary = _summary(base + 20 - loss, off, 800.0 if m == "dense" else 80.0)
                summary["repeats"] = 3 if (v, f) == HEADLINE else 1
                runs[(m, v, f, T2.name, mode)] = StreamSummary.from_json(summary)
    for m, lat in (("dense", 1600.0), ("sparse", 120.0)):
        for mode in ("raw", "ego"):
            runs[(m, *HEADLINE, T1.name, mode)] = StreamSummary.from_json(_summary(10.0, None, lat, 0.25))
    for s, (dense_lat, sparse_lat) in ((T2, (800.0, 80.0)), (T1, (1600.0, 120.0))):
        for m, lat, raw, ego in (("dense", dense_lat, 1.0, 60.0), ("sparse", sparse_lat, 40.0, 95.0)):
            for mode, ap in (("raw", raw), ("ego", ego)):
                runs[(f"oracle@{m}", *HEADLINE, s.name, mode)] = StreamSummary.from_json(_summary(ap, 100.0, lat))
    return runs


def test_report_section_and_markers(tmp_path):
    speeds, rates = [0.25, 0.5, 1.0], [5.0, 10.0, 20.0]
    runs = _runs(speeds, rates)
    text = results_section(runs, [T2, T1], speeds, rates, {"speed": "img/s.png", "rate": "img/r.png"}, "note")
    assert ("| oracle at sparse's latency | 768 x 512, 2 threads | 100.00 / 101.00 | 40.00 / 41.00 | 95.00 / 96.00 | "
            "80.0 (constant) |") in text
    assert "| dense | 768 x 512, 2 threads | 80.00 / 81.00 | 40.00 / 41.00 | 60.00 / 61.00 | 800.0 / 1000.0 |" in text
    assert "| sparse | 768 x 512, 2 threads | 70.00 / 71.00 | 60.00 / 61.00 | 65.00 / 66.00 | 80.0 / 100.0 |" in text
    # the 1-thread rows take their grid's offline AP (threads do not change the outputs), their own sAP and latency
    assert ("| dense | 768 x 512, 1 thread | 80.00 / 81.00 | 10.00 / 11.00 | 10.00 / 11.00 | 1600.0 / 2000.0 |"
            in text)
    # keeps up: 1000 / p95; busy at 1 Hz: median / 1 s; CPU left: 1 - threads x median / 1 s / logical CPUs
    assert "| sparse | 768 x 512, 2 threads | 80.0 / 100.0 | 10.0 | 8 % | 96 % of 4 |" in text
    assert "| dense | 768 x 512, 1 thread | 1600.0 / 2000.0 | 0.5 | all (slower than 1 Hz) | none |" in text
    assert "| dense | 768 x 512, 2 threads | 800.0 / 1000.0 | 1.0 | 80 % | 60 % of 4 |" in text
    assert "at 1 Hz it keeps the CPU 76 % idle" in text
    # ego: dense 80 - 40 v, sparse 70 - 10 v: equal at v = 1/3 m/s; raw: sparse is ahead from 0.25 m/s on
    assert "- ego: sparse overtakes dense at about 0.33 m/s" in text
    assert "- raw: sparse is ahead of dense already at 0.25 m/s" in text
    assert "sAP 3D R40 against sensor rate (at 0.5 m/s), 768 x 512, 2 threads:" in text
    assert "| 20 | 40.00 | 60.00 | 60.00 | 65.00 | 50 % / 50 % |" in text
    assert "GPU column: not measured" in text and "![sAP against speed](img/s.png)" in text
    assert "median of 3 timed runs per frame on the headline stream, 1 on the sweep's other streams" in text
    doc = tmp_path / "streaming.md"
    doc.write_text(f"# Title\n\nprotocol text\n\n{BEGIN}\nold\n{END}\n\nafter\n")
    write_section(doc, text)
    out = doc.read_text()
    assert out.startswith("# Title\n\nprotocol text\n\n") and out.endswith(f"{END}\n\nafter\n")
    assert "old" not in out and text in out
    fresh = tmp_path / "new.md"  # no markers yet: the block is appended
    fresh.write_text("# Title\n")
    write_section(fresh, text)
    assert fresh.read_text() == f"# Title\n\n{BEGIN}\n{text.rstrip(chr(10))}\n{END}\n"
    broken = tmp_path / "broken.md"  # one marker without the other: an error naming the doc, the doc untouched
    broken.write_text(f"# Title\n{BEGIN}\nold\n")
    with pytest.raises(InputError, match="broken.md: expected one"):
        write_section(broken, text)
    assert broken.read_text() == f"# Title\n{BEGIN}\nold\n"
    paths = plot_curves(runs, T2, speeds, rates, tmp_path / "img")
    assert all(p.stat().st_size > 1000 for p in paths.values())


def test_a_sweep_of_one_point_is_reported_as_not_run(tmp_path):
    """--speeds 0.5 --rates 10 (the headline stream only): no sweep table or curve, a line saying so instead."""
    runs = _runs([0.5], [10.0])
    text = results_section(runs, [T2, T1], [0.5], [10.0], {}, "note")
    assert "sAP against robot speed (at 10 Hz): not measured in this run (`--speeds` gave one point)." in text
    assert "sAP against sensor rate (at 0.5 m/s): not measured in this run (`--rates` gave one point)." in text
    assert "| speed (m/s) |" not in text and "| rate (Hz) |" not in text
    assert "| sparse | 768 x 512, 2 threads | 70.00 / 71.00 |" in text
    assert plot_curves(runs, T2, [0.5], [10.0], tmp_path / "img") == {} and not (tmp_path / "img").exists()


def test_a_setting_not_measured_is_named():
    text = results_section({}, [T2], [0.5], [10.0], {}, "note")
    assert "| dense | 768 x 512, 2 threads | not measured |" in text and "keeps up to" not in text


def _lines(capsys) -> list[str]:
    return [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("$ ")]


def test_dry_run_lists_the_commands(tmp_path, capsys):
    """Held-out houses are synthesized with their own seed; every setting (2 grids x 2 thread budgets) is measured on
    the headline stream with one offline pass per grid and model; the other 4 streams under 768 x 512, 2 threads."""
    assert main(["--scale", "small", "--dry-run", "--out", str(tmp_path)]) == 0
    lines = _lines(capsys)
    (synth,) = [ln for ln in lines if " synth " in ln]
    assert synth.endswith(f"synth --out {tmp_path.resolve()}/houses --houses 1 --seed 1000")
    streams = [ln for ln in lines if " stream " in ln]
    assert len(streams) == 5 and all(f"--root {tmp_path.resolve()}/houses " in ln and "--duration 8" in ln
                                     for ln in streams)
    measure = [ln for ln in lines if "--latency-log" in ln]
    assert len(measure) == 4 * 2 + 4 * 2 and all("MALLOC_MMAP_MAX_=0" in ln for ln in measure)
    headline = [ln for ln in measure if "/v0.5-f10 " in ln]
    assert len(headline) == 8
    for grid, config in (("768x512", "mpchair_{m}.yaml"), ("288x144", "mpchair_{m}_cpu.yaml")):
        for t in (1, 2):
            runs = [ln for ln in headline if f"/{grid}-t{t}/" in ln]
            assert len(runs) == 2 and all(f"--threads {t} " in ln for ln in runs)
            assert all(config.format(m=m) in ln for m, ln in zip(("dense", "sparse"), runs))
            assert all(("--no-offline" in ln) == (t == 1) for ln in runs)  # one offline pass per grid and model
    sweep = [ln for ln in measure if "/v0.5-f10 " not in ln]
    assert all("/768x512-t2/" in ln and "--threads 2 " in ln and "--no-offline" in ln for ln in sweep)
    assert all("--results" in ln and "--latency " in ln for ln in lines if "--mode" in ln and "--oracle" not in ln)
    oracle = [ln for ln in lines if "--oracle" in ln]
    assert len(oracle) == 4 * 2 * 2 and all("v0.5-f10" in ln and "median latency>" in ln for ln in oracle)
    assert sum("--mode raw" in ln for ln in lines) == sum("--mode ego" in ln for ln in lines) == 16 + 8


def test_given_houses_are_streamed_as_given(tmp_path, capsys):
    args = ["--scale", "small", "--dry-run", "--out", str(tmp_path), "--houses", str(tmp_path / "h"), "--house", "H1",
            "--grids", "288x144", "--threads", "1", "--speeds", "0.5", "--rates", "10"]
    assert main(args) == 0
    lines = _lines(capsys)
    assert not [ln for ln in lines if " synth " in ln]
    streams = [ln for ln in lines if " stream " in ln]
    assert len(streams) == 1 and "--house H1" in streams[0] and f"--root {tmp_path / 'h'} " in streams[0]
    measure = [ln for ln in lines if "--latency-log" in ln]
    assert len(measure) == 2 and all("/288x144-t1/" in ln and "--no-offline" not in ln for ln in measure)


def test_repeats_flags_override_the_scale(tmp_path, capsys):
    """--repeats sets the timed runs per processed frame on the headline stream (the full scale: 3, the protocol's),
    --sweep-repeats on the others (full: 1); below 1 is refused, as are unknown grids and thread budgets."""
    args = ["--dry-run", "--out", str(tmp_path)]
    assert main(args) == 0
    measure = [ln for ln in _lines(capsys) if "--latency-log" in ln]
    assert all(("--repeats 3 " if "/v0.5-f10 " in ln else "--repeats 1 ") in ln for ln in measure)
    assert main([*args, "--repeats", "1", "--sweep-repeats", "2"]) == 0
    measure = [ln for ln in _lines(capsys) if "--latency-log" in ln]
    assert all(("--repeats 1 " if "/v0.5-f10 " in ln else "--repeats 2 ") in ln for ln in measure)
    for bad, said in ((["--repeats", "0"], "--repeats must be >= 1"), (["--grids", "100x100"], "--grids takes"),
                      (["--threads", "0"], "--threads must be >= 1"), (["--threads", "two"], "comma-separated")):
        assert main([*args, *bad]) == 2
        assert said in capsys.readouterr().err


def test_runs_are_read_from_the_work_folder_with_the_machine_of_their_measuring_run(tmp_path):
    """A score summary (replayed from saved outputs) names no machine: the report takes its measuring run's; the oracle
    runs are keyed ``oracle@<model>``; a stream without its stream.json has no frame count."""
    points = sweep_points([0.25, 0.5], [10.0])
    scored = {k: v for k, v in _summary(42.0, 50.0).items() if k not in ("machine", "repeats")}
    for m in ("dense", "sparse"):
        ev = eval_dir(tmp_path, *HEADLINE, T2, m)
        ev.mkdir(parents=True)
        (ev / "measure.json").write_text(json.dumps(_summary(40.0, 50.0, 123.0)))
        (ev / "ego.json").write_text(json.dumps(scored))
    oracle = eval_dir(tmp_path, *HEADLINE, T2, "oracle-at-sparse")
    oracle.mkdir(parents=True)
    (oracle / "raw.json").write_text(json.dumps({**scored, "latency_ms": {"median": 80.0, "p95": 80.0}}))
    stream_dir(tmp_path, *HEADLINE).mkdir(parents=True)
    (stream_dir(tmp_path, *HEADLINE) / "stream.json").write_text(json.dumps({"totals": {"frames": 77}}))
    runs = read_runs(tmp_path, points, settings(["768x512"], [2, 1]))
    v0, f0 = HEADLINE
    assert list(runs) == [("dense", v0, f0, T2.name, "ego"), ("sparse", v0, f0, T2.name, "ego"),
                          ("oracle@sparse", v0, f0, T2.name, "raw")]
    ego = runs[("dense", v0, f0, T2.name, "ego")]
    assert ego.machine is not None and ego.machine.cpu == "Test CPU" and ego.machine.logical_cpus == 4
    assert ego.repeats is None
    assert ego.ap() == 42.0 and ego.ap("bev") == 43.0 and ego.ap(offline=True) == 50.0
    assert ego.latency_ms.median == 100.0 and ego.staleness_frames.p95 == 2.0 and ego.frames_processed == 0.5
    assert runs[("oracle@sparse", v0, f0, T2.name, "raw")].machine is None
    assert runs[("oracle@sparse", v0, f0, T2.name, "raw")].latency_ms.median == 80.0
    assert stream_frames(tmp_path, points) == {"v0.5-f10": 77}


def _dataset(root, houses: dict[str, tuple[int, int, str]], train: list[int], val: list[int]):
    """A dataset folder's manifest.json (house id -> frame range and one file's checksum) and its train / val lists."""
    write_manifest(root, {h: (a, b, {f"{h}.ply": s}) for h, (a, b, s) in houses.items()})
    (root / "ImageSets").mkdir()
    for name, ids in (("train", train), ("val", val), ("test", [])):
        (root / "ImageSets" / f"{name}.txt").write_text("".join(f"{i:06d}\n" for i in ids))
    return root


def _stream(root, houses: dict[str, str]):
    root.mkdir(parents=True)
    (root / "stream.json").write_text(json.dumps({"houses": {h: {"files_sha256": {f"{h}.ply": s}}
                                                             for h, s in houses.items()}}))
    return root


def test_the_streamed_houses_are_checked_against_the_training_data(tmp_path):
    """A house the training data used (any train or val frame) is named, by id or by identical files; a house with
    only test frames is held out; without the dataset nothing is claimed."""
    data = _dataset(tmp_path / "dataset", {"A": (0, 9, "a"), "B": (10, 19, "b"), "C": (20, 29, "c")},
                    train=[0, 3, 12], val=[5])  # C: test frames only
    held = check_houses(_stream(tmp_path / "s1", {"X": "x", "C": "c"}), data)
    assert held.streamed == ("X", "C") and held.trained == ("A", "B") and held.overlap == ()
    said = houses_text(held, 1000)
    assert "Houses (2): held-out houses made for these streams (`mpchair synth --seed 1000`): X, C" in said
    assert "none of them (by id or by file checksums) is among the 2 houses" in said
    # same id, or other id with the same files: not held out
    seen = check_houses(_stream(tmp_path / "s2", {"A": "zzz", "Y": "b"}), data)
    assert seen.overlap == ("A", "Y")
    assert "**Not held out:** A, Y also gave the models' train / val frames" in houses_text(seen, None)
    unchecked = check_houses(tmp_path / "s1", tmp_path / "no-dataset")
    assert unchecked.dataset is None and "not checked" in houses_text(unchecked, 1000)
    assert check_houses(tmp_path / "no-stream", data) is None
    assert houses_text(None, 1000) == "Houses: not streamed yet."
