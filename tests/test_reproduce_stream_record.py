"""The streaming run's record and the results block written from it (issue 48, item 5): the episode bootstrap of the
sparse - dense sAP gap (known answers on fixture episodes, and on a real stream the same gap the score step reports),
the record written and read back (kept files, machine record, ownership, symlinks refused), the block generated from a
fixture record by ``--from-record`` (the 288 x 144 outcome, what sAP cannot see, the intervals), and the block that
says there is no record yet."""

from __future__ import annotations

import functools
import json
import os

import numpy as np
import pytest
from helpers_detector import stream_summary

from detector.eval.bootstrap import GapEstimate, bootstrap_gap
from reproduction.stream.cli import main
from reproduction.stream.gaps import StreamGap, episode_groups, gap_path, read_gap, stream_gap, write_gap
from reproduction.stream.record import (
    COMMAND,
    MACHINE_JSON,
    RECORD_JSON,
    RecordPlan,
    StreamRecordError,
    read_stream_record,
    restore_stream_record,
    save_stream_record,
)
from reproduction.stream.report import BEGIN, END, SAP_BLIND_SPOT, no_record_section, outcome_lines, results_section
from reproduction.stream.results import HOUSE_CHECK_JSON, StreamSummary
from reproduction.stream.sweep import HEADLINE, SCALES, Setting, eval_dir, stream_dir


def _mean_ap(gt, dt) -> float:
    """A toy AP: the mean of the per-frame values (frames are numbers here), so resampled gaps are known exactly."""
    return float(np.mean(dt))


