"""Typed readers of the files the reproduction's steps write and its report reads back.

A file format with a definition of its own is read through it: ``detector bench --json`` through
:class:`detector.bench.result.BenchResult`, ``manifest.json`` through :mod:`mpchair.dataset.manifest`, a run's
``config.yaml`` through :func:`detector.config.load_run_config`, a machine record through
:class:`detector.device.Machine`. The other records here are small frozen dataclasses with an explicit
``from_json``. A ``read_*`` function returns ``None`` (or an empty list) for a file that does not exist, and a key a
file lacks reads as ``None`` (or an empty mapping), so a report of a partial run names what is missing instead of
failing. APs are percent, times milliseconds unless a name says seconds.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from detector.bench.repeat import Repeated
from detector.bench.result import BenchResult
from detector.config import ExperimentConfig, load_run_config
from detector.device import Machine
from mpchair.core.text import parse_json, read_regular
from mpchair.dataset.manifest import Manifest
from mpchair.dataset.manifest import read_manifest as read_dataset_manifest

#: The eval step's second output per model (``results/eval_<model>/``): ``detector eval --protocol open3d-ml --json``.
OPEN3D_ML_JSON = "open3d_ml.json"
MODELS = ("dense", "sparse")
#: The paper's ablation backbones (section V-B), both Sparse+WideConv variants: the opt-in ablations step trains them.
ABLATIONS = ("sparse1_dense23", "sparse12_dense3", "sparse_wide", "sparse_wide_down")


def read_text(path: Path) -> str | None:
    """The text of ``path``, None when it does not exist; a FIFO, a device or a folder in its place, an oversized or
    non-UTF-8 file is an :class:`InputError` naming it (never a hang)."""
    return read_regular(path, "a work-folder file") if path.exists() or path.is_symlink() else None


def _read_json(path: Path) -> dict | None:
    """The JSON object in ``path``, None when the file does not exist or is empty; malformed or deeply nested JSON
    is an :class:`InputError` naming it."""
    text = read_text(path)
    return parse_json(text, path) if text else None


# --- detector eval: the KITTI protocol (metrics.json, and each validation record of a training's metrics.jsonl) -------
@dataclass(frozen=True)
class KittiAP:
    """Chair's AP of one KITTI metric (``bev``, ``3d``, ...): per difficulty (Easy, Moderate, Hard) and over every
    chair (the Overall level), by recall variant (``R40``, ``R11``); a variant the file lacks is absent."""

    levels: Mapping[str, tuple[float, ...]] = field(default_factory=dict)
    overall: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def from_json(cls, block: dict | None) -> KittiAP:
        block = block or {}
        levels = {r: tuple(v) for r, v in block.items() if r != "overall" and isinstance(v, list) and v}
        return cls(levels=levels, overall=dict(block.get("overall") or {}))


@dataclass(frozen=True)
class KittiMetrics:
    """Chair's KITTI AP by metric (``bev``, ``3d``, ...) and its valid GT counts: Easy / Moderate / Hard
    (``num_gt``) and Overall (``num_gt_overall``); None where the file has none (one written before the Overall
    level existed has no ``overall`` APs and no ``num_gt_overall``)."""

    ap: Mapping[str, KittiAP]
    num_gt: tuple[int, ...] | None = None
    num_gt_overall: int | None = None

    @classmethod
    def from_json(cls, d: dict) -> KittiMetrics:
        chair = d.get("Chair") or {}
        counts = (d.get("num_gt") or {}).get("Chair")
        return cls(ap={k: KittiAP.from_json(v) for k, v in chair.items() if isinstance(v, dict)},
                   num_gt=tuple(counts) if counts else None,
                   num_gt_overall=(d.get("num_gt_overall") or {}).get("Chair"))

    def levels(self, kind: str, recall: str) -> tuple[float, ...] | None:
        """Easy / Moderate / Hard AP of metric ``kind`` and recall variant ``recall`` (None when absent)."""
        return self.ap.get(kind, KittiAP()).levels.get(recall)

    def overall(self, kind: str, recall: str) -> float | None:
        """The Overall level's AP of metric ``kind`` and recall variant ``recall`` (None when absent)."""
        return self.ap.get(kind, KittiAP()).overall.get(recall)


# --- detector eval --protocol open3d-ml (open3d_ml.json) --------------------------------------------------------------
@dataclass(frozen=True)
class Open3dMlMetrics:
    """Open3D-ML's mAP (the reference's own metric) of Chair by metric (``bev``, ``3d``)."""

    ap: Mapping[str, float]

    @classmethod
    def from_json(cls, d: dict) -> Open3dMlMetrics:
        return cls(ap=dict(d.get("Chair") or {}))

    def get(self, kind: str) -> float | None:
        """The mAP of metric ``kind`` (None when absent)."""
        return self.ap.get(kind)


@dataclass(frozen=True)
class EvalOutputs:
    """The eval step's outputs that exist, by model: KITTI ``metrics.json`` and Open3D-ML ``open3d_ml.json``."""

    kitti: Mapping[str, KittiMetrics]
    open3d_ml: Mapping[str, Open3dMlMetrics]


