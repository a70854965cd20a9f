"""``detector stream-eval --rerun``: the stream's recording (:func:`mpchair.recording.rerun.log_stream`) plus, at every
frame, the boxes the detector had at that moment: ``detections/raw`` as emitted (stale, read in the current sensor
frame) and ``detections/ego`` moved by the robot's motion since their input frame."""

from __future__ import annotations

from pathlib import Path

from detector.stream.run import Prepared, query_sources
from detector.stream.score import moved_boxes
from mpchair.recording.rerun import BLUE, RED, Recorder, log_stream


def log_stream_eval(prep: Prepared, out: str | Path) -> dict:
    """Write ``prep``'s stream with the detector's boxes as the recording ``out``; returns the frame counts."""
    sources = query_sources(prep)
    index = {seq.name: s for s, seq in enumerate(prep.stream.sequences)}

    def detections(rec: Recorder, sensor: str, seq_name: str, i: int) -> None:
        s = index[seq_name]
        k = int(sources[s][i])
        out = prep.outputs[s][k] if k >= 0 else None
        raw = out.boxes if out is not None else None
        seq = prep.stream.sequences[s]
        ego = moved_boxes(out.boxes, seq.poses[k], seq.poses[i]) if out is not None and len(out.boxes) else raw
        labels = None if out is None else [f"{n} {sc:.2f}" for n, sc in zip(out.names, out.scores)]
        rec.boxes(f"{sensor}/detections/raw", raw if raw is not None else [], RED, labels)
        rec.boxes(f"{sensor}/detections/ego", ego if ego is not None else [], BLUE, labels)

    return log_stream(prep.stream.root, out, extra=detections)