def test_the_episode_bootstrap_draws_whole_episodes_with_a_known_interval():
    """Two equal episodes, the gap 0 on one and 2 on the other: the whole-stream gap is 1 and each resample's gap is
    0, 1 or 2 (both episodes the first, one of each, both the second), so the 95 % interval is [0, 2]."""
    gt = [None] * 8
    dense = [0.0] * 8
    sparse = [0.0] * 4 + [2.0] * 4
    g = bootstrap_gap(gt, [dense], [sparse], _mean_ap, resamples=400, groups=episode_groups([4, 4]))
    assert g.mean == 1.0 and g.ci95 == (0.0, 2.0) and g.groups == 2 and g.frames == 8
    # a gap that is the same on every episode has an interval of that gap alone
    same = bootstrap_gap(gt, [dense], [[1.5] * 8], _mean_ap, resamples=50, groups=episode_groups([3, 5]))
    assert same.mean == 1.5 and same.ci95 == (1.5, 1.5)
    # every resample pools whole episodes: 3 + 3, 3 + 5 or 5 + 5 frames, never a frame on its own
    seen = set()

    def size(gt, dt) -> float:
        seen.add(len(dt))
        return 0.0

    bootstrap_gap(gt, [dense], [sparse], size, resamples=60, groups=episode_groups([3, 5]))
    assert seen == {6, 8, 10}
    # the same arguments give the same interval; the JSON reads back
    assert bootstrap_gap(gt, [dense], [sparse], _mean_ap, resamples=30, seed=4, groups=episode_groups([4, 4])) == \
        bootstrap_gap(gt, [dense], [sparse], _mean_ap, resamples=30, seed=4, groups=episode_groups([4, 4]))
    assert GapEstimate.from_json(json.loads(json.dumps(g.to_json()))) == g
    with pytest.raises(ValueError, match="every frame in exactly one group"):
        bootstrap_gap(gt, [dense], [sparse], _mean_ap, groups=[[0, 1, 2], [3, 4]])
    # without groups every frame is its own draw, and the JSON has no "groups" (the accuracy study's files unchanged)
    assert "groups" not in bootstrap_gap(gt, [dense], [sparse], _mean_ap, resamples=5).to_json()


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A work folder whose headline stream is a real stream (3 episodes of one synthetic house at 1 Hz) with two
    'models' saved as result files with latency logs: dense a noisy detector at 1.5 s per frame (it cannot keep up),
    sparse the labels at 0.2 s."""
    from detector.infer import boxes_to_results
    from detector.stream.data import read_stream
    from detector.stream.run import LATENCY_LOG_FORMAT
    from mpchair.geometry import labels_to_boxes
    from mpchair.kitti import write_labels
    from mpchair.stream import StreamRequest, stream
    from mpchair.synth import synthesize_house, write_house

    base = tmp_path_factory.mktemp("stream-work")
    house = synthesize_house(7, levels=1)
    write_house(base / "houses", house)
    out = base / "out"
    sdir = stream_dir(out, *HEADLINE)
    stream(StreamRequest(root=base / "houses", houses=(house.id,), episodes=3, out=sdir, rate=1.0, duration=6.0,
                         look_around=False, min_geodesic=3.0, seed=2, progress=False))
    st = read_stream(sdir)
    setting = Setting("288x144", 2)
    for m, latency_us, noise in (("dense", 1_500_000, 0.15), ("sparse", 200_000, 0.0)):
        ev = eval_dir(out, *HEADLINE, setting, m)
        log = {"format": LATENCY_LOG_FORMAT, "machine": {"cpu": "Test CPU"}, "repeats": 1, "sequences": {}}
        for seq in st.sequences:
            log["sequences"][seq.name] = {}
            for i in range(len(seq)):
                rng = np.random.default_rng([int(seq.name), i])
                objs, calib = seq.labels(i).objects(), seq.calib(i)
                boxes = labels_to_boxes(objs, calib) if len(objs) else np.zeros((0, 7))
                boxes[:, :2] += rng.normal(0.0, noise, (len(boxes), 2))
                write_labels(ev / "outputs" / seq.name / f"{i:06d}.txt",
                             boxes_to_results(boxes, rng.random(len(boxes)) if noise else np.ones(len(boxes)),
                                              np.full(len(boxes), "Chair"), calib, st.meta.image_size))
                log["sequences"][seq.name][seq.frame_id(i)] = latency_us
        (ev / "latency.json").write_text(json.dumps(log))
    return out, setting, st


def test_the_gap_on_the_whole_stream_is_the_score_steps_sap_difference(work):
    """stream_gap rebuilds the scored frames exactly as ``detector stream-eval --results --latency`` scores them: the
    whole-stream gap is sAP(sparse) - sAP(dense) of those summaries; its interval is over the 3 episodes."""
    from detector.stream.run import Source, prepare, read_latency_log, score

    out, setting, st = work
    gap = stream_gap(out, setting, resamples=20)
    assert gap.episodes == len(st.sequences) == 3 and gap.frames == st.frames and gap.resamples == 20
    for mode in ("raw", "ego"):
        sap = {}
        for m in ("dense", "sparse"):
            ev = eval_dir(out, *HEADLINE, setting, m)
            prep = prepare(st, Source("results", results=str(ev / "outputs")),
                           latency_log=read_latency_log(ev / "latency.json"))
            sap[m] = score(prep, mode)["sAP"]["Chair"]["3d"]["R40"]
        g = gap.gaps[mode]
        assert g.mean == pytest.approx(sap["sparse"] - sap["dense"], abs=1e-9)
        assert g.ci95[0] <= g.ci95[1] and g.groups == 3
    path = write_gap(out, setting, gap)
    assert path == gap_path(out, setting) and read_gap(path) == gap
    assert read_gap(out / "nothing.json") is None


#: The fixture's stream-eval summaries: a tighter latency spread, one frame stale, a two-CPU machine.
_summary = functools.partial(stream_summary, p95_over_median=1.1, staleness_ms=(100.0, 100.0),
                             staleness_frames=(1.0, 1.0), logical_cpus=2)


#: sAP 3D of the fixture work folder (model, setting name, mode): at 768 x 512 dense cannot keep up (300 ms) and
#: sparse leads; at 288 x 144 both keep up and dense leads on both; sparse scores the same raw sAP under 1 and 2
#: threads at 768 x 512 (both below the 100 ms period).
FIXTURE = {("dense", "768x512-t2"): (3.0, 44.0, 300.0, 0.39, 52.0),
           ("sparse", "768x512-t2"): (18.3, 44.6, 23.0, 1.0, 46.5),
           ("dense", "768x512-t1"): (0.2, 36.0, 600.0, 0.2, None),
           ("sparse", "768x512-t1"): (18.3, 44.6, 36.0, 1.0, None),
           ("dense", "288x144-t2"): (22.6, 50.6, 32.0, 1.0, 52.7),
           ("sparse", "288x144-t2"): (18.4, 44.5, 11.0, 1.0, 46.6),
           ("dense", "288x144-t1"): (22.6, 50.6, 58.0, 1.0, None),
           ("sparse", "288x144-t1"): (18.4, 44.5, 17.0, 1.0, None)}


def _fixture_work(out):
    """A work folder as a full run leaves it (minus the saved outputs): summaries, latency logs, gaps, stream.json,
    the held-out check, commands.log."""
    for (m, sname), (raw, ego, lat, processed, offline) in FIXTURE.items():
        grid, t = sname.split("-t")
        ev = eval_dir(out, *HEADLINE, Setting(grid, int(t)), m)
        ev.mkdir(parents=True, exist_ok=True)
        (ev / "measure.json").write_text(json.dumps(_summary(ego, offline, lat, processed)))
        for mode, ap in (("raw", raw), ("ego", ego)):
            (ev / f"{mode}.json").write_text(json.dumps(_summary(ap, offline, lat, processed)))
        (ev / "latency.json").write_text(json.dumps({"format": "mpchair-stream-latency/1", "sequences": {}}))
        (ev / "outputs" / "00").mkdir(parents=True, exist_ok=True)
        (ev / "outputs" / "00" / "000000.txt").write_text("")  # per-frame detections: not kept
    gap = {mode: GapEstimate(mean=d, ci95=(d - 2.5, d + 1.5), pair_gaps=(d,), seeds=(1, 1), resamples=200,
                             frames=1210, groups=10) for mode, d in (("raw", -4.2), ("ego", -6.1))}
    write_gap(out, Setting("288x144", 2), StreamGap(gap, "3d", 200, 10, 1210))
    sdir = stream_dir(out, *HEADLINE)
    sdir.mkdir(parents=True)
    (sdir / "stream.json").write_text(json.dumps({"totals": {"frames": 1210}, "houses": {"H1": {}, "H2": {}}}))
    (sdir / "sequences" / "00").mkdir(parents=True)
    (sdir / "sequences" / "00" / "times.txt").write_text("0.000000\n")  # the stream's frames: not kept
    (out / HOUSE_CHECK_JSON).write_text(json.dumps({"streamed": ["H1", "H2"], "trained": ["A", "B"], "overlap": [],
                                                    "dataset": "out/reproduce-full/dataset"}))
    (out / "commands.log").write_text(f"     60.0 s  {os.getcwd()}/.venv/bin/mpchair synth\n")
    return out


def _plan(scale: str = "full") -> RecordPlan:
    return RecordPlan(scale=scale, sizes=SCALES[scale], grids=("768x512", "288x144"), threads=(2, 1),
                      speeds=(0.5,), rates=(10.0,), heldout_seed=1000,
                      checkpoints={"dense": "out/reproduce-full/runs/dense/last.pt",
                                   "sparse": "out/reproduce-full/runs/sparse/last.pt"}, notes=("A note.",))


MACHINE = {"cpu": "Test CPU", "torch": "2.x", "widest_vector_isa": "avx512f", "date_utc": "2026-12-07 14:00"}


def test_a_record_is_written_and_read_back(tmp_path):
    """The record keeps the summaries, latency logs, gaps, stream.json, the held-out check and commands.log (paths
    inside the checkout made relative), never the per-frame outputs or the stream's frames; machine.json names the
    CPU, its ISA flags, threads, torch and the date; the folder is the record step's own."""
    out = _fixture_work(tmp_path / "work")
    dest = tmp_path / "results-data" / "stream"
    assert save_stream_record(out, dest, _plan()) == []
    plan, files, machine = read_stream_record(dest)
    assert plan == _plan()
    assert "commands.log" in files and HOUSE_CHECK_JSON in files and "streams/v0.5-f10/stream.json" in files
    assert "eval/v0.5-f10/288x144-t2/gap.json" in files and "eval/v0.5-f10/768x512-t1/sparse/latency.json" in files
    assert not [f for f in files if "outputs" in f or "sequences" in f]
    assert len([f for f in files if f.endswith(("raw.json", "ego.json", "measure.json"))]) == 8 * 3
    for key in ("cpu", "logical_cpus", "torch_threads", "torch", "isa_flags", "native_precision_flags",
                "widest_vector_isa", "date_utc"):
        assert key in machine, key
    assert os.getcwd() not in (dest / "commands.log").read_text()
    marker = json.loads((dest / ".mpchair-output.json").read_text())
    assert marker["made_by"] == COMMAND and RECORD_JSON in marker["files"] and MACHINE_JSON in marker["files"]
    # written again: replaced whole; a file someone added makes it refuse, and the file stays
    assert save_stream_record(out, dest, _plan(), machine=MACHINE) == []
    assert json.loads((dest / MACHINE_JSON).read_text()) == MACHINE
    (dest / "mine.txt").write_text("keep me")
    with pytest.raises(StreamRecordError, match="mine.txt"):
        save_stream_record(out, dest, _plan())
    assert (dest / "mine.txt").read_text() == "keep me"
    # restored into an empty work folder: the same files; a symlink in the record is refused
    restored = restore_stream_record(dest, tmp_path / "again")
    assert sorted(restored) == sorted(files)
    (dest / "mine.txt").unlink()
    gap = dest / "eval" / "v0.5-f10" / "288x144-t2" / "gap.json"
    gap.unlink()
    gap.symlink_to(tmp_path / "elsewhere.json")
    with pytest.raises(StreamRecordError, match="symbolic link"):
        restore_stream_record(dest, tmp_path / "third")


