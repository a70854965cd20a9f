"""Streaming evaluation (sAP) of a detector on a moving robot's stream (``mpchair stream`` output).

``data`` reads a stream folder (times as integer microseconds, poses, labels), ``outputs`` gives every frame's offline
output (a model, result files or the ground-truth oracle) and a model's measured runtime, ``schedule`` the
single-worker (or unbounded) schedule in virtual time and which output each query frame sees, ``score`` the boxes each
query is scored with (``raw`` / ``ego``) and the pooled KITTI evaluation, ``run`` the whole ``detector stream-eval``.
See ``docs/streaming.md``.
"""

from detector.stream.data import Stream, read_stream
from detector.stream.run import Prepared, Source, prepare, score

__all__ = ["Prepared", "Source", "Stream", "prepare", "read_stream", "score"]
