"""End to end: ``mpchair generate`` on a synthetic house — KITTI files OpenPCDet can read, boxes that match the
construction, determinism across worker counts, SIGKILL + resume, splits, and the clear errors."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mpchair.core.errors import InputError
from mpchair.dataset.generate import GenerateRequest, generate, shard_frames
from mpchair.dataset.manifest import FrameRecord, Manifest, read_frame_record, read_manifest
from mpchair.dataset.splits import split_frames
from mpchair.geometry import (
    canonical_yaw,
    fov_mask,
    labels_to_boxes,
    points_in_boxes,
    transform_boxes,
    wrap_angle,
)
from mpchair.kitti import read_calib, read_image_size, read_imageset, read_labels, read_velodyne
from mpchair.synth import synthesize_house, write_house
from mpchair.synth.realism import CLEAN

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 3


@pytest.fixture(scope="module")
def house_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("houses")
    house = synthesize_house(7, levels=1, realism=CLEAN)  # the exact counts and label roundings below are this house's
    write_house(root, house)
    return root, house


def _req(root, house, out, **kw) -> GenerateRequest:
    return GenerateRequest(root=root, houses=(house.id,), frames=FRAMES, out=out, seed=11, progress=False, **kw)


def _tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file() and not p.name.endswith(".tmp")}


@pytest.fixture(scope="module")
def dataset(house_root, tmp_path_factory):
    root, house = house_root
    out = tmp_path_factory.mktemp("ds") / "one"
    summary = generate(_req(root, house, out, workers=1))
    return out, summary


def _assert_testing_folder(out: Path) -> None:
    """testing/{velodyne,calib,image_2}/ hold exactly the test split's frames, as training/'s files (hard links)."""
    test_ids = read_imageset(out / "ImageSets" / "test.txt")
    for kind, ext in (("velodyne", "bin"), ("calib", "txt"), ("image_2", "png")):
        folder = out / "testing" / kind
        assert (sorted(p.stem for p in folder.iterdir()) if folder.is_dir() else []) == sorted(test_ids)
        for fid in test_ids:
            assert os.path.samefile(folder / f"{fid}.{ext}", out / "training" / kind / f"{fid}.{ext}")
    assert not (out / "testing" / "label_2").exists()  # KITTI's test split has no labels


def test_the_test_split_is_where_openpcdet_looks_for_it(house_root, tmp_path):
    """OpenPCDet's create_kitti_infos reads the test split from testing/ (scan, calib, image for its size): a
    10-frame dataset (3 test frames) has them there, the training/ files' own bytes, and keeps them in training/
    for the readers that take the splits from ImageSets/ (ours, Open3D-ML's subclass)."""
    root, house = house_root
    out = tmp_path / "ds"
    generate(GenerateRequest(root=root, houses=(house.id,), frames=10, out=out, seed=11, progress=False, workers=1))
    assert len(read_imageset(out / "ImageSets" / "test.txt")) > 0
    _assert_testing_folder(out)


def test_dataset_is_kitti_that_openpcdet_reads(dataset, house_root):
    out, summary = dataset
    _, house = house_root
    assert summary.complete and summary.frames == FRAMES and summary.made == FRAMES and summary.kept >= FRAMES
    manifest = read_manifest(out)
    assert str(out) not in (out / "manifest.json").read_text()  # no absolute paths
    assert manifest.houses[house.id].files_sha256[f"{house.id}.house"] == __import__("hashlib").sha256(
        house.files()[".house"]).hexdigest()
    ids = sorted(read_imageset(out / "ImageSets" / f"{s}.txt") for s in ("train", "val", "test"))
    assert sorted(sum(ids, [])) == [f"{i:06d}" for i in range(FRAMES)]
    # OpenPCDet's create_kitti_infos reads the test split from testing/ (scan, calib, image; no labels): the same
    # files as training/'s (hard links), for exactly the test ids
    _assert_testing_folder(out)
    truth = {o.index: o for o in house.objects}
    for rec in manifest.frames:
        fid = rec.frame
        calib_lines = (out / "training" / "calib" / f"{fid}.txt").read_text().splitlines()[:7]
        assert [ln.split(":")[0] for ln in calib_lines] == ["P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam",
                                                            "Tr_imu_to_velo"]
        assert all("  " not in ln for ln in calib_lines)
        text = (out / "training" / "label_2" / f"{fid}.txt").read_text()
        rows = text.splitlines()
        assert rows and all(len(r.split(" ")) == 15 for r in rows)
        calib = read_calib(out / "training" / "calib" / f"{fid}.txt")
        labels = read_labels(out / "training" / "label_2" / f"{fid}.txt")
        assert read_image_size(out / "training" / "image_2" / f"{fid}.png") == (1024, 1024)
        pts = read_velodyne(out / "training" / "velodyne" / f"{fid}.bin")
        assert len(pts) == rec.points and (pts[:, 3] == 1.0).all()
        assert (np.abs(pts[:, 2]) < 2).all() and (pts[:, 0] > 0).all() and pts[:, 0].max() <= 25 + 1e-4
        pose = np.loadtxt(out / "training" / "pose" / f"{fid}.txt").reshape(3, 4)
        T = np.vstack([pose, [0, 0, 0, 1]])
        # Boxes: the label file's boxes == the construction's aligned boxes moved through the inverse pose.
        boxes = labels_to_boxes(labels.objects(), calib)
        assert list(labels.names) == ["Chair"] * len(rec.kept)
        expect = transform_boxes(np.stack([truth[k.object_index].aligned_box for k in rec.kept]), np.linalg.inv(T))
        np.testing.assert_allclose(boxes[:, :6], expect[:, :6], atol=0.006)
        # The heading is the canonical one (long side's direction in [-pi/2, pi/2)), up to the file's 2 decimals.
        dyaw = wrap_angle(boxes[:, 6] - canonical_yaw(expect[:, 6]))
        np.testing.assert_allclose(dyaw, 0, atol=0.006)
        # OpenPCDet's FOV crop keeps every labelled box: each box's 2D box has area inside image_2 (its centre can sit
        # below the image when the chair is close) and all its points are inside image_2.
        assert ((labels.bbox[:, 2] > labels.bbox[:, 0]) & (labels.bbox[:, 3] > labels.bbox[:, 1])).all()
        # (The grid's last row / column lands on u or v = 1024, which the crop drops: P2 is f = c = 512 as specified,
        # half a pixel off habitat's linspace grid.)
        fov = fov_mask(pts, calib, (1024, 1024))
        for in_box in points_in_boxes(pts[:, :3], boxes):
            assert (fov & in_box).sum() >= 0.95 * in_box.sum()
        assert fov.mean() > 0.99
        assert (labels.bbox[:, 2] > labels.bbox[:, 0]).all() and (labels.bbox <= 1023).all()
        assert set(labels.occluded) <= {0, 1, 2} and ((labels.truncated >= 0) & (labels.truncated <= 1)).all()
        for k in rec.kept:
            assert k.visible_pixels > 35 and k.points_in_box >= 35 and k.in_box_fraction >= 0.8
        assert all(r.reason for r in rec.rejected)


@pytest.mark.parametrize("sensor", ["mp3d-depth90", "lidar64", "lidar16"])
def test_every_profile_writes_canonical_chair_yaws(house_root, tmp_path, sensor):
    """Each sensor profile generates end to end, and every label's heading is canonical in the sensor frame:
    yaw in [-pi/2, pi/2), i.e. KITTI rotation_y in (-pi, 0] (the long side's direction, as the original did)."""
    root, house = house_root
    out = tmp_path / sensor
    summary = generate(GenerateRequest(root=root, houses=(house.id,), frames=4, out=out, seed=5, sensor=sensor,
                                       progress=False))
    assert summary.complete and summary.kept > 0
    n = 0
    for fid in (f"{i:06d}" for i in range(4)):
        labels = read_labels(out / "training" / "label_2" / f"{fid}.txt")
        calib = read_calib(out / "training" / "calib" / f"{fid}.txt")
        assert ((labels.rotation_y > -np.pi) & (labels.rotation_y <= 0)).all(), labels.rotation_y
        yaw = labels_to_boxes(labels.objects(), calib)[:, 6]
        assert ((yaw >= -np.pi / 2) & (yaw < np.pi / 2)).all()
        n += len(yaw)
    assert n == summary.kept


def test_two_workers_give_identical_bytes(dataset, house_root, tmp_path):
    out, _ = dataset
    root, house = house_root
    generate(_req(root, house, tmp_path / "two", workers=2))
    assert _tree(tmp_path / "two") == _tree(out)


def test_sigkill_then_resume_is_byte_identical(dataset, house_root, tmp_path):
    out, _ = dataset
    root, house = house_root
    dest = tmp_path / "killed"
    cmd = [sys.executable, "-m", "mpchair.cli", "generate", "--root", str(root), "--house", house.id, "--frames",
           str(FRAMES), "--out", str(dest), "--seed", "11", "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and not list((dest / ".frames").glob("*.json")) and proc.poll() is None:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (dest / "manifest.json").exists() or len(list((dest / ".frames").glob("*.json"))) == FRAMES
    res = subprocess.run(cmd + ["--json"], env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["complete"] and summary["made"] + summary["resumed"] == FRAMES
    assert _tree(dest) == _tree(out)


#: The summary fields that describe the dataset (not the run).
DESCRIBES = ("frames", "complete", "scope", "kept", "kept_by_class", "rejected", "points", "rays", "splits")


def test_shards_fill_one_folder(dataset, house_root, tmp_path):
    out, whole = dataset
    root, house = house_root
    s0 = generate(_req(root, house, tmp_path / "sh", shard=(0, 2)))
    # shard 0 of 2 makes the first contiguous block, frames [0, FRAMES // 2)
    made = sorted(p.stem for p in (tmp_path / "sh" / ".frames").glob("*.json"))
    assert made == [f"{g:06d}" for g in range(FRAMES // 2)] and s0.made == FRAMES // 2
    assert not s0.complete and not (tmp_path / "sh" / "manifest.json").exists()
    s1 = generate(_req(root, house, tmp_path / "sh", shard=(1, 2)))
    assert s1.complete and s1.made == FRAMES - FRAMES // 2
    assert _tree(tmp_path / "sh") == _tree(out)
    # the first shard described its own frames, the last one (which wrote the manifest) the whole dataset
    records = read_manifest(out).frames
    assert s0.scope == "shard" and s0.kept == sum(len(r.kept) for r in records[: FRAMES // 2]) and not s0.splits
    assert "incomplete: other shards pending" in s0.line() and "this shard's frames: boxes kept" in s0.line()
    assert {k: getattr(s1, k) for k in DESCRIBES} == {k: getattr(whole, k) for k in DESCRIBES}


def test_shard_blocks_partition_the_frames_house_by_house():
    for n_total in (1, 3, 7, 200):
        for n in (1, 2, 3, 8, 250):
            blocks = [shard_frames(n_total, (i, n)) for i in range(n)]
            assert [g for b in blocks for g in b] == list(range(n_total))  # every frame once, in order
            assert max(map(len, blocks)) - min(map(len, blocks)) <= 1
    # 4 houses of 50 frames in 4 shards: one house each (a strided split would give every shard all 4 houses)
    assert [shard_frames(200, (i, 4)) for i in range(4)] == [range(0, 50), range(50, 100), range(100, 150),
                                                             range(150, 200)]


def test_a_complete_dataset_is_described_from_its_manifest(dataset, house_root, capsys):
    """Run twice: the second run makes nothing, says so, and reports the same dataset numbers as the first."""
    out, first = dataset
    root, house = house_root
    manifest = read_manifest(out)
    totals = manifest.totals
    assert first.made == FRAMES and not first.nothing_to_make and first.scope == "dataset"
    assert first.kept == totals.boxes_kept > 0 and first.kept_by_class == {"chair": first.kept}
    assert first.rejected == totals.boxes_rejected and first.points == totals.points / FRAMES > 0
    assert first.rays == sum(r.rays for r in manifest.frames) > 0
    before = _files(out)
    args = ["generate", "--root", root, "--house", house.id, "--frames", FRAMES, "--out", out, "--seed", 11, "--quiet"]
    code, text = _cli(capsys, *args, "--json")
    assert code == 0, text
    again = json.loads(text)
    assert again["made"] == 0 and again["resumed"] == FRAMES and again["nothing_to_make"]
    assert {k: again[k] for k in DESCRIBES} == {k: getattr(first, k) for k in DESCRIBES}
    code, line = _cli(capsys, *args)
    assert code == 0, line
    assert line.startswith(f"{out}: {FRAMES} frames (complete); nothing needed to be made ({FRAMES} frames already "
                           f"there); boxes kept {first.kept} (chair {first.kept}), rejected: ")
    assert line.split("; boxes kept ")[1] == first.line().split("; boxes kept ")[1] + "\n"  # same numbers as run 1
    assert _files(out) == before


def _files(path: Path) -> dict[str, bytes]:
    """Every file under ``path`` (temporary ones included), by relative path."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def _cli(capsys, *args) -> tuple[int, str]:
    """``mpchair`` through its console-script entry (InputError -> one ``error:`` line, exit 2): code, stdout+stderr."""
    from mpchair.cli import main

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    captured = capsys.readouterr()
    return e.value.code, captured.out + captured.err


#: Every error docs/generate.md lists ("one line, exit 2, nothing written"): extra CLI arguments and the message.
ERRORS = {
    "unknown house": (["--house", "nope"], r"unknown house 'nope' \(available: {house}\)"),
    "no object of the class": (["--category", "toilet"],
                               r"house {house} has no object of class toilet \(it has: .*chair"),
    "unknown sensor": (["--sensor", "nope"], r"unknown sensor 'nope' \(available: lidar16, lidar64, mp3d-depth90\)"),
    "bad YAML": (["--sensor", "{bad_yaml}"], r"{bad_yaml}.*bogus_key"),
    "too few valid viewpoints": (["--robot-radius", "30", "--max-attempts", "3"],
                                 r"house {house}: found 0 valid viewpoints in 3 attempts"),
    "other settings": (["--seed", "12"], r"made with other settings \(seed differ\)"),
    "split-mode house with fewer than 3 houses": (["--split-mode", "house"],
                                                  r"--split-mode house needs at least 3 houses"),
}


@pytest.mark.parametrize("case", list(ERRORS))
def test_every_documented_error_is_one_line_exit_2_and_writes_nothing(case, house_root, dataset, tmp_path, capsys):
    root, house = house_root
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text((ROOT / "mpchair" / "scan" / "profiles" / "mp3d-depth90.yaml").read_text() + "bogus_key: 1\n")
    extra, pattern = ERRORS[case]
    extra = [a.replace("{bad_yaml}", str(bad_yaml)) for a in extra]
    out = dataset[0] if case == "other settings" else tmp_path / "out"
    before = _files(out) if out.exists() else None
    args = ["generate", "--root", root, "--frames", FRAMES, "--out", out, "--seed", "11", "--quiet"]
    if "--house" not in extra:
        args += ["--house", house.id]
    code, text = _cli(capsys, *args, *extra)
    assert code == 2 and text.startswith("error: ") and text.count("\n") == 1, text
    assert re.search(pattern.format(house=house.id, bad_yaml=re.escape(str(bad_yaml))), text), text
    if before is None:
        assert not out.exists(), sorted(_files(out))
    else:
        assert _files(out) == before


def test_keep_empty_writes_frames_without_boxes_with_one_dontcare_row(house_root, tmp_path, capsys):
    """A sensor file whose filters keep no chair: without --keep-empty no viewpoint is accepted (an error that says
    to use it); with it every frame is written, its label file one DontCare row and its manifest record the
    rejections."""
    root, house = house_root
    strict = tmp_path / "strict.yaml"
    text = (ROOT / "mpchair" / "scan" / "profiles" / "mp3d-depth90.yaml").read_text()
    assert "min_visible_pixels: 35\n" in text
    strict.write_text(text.replace("min_visible_pixels: 35\n", "min_visible_pixels: 100000000\n"))
    args = ["generate", "--root", root, "--house", house.id, "--frames", "2", "--sensor", strict, "--seed", "3",
            "--max-attempts", "5", "--quiet"]
    code, text = _cli(capsys, *args, "--out", tmp_path / "no")
    assert code == 2 and "none keeps a box; use --keep-empty" in text, text
    code, text = _cli(capsys, *args, "--out", tmp_path / "yes", "--keep-empty", "--json")
    assert code == 0, text
    summary = json.loads(text)
    assert summary["complete"] and summary["frames"] == 2 and summary["kept"] == 0
    manifest = read_manifest(tmp_path / "yes")
    assert len(manifest.frames) == 2
    for rec in manifest.frames:
        fid = rec.frame
        assert rec.kept == () and rec.rejected and rec.views_tried == 1  # the first valid view is taken
        labels = read_labels(tmp_path / "yes" / "training" / "label_2" / f"{fid}.txt")
        assert list(labels.names) == ["DontCare"] and len(labels.objects()) == 0
        assert len(read_velodyne(tmp_path / "yes" / "training" / "velodyne" / f"{fid}.bin")) == rec.points > 1000
    # every candidate failed on the visible pixels the strict profile asks for (or on a cheaper filter before it)
    reasons = {r.reason for rec in manifest.frames for r in rec.rejected}
    assert "visible_pixels" in reasons and reasons <= {"height", "distance", "fov", "visible_pixels"}


def test_split_modes_end_to_end(house_root, tmp_path, capsys):
    """--split-mode reaches ImageSets: ``paper`` on one house (first half of its frames = the train/val pool, split
    at 2/3; second half = test) and ``house`` on three houses (no house in two splits)."""
    root, house = house_root
    code, text = _cli(capsys, "generate", "--root", root, "--house", house.id, "--frames", "6", "--out",
                      tmp_path / "paper", "--split-mode", "paper", "--seed", "1", "--quiet")
    assert code == 0, text
    sets = {s: read_imageset(tmp_path / "paper" / "ImageSets" / f"{s}.txt") for s in ("train", "val", "test")}
    assert sets == {"train": ["000000", "000001"], "val": ["000002"], "test": ["000003", "000004", "000005"]}

    three = tmp_path / "three"
    for h in (house, synthesize_house(17, levels=1), synthesize_house(27, levels=1)):
        write_house(three, h)
    ids = sorted(p.name for p in (three / "v1" / "scans").iterdir())
    assert len(ids) == 3
    code, text = _cli(capsys, "generate", "--root", three, *sum((["--house", h] for h in ids), []), "--frames", "1",
                      "--out", tmp_path / "house", "--split-mode", "house", "--seed", "4", "--quiet")
    assert code == 0, text
    house_of = {rec.frame: rec.house for rec in read_manifest(tmp_path / "house").frames}
    got = {s: read_imageset(tmp_path / "house" / "ImageSets" / f"{s}.txt") for s in ("train", "val", "test")}
    expect = split_frames(3, 1, "house", seed=4)
    assert got == {s: [f"{i:06d}" for i in expect[s]] for s in got}
    houses = [{house_of[f] for f in got[s]} for s in ("train", "val", "test")]
    assert sum(map(len, houses)) == 3 and set().union(*houses) == set(ids)
    manifest = read_manifest(tmp_path / "house")
    assert {s: set(v) for s, v in manifest.split_houses.items()} == dict(zip(("train", "val", "test"), houses))

    # chosen houses: --val-house / --test-house imply house mode; the manifest and its command record the choice
    code, text = _cli(capsys, "generate", "--root", three, *sum((["--house", h] for h in ids), []), "--frames", "1",
                      "--out", tmp_path / "chosen", "--val-house", ids[0], "--test-house", ids[2], "--quiet")
    assert code == 0, text
    manifest = read_manifest(tmp_path / "chosen")
    assert manifest.split_houses == {"train": [ids[1]], "val": [ids[0]], "test": [ids[2]]}
    assert manifest.config["split_mode"] == "house" and manifest.config["val_houses"] == [ids[0]]
    assert ("--val-house", ids[0]) == tuple(manifest.command[manifest.command.index("--val-house"):][:2])
    got = {s: read_imageset(tmp_path / "chosen" / "ImageSets" / f"{s}.txt") for s in ("train", "val", "test")}
    assert got == {"train": ["000001"], "val": ["000000"], "test": ["000002"]}
    assert "split_houses" not in json.loads((tmp_path / "paper" / "manifest.json").read_text())  # other modes as before
    for extra, message in ((["--val-house", ids[0], "--test-house", ids[0]], "both splits"),
                           (["--val-house", "nope", "--test-house", ids[0]], "not one of the --house ids"),
                           (["--val-house", ids[0], "--test-house", ids[1], "--split-mode", "frame"],
                            "need --split-mode house"),
                           (["--val-house", ids[0]], "at least one house for each")):
        code, text = _cli(capsys, "generate", "--root", three, *sum((["--house", h] for h in ids), []), "--frames",
                          "1", "--out", tmp_path / "bad", *extra, "--quiet")
        assert code != 0 and message in text and "Traceback" not in text, text
        assert not (tmp_path / "bad" / "training").exists()


def test_open3d_backend_gives_the_embree_dataset(dataset, house_root, tmp_path):
    """``--backend open3d`` end to end: the same viewpoints, labels and calibration as Embree, and scans equal up to
    the two ray casters' float differences (docs/generate.md: 1e-4 m)."""
    pytest.importorskip("open3d", reason="the project's open3d extra is not installed")
    out, _ = dataset
    root, house = house_root
    generate(_req(root, house, tmp_path / "o3d", workers=1, backend="open3d"))
    theirs, ours = _files(tmp_path / "o3d"), _files(out)
    assert theirs.keys() == ours.keys()
    for name in ours:
        if "/label_2/" in name or "/calib/" in name or name.startswith("ImageSets"):
            assert theirs[name] == ours[name], name
        elif "/pose/" in name:  # the same viewpoint; its height comes from a floor hit (measured 4e-6 m apart)
            a, b = (np.array(t.split(), dtype=np.float64) for t in (theirs[name], ours[name]))
            np.testing.assert_allclose(a, b, atol=1e-4, rtol=0)
        elif "/velodyne/" in name:
            a = np.frombuffer(theirs[name], dtype=np.float32).reshape(-1, 4)
            b = np.frombuffer(ours[name], dtype=np.float32).reshape(-1, 4)
            assert a.shape == b.shape, name
            np.testing.assert_allclose(a, b, atol=1e-4, rtol=0)
            # ... but not the same bits: Open3D really cast them (measured: ~30k of ~80k values differ by ~1e-6 m)
            assert (a != b).any(), name
    settings = json.loads(theirs[".generate.json"])
    assert settings["backend"] == "open3d" and json.loads(ours[".generate.json"])["backend"] == "embree"


def test_split_modes():
    s = split_frames(4, 3750, "paper", seed=0)
    assert len(s["train"]) == 5000 and len(s["val"]) == 2500 and len(s["test"]) == 7500
    assert s["val"][0] == 2 * 3750 + 1250 and max(s["train"]) < min(s["val"])  # the original: index >= 5000
    assert all(i % 3750 >= 1875 for i in s["test"])
    f = split_frames(2, 50, "frame", seed=1)
    assert sorted(f["train"] + f["val"] + f["test"]) == list(range(100)) and len(f["train"]) == 60
    assert f == split_frames(2, 50, "frame", seed=1) and f != split_frames(2, 50, "frame", seed=2)
    h = split_frames(5, 10, "house", seed=0)
    houses = [{i // 10 for i in h[k]} for k in ("train", "val", "test")]
    assert not (houses[0] & houses[1]) and not (houses[0] & houses[2]) and sum(map(len, houses)) == 5
    with pytest.raises(InputError, match="at least 3 houses"):
        split_frames(2, 10, "house", seed=0)


def test_manifest_holds_the_frame_records_whatever_the_root_is_named(dataset, house_root, tmp_path):
    out, _ = dataset
    manifest = json.loads((out / "manifest.json").read_text())
    records = [json.loads((out / ".frames" / f"{g:06d}.json").read_text()) for g in range(FRAMES)]
    assert manifest["frames"] == records
    # A root named like the manifest's internal placeholder still gives the same records (the slow encoder path).
    root, house = house_root
    odd = tmp_path / "@@frame records@@"
    odd.symlink_to(root, target_is_directory=True)
    generate(_req(odd, house, tmp_path / "odd", workers=1))
    again = json.loads((tmp_path / "odd" / "manifest.json").read_text())
    assert again["frames"] == records and "@@frame records@@" in again["command"]


def test_the_manifest_names_its_viewpoint_settings_and_reads_without_its_frames(dataset, tmp_path):
    """The sensor height and robot radius come from the run's settings (what the report quotes; they agree with the
    command line the manifest records), and a copy without its per-frame list (a run record's) reads with
    ``frames=False`` as the same manifest less its frames; the full reader still requires them."""
    out, _ = dataset
    manifest = read_manifest(out)
    command = list(manifest.command)
    assert manifest.sensor_height == float(command[command.index("--height") + 1]) == GenerateRequest.height
    assert manifest.robot_radius == float(command[command.index("--robot-radius") + 1])
    data = json.loads((out / "manifest.json").read_text())
    data["frames_left_out_of_the_record"] = len(data.pop("frames"))
    (tmp_path / "manifest.json").write_text(json.dumps(data))
    head = read_manifest(tmp_path, frames=False)
    assert head == dataclasses.replace(manifest, frames=()) and manifest.frames
    with pytest.raises(InputError, match="manifest.json: not an mpchair manifest: missing key 'frames'"):
        read_manifest(tmp_path)


def test_records_read_back_to_the_bytes_written(dataset, tmp_path):
    """The typed records are the files: every ``.frames`` record and the manifest read back (FrameRecord, Manifest)
    encode to the very bytes ``generate`` wrote, the manifest's frames are the frame records, and a file that is not
    a record is an InputError naming it."""
    out, _ = dataset
    text = (out / "manifest.json").read_text()
    manifest = read_manifest(out)
    assert isinstance(manifest, Manifest) and manifest.to_json() + "\n" == text
    assert Manifest.from_dict(json.loads(text)) == manifest
    for g, rec in enumerate(manifest.frames):
        path = out / ".frames" / f"{g:06d}.json"
        assert isinstance(rec, FrameRecord) and read_frame_record(path) == rec
        assert rec.to_json() + "\n" == path.read_text() and f"\n  {rec.to_json()}" in text  # one line per record
    assert read_manifest(tmp_path) is None  # no manifest.json (real KITTI)
    bad = tmp_path / "bad"
    bad.mkdir()
    data = json.loads(text)
    del data["frames"][1]["pose"]
    (bad / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"manifest.json: not an mpchair manifest: frames\[1\]: missing key 'pose'"):
        read_manifest(bad)
    (bad / "manifest.json").write_text("[1]")
    with pytest.raises(InputError, match="manifest.json: expected a JSON object"):
        read_manifest(bad)
    (bad / "r.json").write_text('{"frame": "000000"}')
    with pytest.raises(InputError, match="r.json: not an mpchair frame record: missing key"):
        read_frame_record(bad / "r.json")