def test_the_block_is_generated_from_the_record_alone(tmp_path, capsys):
    """``--from-record DIR --steps report``: no models, no streams, no dataset; the block names the record's machine,
    states the 288 x 144 outcome (both keep up, dense ahead on raw and ego), what sAP cannot see (with this run's
    evidence: sparse at two thread budgets, the same raw sAP) and the episode intervals."""
    dest = tmp_path / "record"
    save_stream_record(_fixture_work(tmp_path / "work"), dest, _plan(), machine=MACHINE)
    doc = tmp_path / "streaming.md"
    doc.write_text(f"# Streaming\n\nprose\n\n{BEGIN}\nstale numbers\n{END}\n\nmore prose\n")
    assert main(["--from-record", str(dest), "--steps", "report", "--docs", str(doc)]) == 0
    text = doc.read_text()
    assert text.startswith("# Streaming\n\nprose\n\n") and text.endswith(f"{END}\n\nmore prose\n")
    assert "stale numbers" not in text and "A note." in text and "Test CPU" in text
    assert ("- **288 x 144, 2 threads**: dense keeps up (p95 35.2 ms, 100 % of frames processed); sparse keeps up "
            "(p95 12.1 ms, 100 % of frames processed). Raw sAP 3D dense 22.60 against sparse 18.40 (dense ahead), "
            "ego sAP 3D dense 50.60 against sparse 44.50 (dense ahead).") in text
    assert "- **768 x 512, 2 threads**: dense does not keep up (p95 330.0 ms, 39 % of frames processed)" in text
    assert "latency below one sensor period" in text
    assert ("In this run: sparse at 768 x 512 scores raw sAP 3D 18.30 at 23.0 ms (2 threads), 18.30 at 36.0 ms "
            "(1 thread)") in text
    assert "| 288 x 144, 2 threads | -4.20 [-6.70, -2.70] | -6.10 [-8.60, -4.60] |" in text
    assert "200 resamples of the 10 episodes (1210 frames)" in text
    assert "none of them (by id or by file checksums) is among the 2 houses" in text
    # the same block again from the same record: byte for byte
    assert main(["--from-record", str(dest), "--steps", "report", "--docs", str(doc)]) == 0
    assert doc.read_text() == text
    # only the report can be written from a record
    assert main(["--from-record", str(dest), "--steps", "measure,report", "--docs", str(doc)]) == 2
    assert "give --steps report" in capsys.readouterr().err


