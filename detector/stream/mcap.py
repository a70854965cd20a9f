"""``detector stream-eval --mcap``: the stream's ROS 2 bag (:func:`mpchair.recording.mcap.log_stream`) plus, at every
frame, the boxes the detector had at that moment, in frame ``sensor`` and stamped with that frame's capture time:
``/detections/<model>`` as emitted (stale: computed from an earlier frame, read in the current one) and
``/detections/<model>/ego`` moved by the robot's motion since their input frame (what ``--mode ego`` scores), each a
vision_msgs/Detection3DArray with a visualization_msgs/MarkerArray beside it (``.../markers``). A frame before the
first output gets empty arrays, so every topic has one message per frame."""

from __future__ import annotations

import re
from pathlib import Path

from detector.stream.outputs import Output
from detector.stream.run import Prepared, Source, query_sources
from detector.stream.score import moved_boxes
from mpchair.recording.mcap import Bag, log_stream, write_boxes

RAW_COLOR, EGO_COLOR = (230, 60, 50), (60, 120, 240)


def model_name(source: Source) -> str:
    """The ``<model>`` of the detection topics: a model's config file name (``mpchair_sparse_cpu``), ``results`` or
    ``oracle``, as a ROS 2 name token (letters, digits and single underscores; never a leading digit)."""
    name = Path(source.config).stem if source.kind == "model" and source.config else source.kind
    token = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", name)).strip("_") or "model"
    return f"m{token}" if token[0].isdigit() else token


def log_stream_eval(prep: Prepared, out: str | Path) -> dict:
    """Write ``prep``'s stream with the detector's boxes as the bag ``out``; returns what
    :func:`~mpchair.recording.mcap.log_stream` returns, plus ``"model"`` (the topics' ``<model>``)."""
    sources = query_sources(prep)
    index = {seq.name: s for s, seq in enumerate(prep.stream.sequences)}
    topic = f"/detections/{model_name(prep.source)}"

    def detections(bag: Bag, seq_name: str, i: int, time_us: int) -> None:
        s = index[seq_name]
        k = int(sources[s][i])
        out = prep.outputs[s][k] if k >= 0 else None
        if out is None:  # no output emitted yet: empty arrays clear the viewer's boxes
            out = Output.empty()
        seq = prep.stream.sequences[s]
        ego = moved_boxes(out.boxes, seq.poses[k], seq.poses[i]) if len(out.boxes) else out.boxes
        names, scores = [str(n) for n in out.names], [float(v) for v in out.scores]
        texts = [f"{n} {v:.2f}" for n, v in zip(names, scores)]
        write_boxes(bag, topic, out.boxes, names, scores, [RAW_COLOR] * len(names), texts, time_us)
        write_boxes(bag, f"{topic}/ego", ego, names, scores, [EGO_COLOR] * len(names), texts, time_us)

    return {**log_stream(prep.stream.root, out, extra=detections), "model": topic.rpartition("/")[2]}
