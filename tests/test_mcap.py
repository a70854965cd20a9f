"""ROS 2 bags (MCAP): ``mpchair view --mcap`` (a stream, a dataset) and ``detector stream-eval --mcap``, read back with
the MCAP reader and every message decoded with mcap-ros2-support's decoder: the topics, one message per frame, the
clouds equal the velodyne files, the boxes the labels, tf the poses, the stamps the capture times; the detector's
boxes are the output it had at each frame, as emitted and moved by the robot's motion; and the clear errors (no extra
installed, a bad output path)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from helpers_recordings import make_recording_inputs

from mpchair.geometry import labels_to_boxes, wrap_angle
from mpchair.kitti import read_calib, read_labels, read_poses, read_times, velodyne_rows

ROOT = Path(__file__).resolve().parents[1]
FRAME_TOPICS = ("/points", "/tf", "/ground_truth", "/ground_truth/markers")


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """A stream (2 episodes, 6 frames each at 1 Hz) and a 3-frame dataset of one synthetic house."""
    return make_recording_inputs(tmp_path_factory.mktemp("mcap"))


def _main(module: str, *args: str) -> None:
    """Run a CLI in this process; it must exit 0."""
    main = __import__(module, fromlist=["main"]).main
    with pytest.raises(SystemExit) as e:
        main(list(args))
    assert e.value.code == 0


def _read(path: Path) -> tuple[dict[str, list], dict[str, str], dict]:
    """Every message of a bag decoded: ``{topic: [(log time ns, message), ...]}`` in log-time order, the schema name
    of each topic, and the ``mpchair`` metadata record; checks the file is laid out as rosbag2's mcap storage writes
    (profile ros2, ros2msg schemas, cdr messages)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    messages: dict[str, list] = defaultdict(list)
    types = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            assert types.setdefault(channel.topic, schema.name) == schema.name
            messages[channel.topic].append((message.log_time, decoded))
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return messages, types, meta["mpchair"]


def _us(stamp) -> int:
    return stamp.sec * 1_000_000 + stamp.nanosec // 1000


def _matrix(t) -> np.ndarray:
    """(4,4) of a geometry_msgs/Transform."""
    q, v = t.rotation, t.translation
    x, y, z, w = q.x, q.y, q.z, q.w
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = [v.x, v.y, v.z]
    return T


def _boxes(array) -> tuple[np.ndarray, list[str], list[float]]:
    """(N,7) boxes, class ids and scores of a vision_msgs/Detection3DArray (upright boxes: yaw from the quaternion)."""
    rows, names, scores = [], [], []
    for d in array.detections:
        c, s, q = d.bbox.center.position, d.bbox.size, d.bbox.center.orientation
        assert q.x == q.y == 0.0
        rows.append([c.x, c.y, c.z, s.x, s.y, s.z, 2 * np.arctan2(q.z, q.w)])
        (hyp,) = d.results
        names.append(hyp.hypothesis.class_id)
        scores.append(hyp.hypothesis.score)
        assert hyp.pose.pose == d.bbox.center and d.header == array.header
    return np.array(rows).reshape(-1, 7), names, scores


def _label_boxes(label_file: Path, calib_file: Path) -> tuple[np.ndarray, list[str]]:
    objs = read_labels(label_file).objects()
    if not len(objs):
        return np.zeros((0, 7)), []
    return labels_to_boxes(objs, read_calib(calib_file)), list(objs.names)