def read_eval_outputs(res: Path, models: tuple[str, ...] = MODELS) -> EvalOutputs:
    """The eval outputs of ``models`` under results folder ``res`` (``eval_<model>/``)."""
    kitti = {m: KittiMetrics.from_json(d) for m in models if (d := _read_json(res / f"eval_{m}" / "metrics.json"))
             is not None}
    o3d = {m: Open3dMlMetrics.from_json(d) for m in models if (d := _read_json(res / f"eval_{m}" / OPEN3D_ML_JSON))
           is not None}
    return EvalOutputs(kitti=kitti, open3d_ml=o3d)


# --- detector bench --json-out (bench_<allocator>.json) ---------------------------------------------------------------
def read_bench(path: Path) -> BenchResult | None:
    """A bench JSON, read by its one definition (:class:`detector.bench.result.BenchResult`); None when the bench
    step did not write it."""
    d = _read_json(path)
    return None if d is None else BenchResult.from_json(d)


def read_bench_repeated(path: Path) -> Repeated | None:
    """The spread over runs of a ``detector bench --runs N`` JSON (:class:`detector.bench.repeat.Repeated`); None for
    a one-run JSON or no file."""
    d = _read_json(path)
    return Repeated.from_json(d["repeated"]) if d and isinstance(d.get("repeated"), dict) else None


def bench_weights(path: Path) -> tuple[str, ...]:
    """The ``weights`` line of each model of a bench JSON, in its order (empty when there is no file)."""
    bench = read_bench(path)
    return tuple(m.weights for m in bench.models) if bench else ()


# --- tools/bench_reference_head.py --json-out (bench_reference_head.json) ---------------------------------------------
@dataclass(frozen=True)
class ReferenceHeadBench:
    """Each model's mean ms per frame by component (``head``, ``total``, ``head_reference``,
    ``total_reference_head``, ...), by name in the file's order, and the CPU and torch threads it ran on."""

    mean_ms: Mapping[str, Mapping[str, float]]
    cpu: str = ""
    threads: int | None = None

    @classmethod
    def from_json(cls, d: dict) -> ReferenceHeadBench:
        mach = Machine.from_json(d.get("machine") or {})
        return cls(mean_ms={m["name"]: dict(m["mean_ms"]) for m in d["models"]}, cpu=mach.cpu,
                   threads=mach.torch_threads)

    def ratio(self, numerator: str, denominator: str, key: str) -> float | None:
        """``numerator``'s ``key`` ms over ``denominator``'s (None when either model is absent)."""
        if numerator not in self.mean_ms or denominator not in self.mean_ms:
            return None
        return self.mean_ms[numerator][key] / max(self.mean_ms[denominator][key], 1e-9)


def read_reference_head(path: Path) -> ReferenceHeadBench | None:
    """The refhead step's JSON (None when absent)."""
    d = _read_json(path)
    return None if d is None else ReferenceHeadBench.from_json(d)


# --- tools/bench_density.py --json-out (density_curve.json) -----------------------------------------------------------
@dataclass(frozen=True)
class CurvePoint:
    """One density of the curve: D, pillars, both backbones' median ms, their ratio and the op-count ratio (dense
    MACs / sparse exact MACs); ``frame_id`` for a real frame (None: synthetic sites)."""

    density: float
    pillars: float
    dense_ms: float
    sparse_ms: float
    runtime_ratio: float
    op_ratio: float
    frame_id: str | None = None

    @classmethod
    def from_json(cls, d: dict) -> CurvePoint:
        return cls(density=d["density"], pillars=d["pillars"], dense_ms=d["dense_ms"], sparse_ms=d["sparse_ms"],
                   runtime_ratio=d["runtime_ratio"], op_ratio=d["op_ratio"], frame_id=d.get("frame_id"))


@dataclass(frozen=True)
class DensityCurve:
    """The density curve: its synthetic points, the real frames, the two crossings (D or None: ``ratio_one``,
    ``meets_ops``, ``ratio_one_extrapolated``), the canvas (ny, nx), how the sites were made, the weights, the CPU."""

    points: tuple[CurvePoint, ...]
    real: tuple[CurvePoint, ...]
    crossings: Mapping[str, float | None]
    output_shape: tuple[int, ...]
    sites: str
    weights: str
    cpu: str
    threads: int | None

    @classmethod
    def from_json(cls, d: dict) -> DensityCurve:
        mach = Machine.from_json(d.get("machine") or {})
        return cls(points=tuple(CurvePoint.from_json(p) for p in d["points"]),
                   real=tuple(CurvePoint.from_json(p) for p in d.get("real") or ()),
                   crossings=dict(d.get("crossings") or {}), output_shape=tuple(d["geometry"]["output_shape"]),
                   sites=d.get("sites", ""), weights=(d.get("protocol") or {}).get("weights", ""),
                   cpu=mach.cpu, threads=mach.torch_threads)


def read_density_curve(path: Path) -> DensityCurve | None:
    """The curve step's JSON (None when absent)."""
    d = _read_json(path)
    return None if d is None else DensityCurve.from_json(d)


