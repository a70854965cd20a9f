"""The streaming reproduction's scales and sweep: one stream per (robot speed m/s, sensor rate Hz) point, the speeds
at 10 Hz and the rates at 0.5 m/s around the headline stream."""

from __future__ import annotations

import dataclasses
from pathlib import Path

MODELS = ("dense", "sparse")
MODES = ("raw", "ego")
HEADLINE = (0.5, 10.0)  # m/s, Hz


@dataclasses.dataclass(frozen=True)
class Scale:
    """Sizes of one scale: houses (None = all), episodes per house, episode cap (s), latency repeats and warm-up."""

    houses: int | None
    episodes: int
    duration: float
    repeats: int
    warmup: int


SCALES = {
    "small": Scale(houses=2, episodes=1, duration=8.0, repeats=1, warmup=2),
    # every reproduction house, one 20 s episode each (look-around included): ~1,600 frames at 10 Hz per stream;
    # about 45 min on 2 idle AVX2 cores, most of it the dense model's measured latencies (2 repeats per frame)
    "full": Scale(houses=None, episodes=1, duration=20.0, repeats=2, warmup=10),
}


def stream_name(speed: float, rate: float) -> str:
    """Folder name of the stream of one (speed m/s, rate Hz) point."""
    return f"v{speed:g}-f{rate:g}"


def sweep_points(speeds: list[float], rates: list[float]) -> list[tuple[float, float]]:
    """Every (speed, rate) needed, headline first: the speeds at 10 Hz and the rates at 0.5 m/s."""
    pts = [HEADLINE] + [(v, HEADLINE[1]) for v in speeds] + [(HEADLINE[0], f) for f in rates]
    return list(dict.fromkeys(pts))


# --- the work folder: streams/<stream>/, eval/<stream>/<model or oracle-at-model>/ ------------------------------------
def stream_dir(out: Path, speed: float, rate: float) -> Path:
    """The stream of one (speed m/s, rate Hz) point in work folder ``out`` (``mpchair stream --out``)."""
    return out / "streams" / stream_name(speed, rate)


def eval_dir(out: Path, speed: float, rate: float, who: str) -> Path:
    """The stream-eval outputs of ``who`` (a model, or ``oracle-at-<model>``) on one point's stream."""
    return out / "eval" / stream_name(speed, rate) / who
