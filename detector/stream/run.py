"""``detector stream-eval`` as a library call: offline outputs + latencies → schedule → sAP (``docs/streaming.md``).

:func:`prepare` does everything that does not depend on the scoring mode: the offline output of every frame (model,
result files or oracle), the latencies (measured on this machine, or a constant) and each sequence's schedule.
:func:`score` then scores a mode (``ego`` / ``raw``) and returns the JSON-ready summary, so one measurement serves
both modes. With a constant latency everything is a pure function of the inputs (same stream, same bytes).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from detector.stream.data import Stream
from detector.stream.outputs import ModelRunner, Output, oracle_outputs, result_outputs
from detector.stream.schedule import Schedule, latest_outputs, single_worker, unbounded_workers
from detector.stream.score import MODES, ap_ceiling, evaluate_overall, query_results
from mpchair.core.atomic import check_writable
from mpchair.core.errors import InputError
from mpchair.core.owned import check_replaceable, clear_leftovers, replace_folder, work_dir
from mpchair.geometry import labels_to_boxes
from mpchair.kitti import Calib, Labels

SCHEDULES: tuple[str, ...] = ("single", "unbounded")
#: Class evaluated when no model config names the classes (oracle, result files).
DEFAULT_CLASSES: tuple[str, ...] = ("Chair",)


@dataclasses.dataclass(frozen=True)
class Source:
    """Where the outputs come from: ``kind`` ``model`` (``config`` + ``checkpoint`` on ``device`` with ``threads``),
    ``results`` (``results`` folder) or ``oracle``."""

    kind: str
    config: str | None = None
    checkpoint: str | None = None
    results: str | None = None
    device: str = "cpu"
    threads: int | None = None

    def describe(self) -> dict:
        """The source as JSON data."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


LATENCY_LOG_FORMAT = "mpchair-stream-latency/1"
#: The largest constant latency (ms): an hour, longer than any stream; the schedule counts integer microseconds.
MAX_LATENCY_MS = 3_600_000.0


@dataclasses.dataclass(frozen=True, eq=False)
class Prepared:
    """Mode-independent state: per sequence the frames' ground truth (``gts`` label_2 rows, ``valid`` / ``dontcare``
    sensor-frame boxes, ``calibs``), ``outputs`` per frame (``None`` for frames a model never ran on when the offline
    pass was skipped) and the ``schedules``; how latency was obtained (``latency``: ``measured``, ``constant`` or
    ``log``) and the per-frame ``latency_log`` measured or replayed (JSON data; ``None`` for a constant); ``offline``:
    every frame has an output (the offline AP can be computed)."""

    stream: Stream
    source: Source
    classes: tuple[str, ...]
    min_overlaps: dict[str, tuple[float, float, float]]
    gts: list[list[Labels]]
    valid: list[list[np.ndarray]]
    dontcare: list[list[np.ndarray]]
    calibs: list[list[Calib]]
    outputs: list[list[Output | None]]
    schedules: list[Schedule]
    schedule: str
    latency: str
    latency_ms: float | None
    latency_log: dict | None
    offline: bool


def _ground_truth(stream: Stream, classes: Sequence[str]):
    wanted = {c.lower() for c in classes}
    gts, valid, dcs, calibs = [], [], [], []
    for seq in stream.sequences:
        g, v, d, c = [], [], [], []
        for i in range(len(seq)):
            labels, calib = seq.labels(i), seq.calib(i)
            objs = labels.objects()
            objs = objs[np.array([n.lower() in wanted for n in objs.names], dtype=bool)] if len(objs) else objs
            dc = seq.dontcare(i)
            g.append(labels)
            v.append(labels_to_boxes(objs, calib) if len(objs) else np.zeros((0, 7)))
            d.append(labels_to_boxes(dc, calib) if len(dc) else np.zeros((0, 7)))
            c.append(calib)
        gts.append(g)
        valid.append(v)
        dcs.append(d)
        calibs.append(c)
    return gts, valid, dcs, calibs


def read_latency_log(path: str | Path) -> dict:
    """A latency log written by ``--latency-log`` (``{"format", "machine", "repeats", "sequences": {seq: {frame id:
    microseconds}}}``); a foreign or malformed file is an :class:`InputError`."""
    path = Path(path)
    if not path.is_file():
        raise InputError("latency log not found (give 'measured' or a file written by --latency-log)", path)
    try:
        log = json.loads(path.read_text(encoding="utf-8"))
        ok = log.get("format") == LATENCY_LOG_FORMAT and all(
            isinstance(us, int) and us >= 0 for seq in log["sequences"].values() for us in seq.values())
    except (json.JSONDecodeError, AttributeError, KeyError, TypeError):
        ok = False
    if not ok:
        raise InputError(f"not a latency log ({LATENCY_LOG_FORMAT} with integer microseconds per frame)", path)
    return log


