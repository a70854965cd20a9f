"""End to end: ``mpchair stream`` on a synthetic house — the sequence layout, frames made by ``generate``'s own label
pipeline at the planned poses, DontCare for chairs rejected inside the labelled region, exact times, motion within
the limits, SIGKILL + resume byte-identical, and the clear errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mpchair.core.errors import InputError
from mpchair.dataset.frame import build_context, cast_scan, floor_areas, label_pose
from mpchair.geometry import in_region, labels_to_boxes, wrap_angle, yaw_of
from mpchair.kitti import DONTCARE, read_calib, read_labels, read_poses, read_times, read_velodyne
from mpchair.labels.filters import OUTSIDE_REGION_REASONS
from mpchair.labels.select import apply_scan_points
from mpchair.scan.sensors import load_sensor, scan_directions
from mpchair.scan.viewpoints import ViewpointParams
from mpchair.stream import StreamRequest, stream
from mpchair.stream.episodes import EpisodeSettings, plan_episode
from mpchair.stream.freespace import free_space
from mpchair.stream.routes import RouteRules
from mpchair.stream.unicycle import Limits
from mpchair.stream.writer import read_stream_record
from mpchair.synth import synthesize_house, write_house

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def house_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("houses")
    house = synthesize_house(7, levels=1)
    write_house(root, house)
    return root, house


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file() and not p.name.endswith(".tmp")}


@pytest.fixture(scope="module")
def made(house_root, tmp_path_factory):
    root, house = house_root
    req = StreamRequest(root=root, houses=(house.id,), episodes=1, out=tmp_path_factory.mktemp("st") / "s", rate=2.0,
                        seed=1, progress=False)
    return req, stream(req)


def test_stream_layout_times_and_motion(made):
    req, summary = made
    out = Path(req.out)
    meta = json.loads((out / "stream.json").read_text())
    assert summary.complete and summary.sequences == 1 and summary.frames == meta["totals"]["frames"] > 20
    assert meta["format"] == "mpchair-stream/1" and meta["rate_hz"] == 2.0 and meta["seed"] == 1
    assert meta["config"]["limits"]["speed"] == 0.5 and meta["config"]["sensor"]["name"] == "mp3d-depth90"
    assert set(meta["houses"][req.houses[0]]["files_sha256"]) >= {f"{req.houses[0]}.house", f"{req.houses[0]}.ply"}
    assert meta["region"] == {"max_abs_dz": 1.0, "max_distance": 7.0, "half_fov": pytest.approx(np.pi / 4)}
    seq = out / "sequences" / "00"
    times, poses = read_times(seq / "times.txt"), read_poses(seq / "poses.txt")
    n = len(times)
    assert n == summary.frames and np.array_equal(times, np.arange(n) * 500_000)
    assert (seq / "times.txt").read_text().splitlines()[:3] == ["0.000000", "0.500000", "1.000000"]
    for d, ext in (("velodyne", "bin"), ("label_2", "txt"), ("label_dontcare", "txt"), ("calib", "txt")):
        assert sorted(p.name for p in (seq / d).iterdir()) == [f"{i:06d}.{ext}" for i in range(n)]
    # the robot moves within its limits between frames (0.5 s apart): <= 0.25 m and <= 0.5 rad
    step = np.linalg.norm(np.diff(poses[:, :2, 3], axis=0), axis=1)
    turn = np.abs(wrap_angle(np.diff([yaw_of(T) for T in poses])))
    assert step.max() <= 0.25 + 1e-6 and turn.max() <= 0.5 + 1e-6 and step.sum() > 3.0
    assert np.allclose(poses[:, 2, 3], poses[0, 2, 3], atol=0.05)  # one level, sensor at a constant height
    # one record per frame, typed and read back to the bytes written; stream.json's totals are their sums
    paths = sorted((out / ".frames" / "00").glob("*.json"))
    records = [read_stream_record(p) for p in paths]
    assert [r.frame for r in records] == [f"{i:06d}" for i in range(n)] and {r.sequence for r in records} == {"00"}
    assert all(r.to_json() + "\n" == p.read_text() for r, p in zip(records, paths))
    assert [r.time_us for r in records] == list(times) and sum(r.kept for r in records) == summary.kept
    assert meta["totals"]["points"] == sum(r.points for r in records) and summary.dontcare == meta["totals"]["dontcare"]


def test_frames_are_generates_labels_at_the_planned_poses(made, house_root):
    req, _ = made
    root, synth = house_root
    from mpchair.matterport.house import read_house
    from mpchair.matterport.source import find_houses

    house = read_house(find_houses(root)[synth.id])
    sensor = load_sensor("mp3d-depth90")
    ctx = build_context(house, frozenset({3}))
    params = ViewpointParams(height=req.height, robot_radius=req.robot_radius)
    spaces = free_space(floor_areas(house), ctx.raycaster, ctx.floor_ok, ctx.normal_z, params)
    ep = plan_episode(spaces, house.id, 0, EpisodeSettings(req.rate, Limits(), RouteRules(), req.height, True, None,
                                                           req.seed))
    seq = Path(req.out) / "sequences" / "00"
    assert np.allclose(read_poses(seq / "poses.txt"), ep.poses, atol=1e-8)
    checked_dontcare = 0
    for i in range(0, len(ep.times_us), 5):
        dec = label_pose(ctx, sensor, ep.poses[i])
        pts = cast_scan(sensor, scan_directions(sensor), ep.poses[i], ctx.raycaster)
        dec = apply_scan_points(dec, pts, sensor.filters)
        assert np.array_equal(read_velodyne(seq / "velodyne" / f"{i:06d}.bin"), pts)
        labels = read_labels(seq / "label_2" / f"{i:06d}.txt")
        calib = read_calib(seq / "calib" / f"{i:06d}.txt")
        objs = labels.objects()
        kept = dec.boxes[dec.kept]
        assert len(objs) == len(kept) and np.allclose(labels_to_boxes(objs, calib)[:, :3], kept[:, :3], atol=0.01)
        inside = [r != "" and r not in OUTSIDE_REGION_REASONS for r in dec.reasons]
        dc3d = read_labels(seq / "label_dontcare" / f"{i:06d}.txt")
        assert len(dc3d) == sum(inside) and (labels.names == DONTCARE).sum() == max(sum(inside), int(len(objs) == 0))
        if len(dc3d):
            boxes = labels_to_boxes(dc3d, calib)
            assert np.allclose(boxes[:, :3], dec.boxes[inside][:, :3], atol=0.01)
            assert in_region(boxes, 1.0, 7.0, np.pi / 4).all()
            checked_dontcare += len(dc3d)
    assert checked_dontcare > 0  # the stream does hold chairs that became DontCare


def _ends(pid: int, within: float = 10.0) -> bool:
    """Whether process ``pid`` ends (or is a zombie for its new parent to reap) within ``within`` seconds."""
    deadline = time.time() + within
    while time.time() < deadline:
        try:
            if Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0] in ("Z", "X"):
                return True
        except (FileNotFoundError, ProcessLookupError):
            return True
        time.sleep(0.02)
    return False


def test_sigkill_then_resume_is_byte_identical(house_root, tmp_path):
    """Killed and resumed with two workers, the stream equals one made in one go by one process. The kill goes to the
    main process alone (as the out-of-memory killer's would): its workers end with it and hold no lock."""
    root, house = house_root
    args = ["--root", str(root), "--house", house.id, "--episodes", "1", "--rate", "1", "--duration", "6",
            "--no-look-around", "--seed", "4"]
    ref = tmp_path / "ref"
    stream(StreamRequest(root=root, houses=(house.id,), episodes=1, out=ref, rate=1.0, duration=6.0,
                         look_around=False, seed=4, progress=False))
    dest = tmp_path / "killed"
    cmd = [sys.executable, "-m", "mpchair.cli", "stream", *args, "--out", str(dest), "--quiet", "--workers", "2"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and not list((dest / ".frames").rglob("*.json")) and proc.poll() is None:
        time.sleep(0.05)
    workers = [int(c) for c in Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()]
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert workers and all(_ends(w) for w in workers), "a worker outlived its killed parent"
    res = subprocess.run(cmd + ["--json"], env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["complete"] and summary["made"] + summary["resumed"] == summary["frames"] == 7
    assert _tree(dest) == _tree(ref)


def test_clear_errors(house_root, tmp_path, made):
    root, house = house_root

    def req(**kw):
        base = dict(root=root, houses=(house.id,), episodes=1, out=tmp_path / "x", progress=False)
        return StreamRequest(**{**base, **kw})

    with pytest.raises(InputError, match=f"unknown house 'nope'.*available: {house.id}"):
        stream(req(houses=("nope",)))
    with pytest.raises(InputError, match="--speed 0 .* needs --duration"):
        stream(req(speed=0.0))
    with pytest.raises(InputError, match="--rate must be a positive"):
        stream(req(rate=0.0))
    with pytest.raises(InputError, match="no start/goal pair.*relax --min-geodesic"):
        stream(req(min_geodesic=200.0, max_geodesic=300.0))
    assert not (tmp_path / "x").exists()  # nothing written for bad input
    with pytest.raises(InputError, match="other settings.*rate_hz"):
        stream(dataclass_replace(made[0], rate=4.0))
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "f.txt").write_text("x")
    with pytest.raises(InputError, match="not an mpchair stream folder"):
        stream(req(out=tmp_path / "busy"))
    res = subprocess.run([sys.executable, "-m", "mpchair.cli", "stream", "--root", str(root), "--house", house.id,
                          "--episodes", "1", "--speed", "0", "--out", str(tmp_path / "y")],
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        "error: --speed 0 (a robot that stays put) needs --duration"]
    assert not (tmp_path / "y").exists()


def test_a_held_folder_is_refused_and_a_killed_first_settings_write_resumes(house_root, tmp_path):
    """A second `mpchair stream` on a folder a live one holds gets one error and touches nothing; a folder left with
    only the temp file of a killed first `.stream.json` write (and a stale lock file) is resumed, not refused."""
    from mpchair.core.lock import folder_lock

    root, house = house_root
    req = StreamRequest(root=root, houses=(house.id,), episodes=1, out=tmp_path / "s", rate=1.0, duration=2.0,
                        look_around=False, seed=4, progress=False)
    with folder_lock(tmp_path / "s" / ".stream.lock", "mpchair stream"):
        with pytest.raises(InputError, match="another mpchair stream is writing this folder"):
            stream(req)
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == []  # the lock file went with its holder
    (tmp_path / "s" / "..stream.json.k1lled.tmp").write_text('{"half')
    (tmp_path / "s" / ".stream.lock").write_text("12345\n")  # a killed holder's file: the kernel dropped its lock
    summary = stream(req)
    assert summary.complete and summary.frames == 3
    assert not list((tmp_path / "s").glob("..stream.json.*.tmp")) and not (tmp_path / "s" / ".stream.lock").exists()


def dataclass_replace(obj, **kw):
    import dataclasses

    return dataclasses.replace(obj, **kw)