def test_without_a_record_the_block_says_so_and_quotes_no_result(tmp_path):
    doc = tmp_path / "streaming.md"
    doc.write_text(f"# Streaming\n\n{BEGIN}\n| sparse | 18.31 |\n{END}\n")
    assert main(["--from-record", str(tmp_path / "no-record"), "--steps", "report", "--docs", str(doc)]) == 0
    text = doc.read_text()
    block = text.split(BEGIN)[1].split(END)[0]
    assert "**No record yet.**" in block and "18.31" not in block and "|" not in block
    assert block.strip() == no_record_section(str(tmp_path / "no-record")).strip()
    assert SAP_BLIND_SPOT.format(period=100, rate=10) in block


def test_outcome_needs_both_models_scored():
    assert outcome_lines({}, [Setting("288x144", 2)]) == []
    runs = {(m, *HEADLINE, "288x144-t2", mode): StreamSummary.from_json(_summary(10.0, None, 50.0, 1.0))
            for m in ("dense", "sparse") for mode in ("raw", "ego")}
    text = "\n".join(outcome_lines(runs, [Setting("288x144", 2)]))
    assert "Raw sAP 3D dense 10.00 against sparse 10.00 (neither (level) ahead)" in text
    assert "not computed in this run" in results_section(runs, [Setting("288x144", 2)], [0.5], [10.0], {}, "note")
