"""The small inputs the recording tests (Rerun, MCAP) read: a stream (2 episodes of 6 frames at 1 Hz) and a 3-frame
dataset of one synthetic house; and a two-frame stream folder made without raycasting (:func:`small_stream`)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from mpchair.dataset.generate import GenerateRequest, generate
from mpchair.kitti import write_poses, write_times
from mpchair.stream import StreamRequest, stream
from mpchair.synth import synthesize_house, write_house


def make_recording_inputs(base: Path) -> Path:
    """``base/stream`` and ``base/dataset`` (and the house under ``base/houses``); returns ``base``."""
    house = synthesize_house(7, levels=1)
    write_house(base / "houses", house)
    stream(StreamRequest(root=base / "houses", houses=(house.id,), episodes=2, out=base / "stream", rate=1.0,
                         duration=5.0, look_around=False, min_geodesic=3.0, seed=2, progress=False))
    generate(GenerateRequest(root=base / "houses", houses=(house.id,), frames=3, out=base / "dataset", seed=2,
                             progress=False))
    return base


KITTI = Path(__file__).resolve().parent / "data" / "kitti" / "training"


def small_stream(root: Path, rate: object = 10.0) -> Path:
    """A two-frame stream folder (the vendored KITTI frames 000000 and 000001 as sequence 00 of a still sensor, their
    cars labelled ``Chair`` so that the oracle has boxes) whose ``stream.json`` declares ``rate`` (written as given:
    NaN too); every stream reader gets through it, in a second, without raycasting a house."""
    seq = root / "sequences" / "00"
    for sub, ext in (("velodyne", "bin"), ("label_2", "txt"), ("calib", "txt")):
        (seq / sub).mkdir(parents=True)
        for fid in ("000000", "000001"):
            shutil.copy(KITTI / sub / f"{fid}.{ext}", seq / sub / f"{fid}.{ext}")
    (seq / "label_dontcare").mkdir()
    for fid in ("000000", "000001"):
        label = seq / "label_2" / f"{fid}.txt"
        label.write_text(label.read_text().replace("Car ", "Chair "))
        (seq / "label_dontcare" / f"{fid}.txt").write_text("")
    write_times(seq / "times.txt", np.array([0, 100_000]))
    write_poses(seq / "poses.txt", np.stack([np.eye(4), np.eye(4)]))
    meta = {"rate_hz": rate, "region": {"max_abs_dz": 1.5, "max_distance": 10.0, "half_fov": 0.78},
            "image_size": [1242, 375], "sequences": {"00": {}}}
    (root / "stream.json").write_text(json.dumps(meta))
    return root