def _assert_boxes_equal(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape
    np.testing.assert_allclose(a[:, :6], b[:, :6], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(a[:, 6] - b[:, 6]), 0.0, atol=1e-9)


def _sensor_height(meta_file: Path) -> float:
    """The sensor height above the floor a stream / dataset was made with (metres)."""
    return json.loads(meta_file.read_text(encoding="utf-8"))["config"]["viewpoints"]["height"]


def _check_frame(msgs: dict, n: int, t_us: int, velodyne: Path, label: Path, calib: Path, dontcare: Path | None,
                 pose: np.ndarray, height: float) -> None:
    """Frame ``n`` of a bag against its files: stamps, cloud, ground truth (+ markers) and tf (base_link ``height``
    below the sensor)."""
    for topic in FRAME_TOPICS:
        assert msgs[topic][n][0] == t_us * 1000, topic
    cloud = msgs["/points"][n][1]
    assert _us(cloud.header.stamp) == t_us and cloud.header.frame_id == "sensor"
    assert [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 7, 1)]  # 7: FLOAT32
    assert (cloud.height, cloud.width, cloud.point_step, cloud.row_step) == (
        1, velodyne_rows(velodyne), 16, 16 * velodyne_rows(velodyne))
    assert bytes(cloud.data) == velodyne.read_bytes() and not cloud.is_bigendian

    gt = msgs["/ground_truth"][n][1]
    assert _us(gt.header.stamp) == t_us and gt.header.frame_id == "sensor"
    boxes, names = _label_boxes(label, calib)
    dc = _label_boxes(dontcare, calib)[0] if dontcare is not None else np.zeros((0, 7))
    got, got_names, got_scores = _boxes(gt)
    _assert_boxes_equal(got, np.vstack([boxes, dc]))
    assert got_names == names + ["DontCare"] * len(dc) and got_scores == [1.0] * len(got_names)
    markers = msgs["/ground_truth/markers"][n][1].markers
    assert markers[0].action == 3  # DELETEALL: a viewer shows this frame's boxes only
    wires = [m for m in markers if m.ns == "boxes"]
    assert len(wires) == len(got) and all(m.type == 5 and len(m.points) == 24 for m in wires)  # LINE_LIST, 12 edges
    assert [m.text for m in markers if m.ns == "labels"] == names

    (world_base, base_sensor) = msgs["/tf"][n][1].transforms
    assert (world_base.header.frame_id, world_base.child_frame_id) == ("world", "base_link")
    assert (base_sensor.header.frame_id, base_sensor.child_frame_id) == ("base_link", "sensor")
    assert _us(world_base.header.stamp) == _us(base_sensor.header.stamp) == t_us
    np.testing.assert_allclose(_matrix(world_base.transform) @ _matrix(base_sensor.transform), pose, atol=1e-9)
    B = _matrix(world_base.transform)
    np.testing.assert_allclose(B[2, :3], [0, 0, 1], atol=1e-12)  # base_link stands upright on the floor
    np.testing.assert_allclose(B[:3, 3], pose[:3, 3] - [0, 0, height], atol=1e-12)


def test_stream_bag(folders, tmp_path):
    pytest.importorskip("mcap_ros2")
    out = tmp_path / "s.mcap"
    _main("mpchair.cli", "view", str(folders / "stream"), "--mcap", str(out))
    msgs, types, meta = _read(out)
    assert types == {"/points": "sensor_msgs/msg/PointCloud2", "/tf": "tf2_msgs/msg/TFMessage",
                     "/ground_truth": "vision_msgs/msg/Detection3DArray",
                     "/ground_truth/markers": "visualization_msgs/msg/MarkerArray",
                     "/trajectory": "nav_msgs/msg/Path"}
    # the sequences follow each other, the second one period (1 s at 1 Hz) after the first one's last frame
    offsets = json.loads(meta["sequence_offsets_us"])
    assert meta["kind"] == "stream" and offsets == {"00": 0, "01": 6_000_000}
    height = _sensor_height(folders / "stream" / "stream.json")
    n = 0
    for s, seq in enumerate(("00", "01")):
        d = folders / "stream" / "sequences" / seq
        times, poses = read_times(d / "times.txt"), read_poses(d / "poses.txt")
        assert len(times) == 6
        trajectory = msgs["/trajectory"][s][1]
        assert msgs["/trajectory"][s][0] == (times[0] + offsets[seq]) * 1000 and trajectory.header.frame_id == "world"
        assert [_us(p.header.stamp) for p in trajectory.poses] == list(times + offsets[seq])
        np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                                    for p in trajectory.poses], poses[:, :3, 3], atol=1e-12)
        for i, t in enumerate(times):
            fid = f"{i:06d}"
            _check_frame(msgs, n, int(t) + offsets[seq], d / "velodyne" / f"{fid}.bin", d / "label_2" / f"{fid}.txt",
                         d / "calib" / f"{fid}.txt", d / "label_dontcare" / f"{fid}.txt", poses[i], height)
            n += 1
    assert {t: len(m) for t, m in msgs.items()} == {**dict.fromkeys(FRAME_TOPICS, 12), "/trajectory": 2}
    assert any(name == "DontCare" for _, m in msgs["/ground_truth"] for name in _boxes(m)[1])  # in the test data
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_same_stream_same_bytes(folders, tmp_path):
    pytest.importorskip("mcap_ros2")
    from mpchair.recording.mcap import log_stream

    log_stream(folders / "stream", tmp_path / "a.mcap")
    log_stream(folders / "stream", tmp_path / "b.mcap")
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()