# --- mpchair stats --density --json (density.json) --------------------------------------------------------------------
@dataclass(frozen=True)
class DensitySummary:
    """The summary of D (the fraction of non-empty pillars per frame) that the report quotes: the values of
    ``median``, ``min`` and ``max`` the stats JSON has, as it wrote them, in that order."""

    values: Mapping[str, float]

    @classmethod
    def from_json(cls, d: dict) -> DensitySummary:
        s = d.get("summary", d)
        return cls(values={k: s[k] for k in ("median", "min", "max") if k in s})


def read_density(path: Path) -> DensitySummary | None:
    """``density.json`` of the stats step (None when absent or empty)."""
    d = _read_json(path)
    return None if d is None else DensitySummary.from_json(d)


# --- mpchair generate (dataset/manifest.json) -------------------------------------------------------------------------
def read_manifest(dataset: Path) -> Manifest | None:
    """``dataset/manifest.json`` without its per-frame list (:func:`mpchair.dataset.manifest.read_manifest`; a run
    record's copy has none), None when the dataset has no manifest (not generated yet)."""
    return read_dataset_manifest(dataset, frames=False)


# --- detector viz-sparsity --json (viz.json) --------------------------------------------------------------------------
@dataclass(frozen=True)
class SparsityFrame:
    """The frame the sparsity figures were drawn on: its id and D (non-empty pillars / canvas, the dense input)."""

    frame_id: str
    density: float


def read_sparsity_frame(path: Path) -> SparsityFrame | None:
    """``viz.json`` of the viz step (None when absent or without the dense input's fraction)."""
    d = _read_json(path)
    fractions = (d or {}).get("nonzero_fraction", {}).get("dense") or []
    return SparsityFrame(str(d["frame_id"]), float(fractions[0])) if d and fractions else None


# --- detector train (RUN/config.yaml, RUN/metrics.jsonl) --------------------------------------------------------------
def read_run_config(run: Path) -> ExperimentConfig | None:
    """The experiment a run folder was trained with (``RUN/config.yaml``, read by
    :func:`detector.config.load_run_config`), None when it has none (not trained yet)."""
    path = run / "config.yaml"
    if not read_text(path):  # (refuses a FIFO or a device in its place)
        return None
    return load_run_config(path)


@dataclass(frozen=True)
class StepRecord:
    """A training step of metrics.jsonl: its number (from 1), epoch (None if not recorded) and wall seconds."""

    step: int
    epoch: int | None
    time_s: float

    @classmethod
    def from_json(cls, d: dict) -> StepRecord:
        return cls(step=d["step"], epoch=d.get("epoch"), time_s=d["time_s"])


@dataclass(frozen=True)
class EpochRecord:
    """A finished epoch of metrics.jsonl: its number (from 1) and wall seconds."""

    epoch: int
    time_s: float

    @classmethod
    def from_json(cls, d: dict) -> EpochRecord:
        return cls(epoch=d["epoch"], time_s=d["time_s"])


@dataclass(frozen=True)
class EvalRecord:
    """A validation during training (metrics.jsonl): the epoch after which it ran, and its KITTI AP."""

    epoch: int
    metrics: KittiMetrics

    @classmethod
    def from_json(cls, d: dict) -> EvalRecord:
        return cls(epoch=d["epoch"], metrics=KittiMetrics.from_json(d))


def _records(run: Path, kind: str) -> list[dict]:
    """A run folder's metrics.jsonl records of one ``kind``, in order; none without the file, and without the torn
    last line a killed run may leave."""
    found = []
    for line in (read_text(run / "metrics.jsonl") or "").splitlines():
        with contextlib.suppress(ValueError, RecursionError):
            record = json.loads(line)
            if isinstance(record, dict) and record.get("kind") == kind and _well_formed(record, kind):
                found.append(record)
    return found


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _well_formed(record: dict, kind: str) -> bool:
    """Whether a metrics.jsonl record has the fields its kind's reader takes (a hand-edited or foreign line is
    skipped like a torn one)."""
    if kind == "step":
        return isinstance(record.get("step"), int) and _is_number(record.get("time_s"))
    return True


def step_records(run: Path) -> list[StepRecord]:
    """The training steps of a run folder's metrics.jsonl, in order."""
    return [StepRecord.from_json(r) for r in _records(run, "step")]


def epoch_records(run: Path) -> list[EpochRecord]:
    """The finished epochs of a run folder's metrics.jsonl, in order."""
    return [EpochRecord.from_json(r) for r in _records(run, "epoch")]


def end_record(run: Path) -> dict | None:
    """The ``end`` record of a run's metrics.jsonl (None: the run has not ended); here beside the other readers of
    metrics.jsonl so that reproduction.committed reads it without importing the accuracy study (and its steps)."""
    path = run / "metrics.jsonl"
    if not path.is_file():
        return None
    end = None
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and rec.get("kind") == "end":
            end = rec
    return end


def eval_records(run: Path) -> list[EvalRecord]:
    """The validations of a run folder's metrics.jsonl, in order."""
    return [EvalRecord.from_json(r) for r in _records(run, "eval")]
