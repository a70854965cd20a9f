"""Streams: a robot driving through a house, scanning at a fixed rate, every frame labelled like ``generate``'s.

``freespace`` (where a robot can stand: a 5 cm grid per level), ``routes`` (start/goal sampling, clearance-weighted
shortest paths, shortcutting), ``unicycle`` (the drive under speed / turn / acceleration limits), ``episodes`` (route
+ drive + capture times and poses), ``writer`` (KITTI-odometry-style sequence folders) and ``run`` (the
``mpchair stream`` orchestration: planning, frames, resume, ``stream.json``). See ``docs/streaming.md``.
"""

from mpchair.stream.run import StreamRequest, StreamSummary, stream

__all__ = ["StreamRequest", "StreamSummary", "stream"]
