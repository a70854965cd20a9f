"""The sparse - dense sAP gap on the headline stream with a 95 % interval over episodes (the ``gaps`` step).

sAP pools every query frame of every episode; consecutive frames of one episode see the same chairs from nearly the
same place, so frames are not independent draws and a frame bootstrap would give too narrow an interval. Here each
resample draws whole episodes (the stream's sequences) with replacement, the same episodes for both models (paired),
and the gap is sAP(sparse) - sAP(dense) on the pooled frames of that resample (:func:`detector.eval.bootstrap
.bootstrap_gap` with ``groups``). The scored frames are rebuilt exactly as the score step scores them: each model's
saved outputs replayed with its measured latency log (:func:`detector.stream.run.prepare`), so the gap on the whole
stream is the difference of the two ``raw.json`` / ``ego.json`` sAPs.

Writes ``eval/<headline stream>/<setting>/gap.json`` per setting: ``{"format", "metric", "resamples", "episodes",
"frames", "raw": GapEstimate, "ego": GapEstimate}`` (AP in percent, R40, Chair, IoU 0.5).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from detector.eval.bootstrap import GapEstimate
from mpchair.core.atomic import write_text
from mpchair.core.errors import InputError
from mpchair.core.text import load_json
from reproduction.stream.sweep import HEADLINE, MODES, Setting, eval_dir, stream_dir

GAP_FORMAT = "mpchair-stream-gap/1"
#: Episode resamples per interval (each one evaluates both models on the resampled frames).
RESAMPLES = 200
#: The metric the interval is of (3D, R40: the headline metric of the streaming tables).
METRIC = "3d"


@dataclass(frozen=True)
class StreamGap:
    """One setting's sparse - dense sAP gaps by mode (``raw``, ``ego``), the metric, resamples and episodes."""

    gaps: dict[str, GapEstimate]
    metric: str
    resamples: int
    episodes: int
    frames: int

    def to_json(self) -> dict:
        return {"format": GAP_FORMAT, "metric": self.metric, "resamples": self.resamples, "episodes": self.episodes,
                "frames": self.frames, **{m: g.to_json() for m, g in self.gaps.items()}}

    @classmethod
    def from_json(cls, d: dict, where: Path) -> StreamGap:
        """The gaps of :meth:`to_json`'s data; a file of another format is an :class:`InputError` naming ``where``."""
        try:
            if d.get("format") != GAP_FORMAT:
                raise ValueError(f"format {d.get('format')!r}")
            return cls(gaps={m: GapEstimate.from_json(d[m]) for m in MODES if m in d}, metric=str(d["metric"]),
                       resamples=int(d["resamples"]), episodes=int(d["episodes"]), frames=int(d["frames"]))
        except (AttributeError, KeyError, TypeError, ValueError, IndexError) as e:
            raise InputError(f"not a stream gap file ({GAP_FORMAT}): {e}", where) from None


def gap_path(out: Path, setting: Setting) -> Path:
    """Where the gaps of ``setting`` on the headline stream are written in work folder ``out``."""
    return eval_dir(out, *HEADLINE, setting, "gap.json")


def read_gap(path: Path) -> StreamGap | None:
    """The gap file at ``path``, None when absent."""
    if not path.is_file():
        return None
    return StreamGap.from_json(load_json(path, "stream gap file"), path)


def episode_groups(lengths: list[int]) -> list[list[int]]:
    """The pooled frame indices of each episode, from the episodes' frame counts in stream order."""
    groups, start = [], 0
    for n in lengths:
        groups.append(list(range(start, start + n)))
        start += n
    return groups


def _scored(stream, outputs: Path, latency_log: Path, modes: tuple[str, ...]):
    """(ground truth per pooled frame, {mode: the result rows each frame is scored with}) of one model's saved
    outputs replayed with its measured latencies (what ``detector stream-eval --results --latency`` scores)."""
    from detector.stream.run import Source, prepare, query_labels, query_sources, read_latency_log

    prep = prepare(stream, Source("results", results=str(outputs)), latency_log=read_latency_log(latency_log))
    sources = query_sources(prep)
    return [g for row in prep.gts for g in row], {m: query_labels(prep, m, sources) for m in modes}


def stream_gap(out: Path, setting: Setting, *, resamples: int = RESAMPLES, metric: str = METRIC,
               seed: int = 0) -> StreamGap:
    """The sparse - dense gaps of ``setting`` on the headline stream of work folder ``out`` (module docstring)."""
    from detector.eval.bootstrap import bootstrap_gap, kitti_ap
    from detector.stream.data import read_stream

    stream = read_stream(stream_dir(out, *HEADLINE))
    gt, scored = None, {}
    for m in ("dense", "sparse"):
        ev = eval_dir(out, *HEADLINE, setting, m)
        gt, scored[m] = _scored(stream, ev / "outputs", ev / "latency.json", MODES)
    groups = episode_groups([len(s) for s in stream.sequences])
    ap = kitti_ap("Chair", metric)
    gaps = {mode: bootstrap_gap(gt, [scored["dense"][mode]], [scored["sparse"][mode]], ap, resamples=resamples,
                                seed=seed, groups=groups) for mode in MODES}
    return StreamGap(gaps=gaps, metric=metric, resamples=resamples, episodes=len(groups), frames=len(gt))


def write_gap(out: Path, setting: Setting, gap: StreamGap) -> Path:
    """Write ``gap`` where :func:`gap_path` says; the path."""
    path = gap_path(out, setting)
    write_text(path, json.dumps(gap.to_json(), indent=1) + "\n")
    return path