def prepare(stream: Stream, source: Source, *, latency_ms: float | None = None, latency_log: dict | None = None,
            schedule: str = "single", repeats: int = 3, warmup: int = 10, offline: bool = True,
            progress: bool = False) -> Prepared:
    """Offline outputs, latencies and schedules of ``stream`` (see the module docstring).

    Latency: ``latency_ms`` a constant for every frame; else ``latency_log`` (:func:`read_latency_log`) replays
    logged per-frame latencies; else a model's runtime is measured per processed frame (median of ``repeats`` runs,
    after ``warmup`` runs on the first frames). ``offline`` False skips a model's pass over every frame (no offline
    AP; the model then runs only on the frames the schedule processes). Bad combinations (measuring result files or
    the oracle, a negative latency, a log without a processed frame, an unknown schedule) are :class:`InputError`.
    """
    from tqdm import tqdm

    if schedule not in SCHEDULES:
        raise InputError(f"unknown schedule {schedule!r} ({' or '.join(SCHEDULES)})")
    if latency_ms is not None and not 0 <= latency_ms <= MAX_LATENCY_MS:  # inf / 1e300 overflowed the int64 schedule
        raise InputError(f"--latency-ms must be >= 0 and at most {MAX_LATENCY_MS:g} (an hour), got {latency_ms}")
    measured = latency_ms is None and latency_log is None
    if measured and source.kind != "model":
        raise InputError(f"--latency measured needs a model (--config and --checkpoint); for {source.kind} outputs "
                         "give --latency-ms or a latency log")
    if repeats < 1 or warmup < 0:
        raise InputError(f"need repeats >= 1 and warmup >= 0, got {repeats} and {warmup}")
    runner = None
    min_overlaps: dict[str, tuple[float, float, float]] = {}
    if source.kind == "model":
        runner = ModelRunner(source.config, source.checkpoint, source.device, source.threads)
        classes = runner.classes
        min_overlaps = {c: (t, t, t) for c, t in zip(runner.cfg.eval.classes, runner.cfg.eval.iou_thresholds)}
    else:
        classes = DEFAULT_CLASSES
    from detector.eval import DEFAULT_MIN_OVERLAPS

    min_overlaps = {c: min_overlaps.get(c, DEFAULT_MIN_OVERLAPS[c.lower()]) for c in classes}
    gts, valid, dcs, calibs = _ground_truth(stream, classes)

    outputs: list[list[Output | None]]
    if source.kind == "oracle":
        outputs = oracle_outputs(stream, classes)
    elif source.kind == "results":
        outputs = result_outputs(stream, source.results, classes)
    else:
        outputs = [[None] * len(seq) for seq in stream.sequences]
        if offline:
            with tqdm(total=stream.frames, desc="offline outputs", unit="frame", disable=not progress) as bar:
                for s, seq in enumerate(stream.sequences):
                    for i in range(len(seq)):
                        outputs[s][i] = runner.run(runner.frame(stream, seq, i))
                        bar.update(1)

    log = None
    if measured:
        from detector.device import machine_info

        first = stream.sequences[0]
        for w in range(warmup):  # the kernels, caches and allocator settle before anything is timed
            runner.run(runner.frame(stream, first, w % len(first)))
        log = {"format": LATENCY_LOG_FORMAT, "machine": machine_info(runner.device), "repeats": repeats,
               "source": source.describe(), "sequences": {seq.name: {} for seq in stream.sequences}}
    plan = single_worker if schedule == "single" else unbounded_workers
    schedules = []
    with tqdm(desc="timed frames", unit="frame", disable=not (progress and measured)) as bar:
        for s, seq in enumerate(stream.sequences):
            schedules.append(plan(seq.times_us, _latency_function(stream, s, runner, outputs, latency_ms, latency_log,
                                                                  log, repeats, bar)))
    for s, (seq, sched) in enumerate(zip(stream.sequences, schedules)):  # processed frames without an output yet
        for k in sched.inputs:
            if outputs[s][k] is not None:
                continue
            if runner is None:
                raise InputError(f"no result file for frame {seq.frame_id(int(k))} of sequence {seq.name}, which the "
                                 "schedule processes", Path(str(source.results)) / seq.name)
            outputs[s][k] = runner.run(runner.frame(stream, seq, int(k)))
    kind = "constant" if latency_ms is not None else "log" if latency_log is not None else "measured"
    return Prepared(stream=stream, source=source, classes=tuple(classes), min_overlaps=min_overlaps, gts=gts,
                    valid=valid, dontcare=dcs, calibs=calibs, outputs=outputs, schedules=schedules, schedule=schedule,
                    latency=kind, latency_ms=latency_ms, latency_log=log if measured else latency_log,
                    offline=all(o is not None for row in outputs for o in row))


