"""``detector stream-eval``: the protocol's invariants on real streams (``mpchair stream`` on a synthetic house) —
zero latency scores exactly the offline outputs, a perfect detector scores 100 (with fewer than 41 chairs KITTI's
ceiling, below 100), a still robot loses only the queries
before the first output, staleness follows the schedule exactly, ego compensation never hurts a perfect detector, the
JSON is byte-identical across runs — plus a model with measured latency, and the clear errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers_detector import write_test_config

from detector.commands.stream_eval import format_summary
from detector.eval import evaluate
from detector.infer import boxes_to_results
from detector.stream import Source, prepare, read_stream, score
from detector.stream.run import query_labels, query_sources
from detector.stream.score import ap_ceiling, evaluate_overall
from mpchair.core.errors import InputError
from mpchair.geometry import labels_to_boxes
from mpchair.kitti import Labels, write_labels
from mpchair.stream import StreamRequest, stream
from mpchair.synth import synthesize_house, write_house
from mpchair.synth.realism import CLEAN

ROOT = Path(__file__).resolve().parents[1]
PERIOD_MS = 500.0  # the streams below run at 2 Hz


@pytest.fixture(scope="module")
def streams(tmp_path_factory):
    """A moving stream (2 episodes) and a still one (the robot stands for 4 s) of one synthetic house, at 2 Hz."""
    base = tmp_path_factory.mktemp("streams")
    house = synthesize_house(7, levels=1, realism=CLEAN)  # the exact ground-truth counts below are this house's
    write_house(base / "houses", house)
    common = dict(root=base / "houses", houses=(house.id,), rate=2.0, progress=False)
    stream(StreamRequest(episodes=2, out=base / "moving", seed=1, **common))
    # seed 3: a start that faces two chairs (a still robot sees what its first heading shows)
    stream(StreamRequest(episodes=1, out=base / "still", speed=0.0, turn_rate=0.0, duration=4.0, seed=3, **common))
    return read_stream(base / "moving"), read_stream(base / "still")


def _write_noisy_results(st, out: Path, same_noise_every_frame: bool = False) -> Path:
    """A fallible detector as result files: each labelled chair found with probability 0.8, moved by a few cm, with
    a random score, plus one false positive per frame."""
    for seq in st.sequences:
        for i in range(len(seq)):
            rng = np.random.default_rng(0 if same_noise_every_frame else [len(seq), i, int(seq.name)])
            labels, calib = seq.labels(i), seq.calib(i)
            objs = labels.objects()
            boxes = labels_to_boxes(objs, calib) if len(objs) else np.zeros((0, 7))
            boxes = boxes[rng.random(len(boxes)) < 0.8]
            boxes[:, :2] += rng.normal(0.0, 0.08, (len(boxes), 2))
            fp = np.array([[rng.uniform(1, 6), rng.uniform(-1, 1), -0.5, 0.9, 0.6, 0.9, 0.0]])
            boxes = np.vstack([boxes, fp])
            scores = rng.random(len(boxes))
            write_labels(out / seq.name / f"{i:06d}.txt",
                         boxes_to_results(boxes, scores, np.full(len(boxes), "Chair"), calib, st.meta.image_size))
    return out


def _ap_values(ap: dict) -> list[float]:
    return [ap["Chair"][m][v] for m in ("3d", "bev") for v in ("R40", "R11")]


def test_zero_latency_scores_exactly_the_offline_outputs(streams, tmp_path):
    moving, _ = streams
    results = _write_noisy_results(moving, tmp_path / "res")
    prep = prepare(moving, Source("results", results=str(results)), latency_ms=0.0)
    for mode in ("ego", "raw"):
        s = score(prep, mode)
        assert s["sAP"] == s["offline_AP"]
        assert all(0 < v < 100 for v in _ap_values(s["sAP"]))  # a detector with misses and false positives
        assert s["staleness_frames"] == {"mean": 0.0, "p95": 0.0} and s["frames_processed"] == 1.0
        assert s["queries_without_output"] == 0 and s["in_time"] == 1.0
    # one frame of latency costs AP on a moving robot
    late = score(prepare(moving, Source("results", results=str(results)), latency_ms=PERIOD_MS), "raw")
    assert late["sAP"]["Chair"]["3d"]["R40"] < late["offline_AP"]["Chair"]["3d"]["R40"]


def test_oracle_with_zero_latency_scores_100(streams):
    moving, _ = streams
    prep = prepare(moving, Source("oracle"), latency_ms=0.0)
    for mode in ("ego", "raw"):
        s = score(prep, mode)
        assert s["num_gt"]["Chair"] >= 41  # enough chairs for AP to reach 100 (KITTI's 41 recall points)
        assert _ap_values(s["sAP"]) == [100.0] * 4 and _ap_values(s["offline_AP"]) == [100.0] * 4


def _one_chair(score: float | None) -> Labels:
    """One upright chair 3 m in front of the camera (rectified camera frame), as a label (``None``) or a result row."""
    return Labels(names=["Chair"], truncated=[0.0], occluded=[0], alpha=[0.0], bbox=[[300.0, 100.0, 400.0, 250.0]],
                  dims_hwl=[[0.9, 0.6, 0.6]], location=[[0.0, 0.5, 3.0]], rotation_y=[0.0],
                  score=None if score is None else [score])


@pytest.mark.parametrize("num_gt", [1, 2, 10, 18, 38, 40, 41, 42, 100])
def test_ap_ceiling_is_what_a_perfect_detector_scores(num_gt):
    # KITTI's few-GT saturation: one threshold per true positive, so N < 41 boxes fill only N of the 41 recall slots
    expected_r40 = 100.0 if num_gt >= 41 else 100.0 * (num_gt - 1) / 40
    expected_r11 = 100.0 if num_gt >= 41 else 100.0 * ((num_gt - 1) // 4 + 1) / 11
    ceiling = ap_ceiling(num_gt)
    assert ceiling["R40"] == pytest.approx(expected_r40, abs=1e-12)
    assert ceiling["R11"] == pytest.approx(expected_r11, abs=1e-12)
    perfect = evaluate([_one_chair(None)] * num_gt, [_one_chair(1.0)] * num_gt, ["Chair"])  # one chair per frame
    for metric in ("3d", "bev"):
        assert perfect.overall["Chair"][metric] == ceiling
    assert ap_ceiling(0) == {"R40": 0.0, "R11": 0.0}


def test_oracle_on_fewer_than_41_chairs_scores_the_kitti_ceiling(streams):
    # a perfect detector on a short stream: every chair found, no false positive, and still below 100
    _, still = streams
    s = score(prepare(still, Source("oracle"), latency_ms=0.0), "ego")
    assert s["num_gt"]["Chair"] == 18
    assert s["ap_ceiling"]["Chair"] == {"R40": 42.5, "R11": pytest.approx(500.0 / 11, abs=1e-12)}
    for ap in (s["sAP"], s["offline_AP"]):
        for metric in ("3d", "bev"):
            assert ap["Chair"][metric] == s["ap_ceiling"]["Chair"]
    table = format_summary(s)  # the printed table shows the ceiling beside the scores
    assert "ceiling (perfect)      42.50      42.50     45.45      45.45" in table
    moving, _ = streams
    full = score(prepare(moving, Source("oracle"), latency_ms=0.0), "raw")
    assert full["ap_ceiling"]["Chair"] == {"R40": 100.0, "R11": 100.0}
    assert "ceiling" not in format_summary(full)  # at 100 it says nothing


def test_still_robot_loses_only_the_queries_before_the_first_output(streams, tmp_path):
    _, still = streams
    assert len(still.sequences[0]) == 9 and (still.sequences[0].poses == still.sequences[0].poses[0]).all()
    results = _write_noisy_results(still, tmp_path / "res", same_noise_every_frame=True)
    prep = prepare(still, Source("results", results=str(results)), latency_ms=1.3 * PERIOD_MS)
    s = score(prep, "raw")
    assert s["num_gt"]["Chair"] == 18 and s["offline_AP"]["Chair"]["3d"]["R40"] > 0
    # the first output is emitted at 650 ms: queries at 0 and 500 ms have nothing yet
    assert s["queries_without_output"] == 2
    own = query_labels(prep, "raw", [np.arange(9)])
    expected = [Labels.empty(with_score=True)] * 2 + own[2:]
    _, ap = evaluate_overall([g for row in prep.gts for g in row], expected, prep.classes, prep.min_overlaps)
    assert s["sAP"] == ap
    assert s["sAP"] != s["offline_AP"]  # the two empty queries do count


def test_constant_latency_gives_exact_staleness(streams):
    moving, _ = streams
    n = [len(q) for q in moving.sequences]
    # one frame period: every frame is processed and scored one frame late
    s = score(prepare(moving, Source("oracle"), latency_ms=PERIOD_MS), "raw")
    assert s["staleness_frames"] == {"mean": 1.0, "p95": 1.0} and s["staleness_ms"] == {"mean": 500.0, "p95": 500.0}
    assert s["queries_without_output"] == 2 and s["frames_processed"] == 1.0 and s["in_time"] == 0.0
    # m = 3 periods, one worker: it takes frames 0, 3, 6, ...; query i sees frame 3 * (i // 3 - 1): 3, 4, 5 stale
    prep = prepare(moving, Source("oracle"), latency_ms=3 * PERIOD_MS)
    for src, m in zip(query_sources(prep), n):
        i = np.arange(3, m)
        assert (src[:3] == -1).all() and np.array_equal(i - src[3:], 3 + i % 3)
    assert score(prep, "raw")["frames_processed"] == pytest.approx(sum(-(-k // 3) for k in n) / sum(n), abs=1e-6)
    # m = 3 periods, a worker per frame: exactly 3 frames after warm-up
    prep = prepare(moving, Source("oracle"), latency_ms=3 * PERIOD_MS, schedule="unbounded")
    for src, m in zip(query_sources(prep), n):
        assert (src[:3] == -1).all() and np.array_equal(np.arange(3, m) - src[3:], np.full(m - 3, 3))
    # a latency just over one period: the output of frame k is first seen at k + 2 (emission <= capture, exact)
    prep = prepare(moving, Source("oracle"), latency_ms=PERIOD_MS + 0.001, schedule="unbounded")
    assert all(np.array_equal(np.arange(2, m) - src[2:], np.full(m - 2, 2)) for src, m in zip(query_sources(prep), n))


def test_ego_compensation_never_hurts_the_oracle(streams):
    moving, _ = streams
    gained = 0.0
    for latency in (250.0, 500.0, 1000.0, 2000.0):
        prep = prepare(moving, Source("oracle"), latency_ms=latency)
        ego, raw = score(prep, "ego"), score(prep, "raw")
        assert all(e >= r for e, r in zip(_ap_values(ego["sAP"]), _ap_values(raw["sAP"])))
        gained += ego["sAP"]["Chair"]["3d"]["R40"] - raw["sAP"]["Chair"]["3d"]["R40"]
    assert gained > 10  # on a moving robot, stale boxes without compensation miss


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "detector.cli", "stream-eval", *args], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=600)


def test_cli_json_is_byte_identical_and_has_the_issue_shape(streams, tmp_path):
    moving, _ = streams
    outs = []
    for k in range(2):
        res = _cli("--data", str(moving.root), "--oracle", "--latency-ms", "700", "--mode", "raw", "--json-out",
                   str(tmp_path / f"r{k}.json"), "--quiet", *(["--json"] if k else []))
        assert res.returncode == 0, res.stderr
        outs.append((tmp_path / f"r{k}.json").read_bytes())
        # --json prints the same JSON to stdout instead of the table; --json-out alone still prints the table
        if k:
            assert json.loads(res.stdout) == json.loads(outs[-1])
        else:
            assert res.stdout.startswith("streaming evaluation:")
    assert outs[0] == outs[1]
    s = json.loads(outs[0])
    assert set(s["sAP"]["Chair"]) == {"3d", "bev"} and set(s["sAP"]["Chair"]["3d"]) == {"R40", "R11"}
    assert set(s["offline_AP"]["Chair"]["bev"]) == {"R40", "R11"} and set(s["staleness_ms"]) == {"mean", "p95"}
    assert 0 < s["frames_processed"] < 1 and s["queries_without_output"] == 4 and s["mode"] == "raw"


def test_cli_errors(streams, tmp_path, capsys):
    from detector.cli import main

    moving, _ = streams
    cases = [
        (["--oracle", "--latency", "measured"], "--latency measured needs a model"),
        (["--oracle", "--results", str(tmp_path)], "give exactly one of"),
        ([], "give exactly one of"),
        (["--config", "x.yaml", "--oracle"], "give exactly one of"),
        (["--oracle", "--latency-ms", "-5"], "--latency-ms must be >= 0"),
        (["--results", str(tmp_path / "none"), "--latency-ms", "0"], "result folder not found"),
        (["--oracle", "--latency", str(tmp_path / "none.json")], "latency log not found"),
        (["--oracle", "--latency-ms", "0", "--latency-log", str(tmp_path / "l.json")], "--latency-log records"),
        (["--oracle", "--latency-ms", "0", "--json-out", str(tmp_path / "x.txt")], "--json-out must name a .json file"),
    ]
    for args, message in cases:
        with pytest.raises(SystemExit) as e:
            main(["stream-eval", "--data", str(moving.root), *args, "--quiet"])
        lines = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], (
            args, lines)
    with pytest.raises(SystemExit) as e:
        main(["stream-eval", "--data", str(tmp_path), "--oracle", "--latency-ms", "0"])
    assert e.value.code == 2 and "no stream.json" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written


def test_model_with_measured_latency(streams, tmp_path):
    import torch

    from detector.checkpoint import Checkpoint, save_checkpoint
    from detector.config import load_experiment
    from detector.models import build_model

    _, still = streams
    cfg_path = write_test_config(tmp_path / "tiny.yaml", model=dict(point_cloud_range=[0.0, -4.8, -2.0, 6.4, 4.8, 2.0],
                                                                    score_thr=0.05))
    cfg = load_experiment(cfg_path)
    torch.manual_seed(0)
    model = build_model(cfg.model)
    ckpt = tmp_path / "tiny.pt"
    save_checkpoint(ckpt, Checkpoint.capture(model=model, optimizer=torch.optim.SGD(model.parameters(), lr=0.1),
                                             cfg=cfg, epoch=1, step_in_epoch=0, step=1, global_batch=1))
    src = Source("model", config=str(cfg_path), checkpoint=str(ckpt), threads=1)
    prep = prepare(still, src, latency_ms=None, repeats=1, warmup=1)
    s = score(prep, "ego")
    assert s["latency"] == "measured" and s["latency_ms"]["median"] > 0 and s["machine"]["torch_threads"] == 1
    assert 0 < s["frames_processed"] <= 1 and s["queries_without_output"] >= 1
    # an output is never used before it exists: every query's staleness is at least its output's latency
    seq, sched = still.sequences[0], prep.schedules[0]
    src_frames = query_sources(prep)[0]
    for i, k in enumerate(src_frames):
        if k >= 0:
            j = int(np.flatnonzero(sched.inputs == k)[0])
            assert seq.times_us[i] - seq.times_us[k] >= sched.latency_us[j]
    # the same model with zero latency: exactly its offline AP
    zero = score(prepare(still, src, latency_ms=0.0), "ego")
    assert zero["sAP"] == zero["offline_AP"] == s["offline_AP"]
    # the latency log replays the measurement exactly, also without the offline pass (the model then runs only on
    # the processed frames), and saved result files stand in for the model
    log = json.loads(json.dumps(prep.latency_log))
    assert sum(len(v) for v in log["sequences"].values()) == len(sched.inputs)
    again = prepare(still, src, latency_log=log, offline=False)
    assert np.array_equal(again.schedules[0].emit_us, sched.emit_us)
    assert sum(o is not None for o in again.outputs[0]) == len(set(sched.inputs.tolist()))
    replay = score(again, "ego")
    assert replay["sAP"] == s["sAP"] and replay["latency"] == "log"
    # (the offline AP exists only if the schedule happened to process every frame)
    assert replay["offline_AP"] == (s["offline_AP"] if len(set(sched.inputs.tolist())) == 9 else None)
    from detector.stream.run import save_results

    save_results(prep, tmp_path / "res")
    from_files = prepare(still, Source("results", results=str(tmp_path / "res")), latency_log=log)
    assert np.array_equal(from_files.schedules[0].inputs, sched.inputs)
    assert len(list((tmp_path / "res" / "00").glob("*.txt"))) == 9 and from_files.offline
    # without the offline pass only the processed frames are saved (1.3 s latency: frames 0, 2, 5, 7): enough to
    # replay the schedule, no offline AP
    slow = prepare(still, src, latency_ms=1300.0, offline=False)
    assert slow.schedules[0].inputs.tolist() == [0, 2, 5, 7]
    save_results(slow, tmp_path / "part")
    assert sorted(p.stem for p in (tmp_path / "part" / "00").glob("*.txt")) == ["000000", "000002", "000005", "000007"]
    part = prepare(still, Source("results", results=str(tmp_path / "part")), latency_ms=1300.0)
    assert score(part, "raw")["offline_AP"] is None and score(part, "raw")["sAP"] == score(slow, "raw")["sAP"]
    with pytest.raises(InputError, match="no result file for frame 000001 of sequence 00, which the schedule"):
        prepare(still, Source("results", results=str(tmp_path / "part")), latency_ms=0.0)