def test_dataset_bag(folders, tmp_path):
    pytest.importorskip("mcap_ros2")
    root = folders / "dataset" / "training"
    for args, period_us, frames in (([], 100_000, 3), (["--limit", "2", "--rate", "4"], 250_000, 2)):
        out = tmp_path / "d.mcap"
        _main("mpchair.cli", "view", str(folders / "dataset"), "--mcap", str(out), *args)
        msgs, types, meta = _read(out)
        assert sorted(types) == sorted(FRAME_TOPICS)  # no trajectory: a dataset's frames are separate viewpoints
        assert {t: len(m) for t, m in msgs.items()} == dict.fromkeys(FRAME_TOPICS, frames)
        ids = [f"{i:06d}" for i in range(frames)]
        assert meta == {"kind": "dataset", "period_us": str(period_us), "frame_ids": json.dumps(ids)}
        for n, fid in enumerate(ids):
            _check_frame(msgs, n, n * period_us, root / "velodyne" / f"{fid}.bin", root / "label_2" / f"{fid}.txt",
                         root / "calib" / f"{fid}.txt", None, read_poses(root / "pose" / f"{fid}.txt")[0],
                         _sensor_height(folders / "dataset" / "manifest.json"))


def test_stream_eval_bag_has_what_the_detector_had(folders, tmp_path, capsys):
    pytest.importorskip("mcap_ros2")
    from detector.stream import Source, prepare, read_stream
    from detector.stream.run import query_sources

    out = tmp_path / "e.mcap"
    # 1.5 s of latency at 1 Hz: the oracle's first box arrives at frame 2, one or two frames stale
    capsys.readouterr()
    _main("detector.cli", "stream-eval", "--data", str(folders / "stream"), "--oracle", "--latency-ms", "1500",
          "--mcap", str(out), "--quiet")
    msgs, types, _ = _read(out)
    # it says what it wrote, as mpchair view --mcap does: the bag's frames, messages and topics
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1] == (f"wrote {out}: 12 frames, {sum(len(m) for m in msgs.values())} messages on {len(msgs)} "
                           f"topics (open it in Foxglove, or replay it: ros2 bag play -s mcap {out})"), printed
    topics = ("/detections/oracle", "/detections/oracle/ego")
    for topic in topics:
        assert types[topic] == "vision_msgs/msg/Detection3DArray"
        assert types[f"{topic}/markers"] == "visualization_msgs/msg/MarkerArray"
    assert {t: len(m) for t, m in msgs.items()} == {
        **dict.fromkeys(FRAME_TOPICS + topics + tuple(f"{t}/markers" for t in topics), 12), "/trajectory": 2}
    st = read_stream(folders / "stream")
    sources = query_sources(prepare(st, Source("oracle"), latency_ms=1500.0))
    n = 0
    for seq, src in zip(st.sequences, sources):
        assert list(src) == [-1, -1, 0, 1, 1, 3]
        for i, k in enumerate(src):
            assert msgs["/detections/oracle"][n][0] == msgs["/points"][n][0]  # stamped at the query frame
            raw, names, scores = _boxes(msgs["/detections/oracle"][n][1])
            ego, ego_names, _ = _boxes(msgs["/detections/oracle/ego"][n][1])
            if k < 0:
                assert len(raw) == len(ego) == 0
            else:  # the oracle's output: frame k's chairs, score 1, read in frame k's sensor frame ...
                fid = f"{k:06d}"
                want, want_names = _label_boxes(seq.folder / "label_2" / f"{fid}.txt",
                                                seq.folder / "calib" / f"{fid}.txt")
                _assert_boxes_equal(raw, want)
                assert names == ego_names == want_names and scores == [1.0] * len(want)
                # ... and, moved by the robot's motion, the same boxes in the world
                world = lambda b, T: b[:, :3] @ T[:3, :3].T + T[:3, 3]  # noqa: E731
                np.testing.assert_allclose(world(ego, seq.poses[i]), world(raw, seq.poses[k]), atol=1e-9)
                np.testing.assert_allclose(ego[:, 3:6], raw[:, 3:6])
            n += 1