def _latency_function(stream: Stream, s: int, runner: ModelRunner | None, outputs: list, latency_ms: float | None,
                      replay: dict | None, log: dict | None, repeats: int, bar) -> Callable[[int], int]:
    """Frame k's latency (integer microseconds) in sequence ``s``: constant, replayed from a log, or measured (and
    logged, keeping the timed run's output when the offline pass did not run)."""
    seq = stream.sequences[s]
    if latency_ms is not None:
        constant = int(round(latency_ms * 1000))
        return lambda k: constant
    if replay is not None:
        logged = replay["sequences"].get(seq.name, {})

        def from_log(k: int) -> int:
            if seq.frame_id(k) not in logged:
                raise InputError(f"the latency log has no latency for frame {seq.frame_id(k)} of sequence {seq.name} "
                                 "(it was made on another stream, or with another schedule)")
            return int(logged[seq.frame_id(k)])

        return from_log

    def measure(k: int) -> int:
        out, us = runner.measure(runner.frame(stream, seq, k), repeats)
        if outputs[s][k] is None:
            outputs[s][k] = out
        log["sequences"][seq.name][seq.frame_id(k)] = us
        bar.update(1)
        return us

    return measure


def _stats(values: np.ndarray, scale: float) -> dict[str, float | None]:
    if len(values) == 0:
        return {"mean": None, "p95": None}
    v = np.asarray(values, dtype=np.float64) * scale
    return {"mean": round(float(v.mean()), 6), "p95": round(float(np.percentile(v, 95)), 6)}


def query_sources(prep: Prepared) -> list[np.ndarray]:
    """Per sequence, (N,) int64: the input frame whose output each query frame is scored with (-1: none yet)."""
    out = []
    for seq, sched in zip(prep.stream.sequences, prep.schedules):
        j = latest_outputs(seq.times_us, sched)
        out.append(np.where(j >= 0, sched.inputs[np.maximum(j, 0)], -1))
    return out


def query_labels(prep: Prepared, mode: str, sources: list[np.ndarray]) -> list[Labels]:
    """The result rows of every query frame (all sequences, in order) scored in ``mode`` with ``sources``."""
    if mode not in MODES:
        raise InputError(f"unknown mode {mode!r} ({' or '.join(MODES)})")
    thr = {c: prep.min_overlaps[c][1] for c in prep.classes}  # the BEV threshold
    min_overlap = min(thr.values())
    out = []
    for s, seq in enumerate(prep.stream.sequences):
        for i in range(len(seq)):
            k = int(sources[s][i])
            if k < 0:
                out.append(Labels.empty(with_score=True))
                continue
            out.append(query_results(prep.outputs[s][k], seq.poses[k], seq.poses[i], k == i, mode,
                                     prep.stream.meta.region, prep.valid[s][i], prep.dontcare[s][i], min_overlap,
                                     prep.calibs[s][i], prep.stream.meta.image_size))
    return out


def score(prep: Prepared, mode: str) -> dict:
    """The ``--json`` summary of ``prep`` scored in ``mode`` (see ``docs/streaming.md``)."""
    sources = query_sources(prep)
    gts = [g for row in prep.gts for g in row]
    stream_result, sap = evaluate_overall(gts, query_labels(prep, mode, sources), prep.classes, prep.min_overlaps)
    offline_ap = None
    if prep.offline:
        own = [np.arange(len(seq), dtype=np.int64) for seq in prep.stream.sequences]
        _, offline_ap = evaluate_overall(gts, query_labels(prep, mode, own), prep.classes, prep.min_overlaps)
    stale_us, stale_frames = [], []
    for seq, src in zip(prep.stream.sequences, sources):
        has = src >= 0
        i = np.flatnonzero(has)
        stale_us.append(seq.times_us[i] - seq.times_us[src[has]])
        stale_frames.append(i - src[has])
    stale_us_all = np.concatenate(stale_us)
    stale_fr_all = np.concatenate(stale_frames)
    lat = np.concatenate([s.latency_us for s in prep.schedules]).astype(np.float64) / 1000.0
    n = prep.stream.frames
    return {
        "sAP": sap,
        "offline_AP": offline_ap,
        "staleness_ms": _stats(stale_us_all, 1e-3),
        "staleness_frames": _stats(stale_fr_all, 1.0),
        "latency_ms": {"median": round(float(np.median(lat)), 6) if len(lat) else None,
                       "p95": round(float(np.percentile(lat, 95)), 6) if len(lat) else None},
        "frames_processed": round(sum(len(s.inputs) for s in prep.schedules) / n, 6),
        "queries_without_output": int(sum(int((s < 0).sum()) for s in sources)),
        "in_time": round(float(np.count_nonzero(stale_fr_all == 0)) / n, 6),
        "mode": mode,
        "schedule": prep.schedule,
        "latency": {"constant_ms": prep.latency_ms} if prep.latency == "constant" else prep.latency,
        "frames": n,
        "sequences": len(prep.stream.sequences),
        "rate_hz": prep.stream.meta.rate_hz,
        "num_gt": {c: int(stream_result.num_gt_overall[c]) for c in prep.classes},
        # what a perfect detector scores on these chairs: below 100 with fewer than 41 (KITTI's recall slots)
        "ap_ceiling": {c: ap_ceiling(int(stream_result.num_gt_overall[c])) for c in prep.classes},
        "source": prep.source.describe(),
        **({"machine": prep.latency_log["machine"], "repeats": prep.latency_log["repeats"]}
           if prep.latency_log is not None else {}),
    }


