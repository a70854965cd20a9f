"""The streaming reproduction's scales, settings and sweep: one stream per (robot speed m/s, sensor rate Hz) point, the
speeds at 10 Hz and the rates at 0.5 m/s around the headline stream; each model measured under one or more settings
(pseudo-image grid x torch-thread budget) on the headline stream, under the headline setting on the others."""

from __future__ import annotations

import dataclasses
from pathlib import Path

MODELS = ("dense", "sparse")
MODES = ("raw", "ego")
HEADLINE = (0.5, 10.0)  # m/s, Hz
#: The pseudo-image grids a model can be measured at: the paper's 768 x 512 (the whole scan; the trained weights are
#: convolutional, so the CPU-trained checkpoints load into it, as in make reproduce's runtime tables) and the
#: CPU-sized 288 x 144 crop the models were trained on. Value: the config file of model ``{m}``.
GRIDS = {"768x512": "mpchair_{m}.yaml", "288x144": "mpchair_{m}_cpu.yaml"}
#: The thread budgets measured (a robot shares its CPU; the paper's conclusion is "1 Hz with more than 75 % of the
#: CPU left"), the first one the sweeps'.
THREADS = (2, 1)


@dataclasses.dataclass(frozen=True)
class Setting:
    """What a latency is measured under: the pseudo-image ``grid`` (a key of :data:`GRIDS`) and torch ``threads``."""

    grid: str
    threads: int

    @property
    def name(self) -> str:
        """Folder name: ``768x512-t2``."""
        return f"{self.grid}-t{self.threads}"

    @property
    def text(self) -> str:
        """``768 x 512, 2 threads``."""
        return f"{self.grid.replace('x', ' x ')}, {self.threads} thread{'s' * (self.threads != 1)}"


def settings(grids: list[str], threads: list[int]) -> list[Setting]:
    """Every (grid, threads) setting, the headline one first (the first grid at the first thread budget)."""
    return [Setting(g, t) for g in grids for t in threads]


@dataclasses.dataclass(frozen=True)
class Scale:
    """Sizes of one scale: held-out houses synthesized for the streams, episodes per house, episode cap (s), latency
    repeats on the headline stream and on the sweep's other streams, warm-up runs, and the episode resamples of the
    gaps step's intervals."""

    heldout_houses: int
    episodes: int
    duration: float
    repeats: int
    sweep_repeats: int
    warmup: int
    gap_resamples: int = 200


SCALES = {
    "small": Scale(heldout_houses=1, episodes=1, duration=8.0, repeats=1, sweep_repeats=1, warmup=2, gap_resamples=20),
    # the protocol's 5 episodes per house (12 s each, look-around included: ~1,200 frames at 10 Hz on 2 houses) and
    # median of 3 repeats on the headline stream; the sweep's other streams time 1 run per processed frame (a model
    # that cannot keep up is busy for the whole stream on every repeat: docs/streaming.md, "Departures"). 12 s, not
    # 20: a dense model that cannot keep up computes for the whole stream, so the run costs about the streams' total
    # duration per setting and repeat, and it must fit the session of make reproduce (whose models it streams)
    "full": Scale(heldout_houses=2, episodes=5, duration=12.0, repeats=3, sweep_repeats=1, warmup=10),
}


def stream_name(speed: float, rate: float) -> str:
    """Folder name of the stream of one (speed m/s, rate Hz) point."""
    return f"v{speed:g}-f{rate:g}"


def sweep_points(speeds: list[float], rates: list[float]) -> list[tuple[float, float]]:
    """Every (speed, rate) needed, headline first: the speeds at 10 Hz and the rates at 0.5 m/s."""
    pts = [HEADLINE] + [(v, HEADLINE[1]) for v in speeds] + [(HEADLINE[0], f) for f in rates]
    return list(dict.fromkeys(pts))


# --- the work folder: streams/<stream>/, eval/<stream>/<setting>/<model or oracle-at-model>/ --------------------------
def stream_dir(out: Path, speed: float, rate: float) -> Path:
    """The stream of one (speed m/s, rate Hz) point in work folder ``out`` (``mpchair stream --out``)."""
    return out / "streams" / stream_name(speed, rate)


def eval_dir(out: Path, speed: float, rate: float, setting: Setting, who: str) -> Path:
    """The stream-eval outputs of ``who`` (a model, or ``oracle-at-<model>``) measured under ``setting`` on one
    point's stream."""
    return out / "eval" / stream_name(speed, rate) / setting.name / who