def _hide_extra(tmp_path: Path) -> dict:
    """The environment of a Python without mcap / mcap-ros2-support, as on an install without the extra."""
    (tmp_path / "sitecustomize.py").write_text("import sys\nsys.modules['mcap'] = None\n"
                                               "sys.modules['mcap_ros2'] = None\n")
    return {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"}


def test_missing_extra_is_one_error_line(folders, tmp_path):
    env = _hide_extra(tmp_path)
    for module, args in (("mpchair.cli", ["view", str(folders / "stream"), "--mcap", str(tmp_path / "x.mcap")]),
                         ("detector.cli", ["stream-eval", "--data", str(folders / "stream"), "--oracle",
                                           "--latency-ms", "0", "--mcap", str(tmp_path / "x.mcap")])):
        res = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, timeout=600,
                             env=env)
        assert res.returncode == 2 and res.stderr.strip().splitlines() == [
            "error: --mcap needs mcap and mcap-ros2-support, which are not installed; install the ros extra: "
            "pip install -e '.[ros]' (mcap==1.6.0, mcap-ros2-support==0.6.0)"], res.stderr
        assert res.stdout == ""  # stream-eval stopped before scoring
    assert not (tmp_path / "x.mcap").exists()


def test_bad_output_paths(folders, tmp_path, capsys):
    from detector.cli import main as detector_main
    from mpchair.cli import main as mpchair_main

    (tmp_path / "folder.mcap").mkdir()
    (tmp_path / "file").write_text("")
    cases = [(tmp_path / "x.png", "--mcap must name a .mcap file"),
             (tmp_path / "folder.mcap", "--mcap names a folder"),
             (tmp_path / "file" / "x.mcap", f"{tmp_path / 'file'}: cannot write the bag here: not a folder")]
    for out, message in cases:
        for main, args in ((mpchair_main, ["view", str(folders / "stream"), "--mcap", str(out)]),
                           (detector_main, ["stream-eval", "--data", str(folders / "stream"), "--oracle",
                                            "--latency-ms", "0", "--mcap", str(out), "--quiet"])):
            with pytest.raises(SystemExit) as e:
                main(args)
            captured = capsys.readouterr()
            lines = captured.err.strip().splitlines()
            assert e.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], (
                out, lines)
            assert captured.out == ""  # refused before any work
    for args, message in ((["--rerun", str(tmp_path / "x.rrd")], "give --rerun or --mcap, not both"),
                          (["--frame", "0"], "leave out --frame / --out")):
        with pytest.raises(SystemExit) as e:
            mpchair_main(["view", str(folders / "dataset"), "--mcap", str(tmp_path / "y.mcap"), *args])
        assert e.value.code == 2 and message in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "folder.mcap"]  # nothing written


def test_dataset_rate_must_be_positive(folders, tmp_path, capsys):
    pytest.importorskip("mcap_ros2")
    from mpchair.cli import main

    for rate in ("0", "-1", "inf"):
        with pytest.raises(SystemExit) as e:
            main(["view", str(folders / "dataset"), "--mcap", str(tmp_path / "d.mcap"), "--rate", rate])
        assert e.value.code == 2 and "--rate must be a positive number" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_quaternions_of_any_rotation():
    """Tilted poses too (a dataset's sensor may pitch): every branch of the conversion gives back the matrix."""
    from scipy.spatial.transform import Rotation

    from mpchair.recording.ros2_convert import quaternion

    rotations = list(Rotation.random(200, random_state=0).as_matrix())
    rotations += [np.diag(d) for d in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1])]  # 0 and 180 degree turns
    for R in rotations:
        q = quaternion(R)
        assert q["w"] >= 0 and abs(np.linalg.norm(list(q.values())) - 1) < 1e-12
        t = SimpleNamespace(rotation=SimpleNamespace(**q), translation=SimpleNamespace(x=0.0, y=0.0, z=0.0))
        np.testing.assert_allclose(_matrix(t)[:3, :3], R, atol=1e-12)