def source_from_options(config: Path | None, checkpoint: Path | None, results: Path | None, oracle: bool,
                        device: str = "cpu", threads: int | None = None) -> Source:
    """Exactly one of ``--config/--checkpoint``, ``--results``, ``--oracle`` (else an :class:`InputError`)."""
    model = config is not None or checkpoint is not None
    if sum([model, results is not None, oracle]) != 1:
        raise InputError("give exactly one of --config/--checkpoint, --results or --oracle")
    if model:
        if config is None or checkpoint is None:
            raise InputError("a model needs both --config and --checkpoint")
        return Source("model", config=str(config), checkpoint=str(checkpoint), device=device, threads=threads)
    if results is not None:
        return Source("results", results=str(results))
    return Source("oracle")


#: The command that owns a ``--save-results`` folder (:mod:`mpchair.core.owned`).
SAVE_COMMAND = "detector stream-eval --save-results"


def _legacy_saved(folder: Path) -> set[str] | None:
    """The files of a ``--save-results`` folder written before ownership markers: nothing but regular
    ``NN/NNNNNN.txt`` result files (None otherwise)."""
    files = set()
    for seq in folder.iterdir():
        if seq.is_symlink() or not seq.is_dir():
            return None
        for f in seq.iterdir():
            if not (re.fullmatch(r"[0-9]+\.txt", f.name) and f.is_file() and not f.is_symlink()):
                return None
            files.add(f"{seq.name}/{f.name}")
    return files


def check_save_results(out: str | Path, results: str | Path | None = None) -> None:
    """Before any work: :class:`InputError` unless ``out`` may become the ``--save-results`` folder: missing, empty,
    or result files this command saved (a folder holding anything else is never replaced), not the ``--results``
    folder being read, and in a writable folder."""
    out = Path(out)
    if results is not None and Path(results).exists() and out.exists() and os.path.samefile(out, results):
        raise InputError("is the --results folder this run reads; save the results elsewhere", out)
    check_replaceable(out, SAVE_COMMAND, legacy=_legacy_saved, option="--save-results")
    check_writable(out, folder=True)


def save_results(prep: Prepared, out: str | Path) -> Path:
    """Write every output there is as a 16-column KITTI result file ``OUT/NN/NNNNNN.txt`` (rectified camera frame of
    that frame; the ``--results`` layout): every frame after the offline pass, else the frames the schedule processed
    (enough to replay the same schedule).

    All or nothing: the files are written into a hidden work folder beside ``OUT`` that replaces ``OUT`` when complete
    (an older folder this command saved is replaced; any other is refused, :func:`check_save_results`). A write that
    fails (a full disk) is an ``OSError`` naming ``OUT``, and leaves neither ``OUT`` nor the folders this call
    created on the way to it."""
    from detector.infer import boxes_to_results
    from mpchair.kitti import write_labels

    out = Path(out)
    check_save_results(out)
    created = [p for p in (out.parent, *out.parent.parents) if not p.exists()]  # deepest first
    try:
        clear_leftovers(out, SAVE_COMMAND, legacy=_legacy_saved)
        stage = work_dir(out.parent, f".{out.name}.work", SAVE_COMMAND)
        try:
            for s, seq in enumerate(prep.stream.sequences):
                for i in range(len(seq)):
                    o = prep.outputs[s][i]
                    if o is not None:
                        write_labels(stage / seq.name / f"{seq.frame_id(i)}.txt",
                                     boxes_to_results(o.boxes, o.scores, o.names, prep.calibs[s][i],
                                                      prep.stream.meta.image_size))
            replace_folder(stage, out, SAVE_COMMAND, legacy=_legacy_saved)
        finally:
            shutil.rmtree(stage, ignore_errors=True)
    except BaseException as e:
        for p in created:
            with contextlib.suppress(OSError):
                p.rmdir()
        if isinstance(e, OSError):  # name the folder asked for, not the hidden work folder nobody asked for
            raise OSError(e.errno, f"{e.strerror or e}; no result file was saved", str(out)) from None
        raise
    return out
