"""Offline detector outputs on every frame of a stream, and the runtime of a real model on a frame.

An :class:`Output` holds one frame's detections in *that frame's* sensor frame (x forward, y left, z up, metres).
Three sources: ``--oracle`` (the frame's own labels, score 1: a perfect detector), ``--results RDIR`` (16-column
KITTI result files ``RDIR/NN/NNNNNN.txt``, any detector's, in the ``detector eval`` format; frames the schedule does
not process may lack a file) and a trained model
(:class:`ModelRunner`, which also measures latency end to end: from the in-memory point array to the final boxes —
range filter, pillars, backbone, head, decoding and NMS —, the median of ``repeats`` runs, after warm-up runs, with a
device synchronise on CUDA).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from detector.stream.data import Stream, StreamSequence
from mpchair.core.errors import InputError
from mpchair.geometry import fov_mask, labels_to_boxes
from mpchair.kitti import Calib, Labels


@dataclasses.dataclass(frozen=True, eq=False)
class Output:
    """One frame's detections: ``boxes`` (M,7) float64 in that frame's sensor frame, ``scores`` (M,), ``names`` (M,)."""

    boxes: np.ndarray
    scores: np.ndarray
    names: np.ndarray

    @classmethod
    def empty(cls) -> Output:
        """No detections."""
        return cls(np.zeros((0, 7)), np.zeros(0), np.zeros(0, dtype=str))


def labels_to_output(labels: Labels, calib: Calib, classes: Sequence[str]) -> Output:
    """The rows of ``labels`` whose type is one of ``classes`` (case-insensitive) as an :class:`Output`; rows without
    a score (ground truth) get score 1."""
    wanted = {c.lower() for c in classes}
    rows = labels[np.array([n.lower() in wanted for n in labels.names], dtype=bool)] if len(labels) else labels
    if len(rows) == 0:
        return Output.empty()
    scores = np.ones(len(rows)) if rows.score is None else np.asarray(rows.score, dtype=np.float64)
    return Output(labels_to_boxes(rows, calib), scores, np.asarray(rows.names, dtype=str))


def oracle_outputs(stream: Stream, classes: Sequence[str]) -> list[list[Output]]:
    """Per sequence and frame: the frame's own labelled objects of ``classes`` with score 1."""
    return [[labels_to_output(seq.labels(i), seq.calib(i), classes) for i in range(len(seq))]
            for seq in stream.sequences]


def result_outputs(stream: Stream, results: str | Path, classes: Sequence[str]) -> list[list[Output | None]]:
    """Per sequence and frame: ``RESULTS/NN/NNNNNN.txt`` (16 columns; an empty file = no detections; a missing file =
    a frame the detector never ran on, ``None``: allowed only for frames the schedule does not process)."""
    from detector.eval import read_results

    results = Path(results)
    if not results.is_dir():
        raise InputError("result folder not found", results)
    out: list[list[Output | None]] = []
    for seq in stream.sequences:
        row: list[Output | None] = []
        for i in range(len(seq)):
            path = results / seq.name / f"{i:06d}.txt"
            row.append(labels_to_output(read_results(path), seq.calib(i), classes) if path.is_file() else None)
        out.append(row)
    if not any(o is not None for row in out for o in row):
        raise InputError(f"no result file of this stream (expected {results}/NN/NNNNNN.txt)", results)
    return out


class ModelRunner:
    """A trained model (``config`` + ``checkpoint``) run on stream frames, one at a time (batch 1, eval mode)."""

    def __init__(self, config: str | Path, checkpoint: str | Path, device: str = "cpu", threads: int | None = None):
        from detector.checkpoint import load_model
        from detector.config import load_experiment
        from detector.data.experiment import augment_options
        from detector.device import use_device

        self.device = use_device(device, threads)
        self.cfg = load_experiment(config)
        self.model = load_model(self.cfg, checkpoint, self.device)
        self.options = augment_options(self.cfg)
        self.classes = tuple(self.cfg.eval.classes)

    def frame(self, stream: Stream, seq: StreamSequence, i: int):
        """Frame ``i`` of ``seq`` as a :class:`detector.data.Frame` (scan cropped to the camera's view if the config
        asks for it; no labels)."""
        from detector.data.kitti_dataset import load_frame

        frame = load_frame(stream.root / "sequences", f"{i:06d}", classes=self.cfg.data.classes, fov_crop=False,
                           split_dir=seq.name, with_labels=False)
        if self.cfg.data.fov_crop:
            frame = dataclasses.replace(frame, points=frame.points[fov_mask(frame.points, frame.calib,
                                                                            stream.meta.image_size)])
        return frame

    def run(self, frame) -> Output:
        """The model's detections of the eval classes on one frame (from its in-memory scan to the final boxes)."""
        import torch

        from detector.data.pipeline import make_eval_sample

        pts = make_eval_sample(frame, self.options).points
        with torch.no_grad():
            det = self.model.predict([torch.from_numpy(pts).to(self.device)])[0]
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
        boxes = det.boxes.detach().cpu().to(torch.float64).numpy().reshape(-1, 7)
        scores = det.scores.detach().cpu().to(torch.float64).numpy().reshape(-1)
        names = np.array([self.cfg.data.classes[int(k)] for k in det.labels.cpu().numpy().reshape(-1)], dtype=str)
        keep = np.isin(names, self.classes)
        return Output(boxes[keep], scores[keep], names[keep])

    def measure(self, frame, repeats: int = 3) -> tuple[Output, int]:
        """``(output, latency)``: :meth:`run` ``repeats`` times on ``frame``; the latency is the median wall time in
        integer microseconds, the output the first run's (inference is deterministic)."""
        times, out = [], None
        for _ in range(repeats):
            t0 = time.perf_counter()
            result = self.run(frame)
            times.append(time.perf_counter() - t0)
            if out is None:
                out = result
        return out, int(round(float(np.median(times)) * 1e6))
