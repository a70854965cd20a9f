"""The small inputs the recording tests (Rerun, MCAP) read: a stream (2 episodes of 6 frames at 1 Hz) and a 3-frame
dataset of one synthetic house."""

from __future__ import annotations

from pathlib import Path

from mpchair.dataset.generate import GenerateRequest, generate
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
