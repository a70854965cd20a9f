"""The result of ``detector bench`` (:func:`detector.bench.run.run_bench`): one typed record, the one definition of
the ``detector bench --json`` file. :meth:`BenchResult.to_json` writes it, :meth:`BenchResult.from_json` reads it
back; :mod:`detector.bench.report`, the reproduction's report and ``tools/device_check.py`` read it through these
types, never by key.

Times are milliseconds per frame (mean ± std over trials, each trial the mean over its frames); densities are
fractions of the pseudo-image canvas. A file written before a key existed reads with that key's default (noted per
field), so the committed results of earlier runs still load.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from detector.device import MACHINE_KEYS, Machine


@dataclass(frozen=True)
class Stat:
    """One component's time: mean and std over trials (population std), ms per frame."""

    mean_ms: float
    std_ms: float

    def to_json(self) -> dict[str, float]:
        return {"mean_ms": self.mean_ms, "std_ms": self.std_ms}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Stat:
        return cls(mean_ms=d["mean_ms"], std_ms=d.get("std_ms", 0.0))


def _stats(d: Mapping[str, Any] | None) -> dict[str, Stat] | None:
    return None if d is None else {k: Stat.from_json(v) for k, v in d.items()}


@dataclass(frozen=True)
class ModelResult:
    """One row: a model x runtime x precision of ours, or the peer's (``peer`` names the implementation, None for
    ours). ``components``: each timed component (``to_device`` ... ``total``); ``back_to_back``: the shared
    components timed back to back (None for the peer and for a single model); per-frame medians / minima; detections
    and page faults per frame (``page_faults_per_frame_by_component`` None for the peer); the median D of its
    frames. ``runtime`` / ``precision`` default to eager torch fp32 (files from before deployed rows)."""

    name: str
    components: Mapping[str, Stat]
    peer: str | None = None
    runtime: str = "torch"
    precision: str = "fp32"
    config: str = ""
    weights: str = ""
    backbone: str = ""
    head: str = "dense"
    output_shape: tuple[int, ...] = ()
    back_to_back: Mapping[str, Stat] | None = None
    median_frame_ms: Mapping[str, float] = field(default_factory=dict)
    min_frame_ms: Mapping[str, float] = field(default_factory=dict)
    detections_per_frame: float = 0.0
    page_faults_per_frame: float = 0.0
    page_faults_per_frame_by_component: Mapping[str, float] | None = None
    density_median: float | None = None

    @property
    def mean_ms(self) -> dict[str, float]:
        """Mean ms per component."""
        return {k: s.mean_ms for k, s in self.components.items()}

    @property
    def back_to_back_ms(self) -> dict[str, float]:
        """Mean ms per shared component timed back to back (empty when not timed so)."""
        return {k: s.mean_ms for k, s in (self.back_to_back or {}).items()}

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "peer": self.peer,
            "runtime": self.runtime,
            "precision": self.precision,
            "config": self.config,
            "weights": self.weights,
            "backbone": self.backbone,
            "head": self.head,
            "output_shape": list(self.output_shape),
            "components": {k: s.to_json() for k, s in self.components.items()},
            "back_to_back": None if self.back_to_back is None else {
                k: s.to_json() for k, s in self.back_to_back.items()},
            "median_frame_ms": dict(self.median_frame_ms),
            "min_frame_ms": dict(self.min_frame_ms),
            "detections_per_frame": self.detections_per_frame,
            "page_faults_per_frame": self.page_faults_per_frame,
            "page_faults_per_frame_by_component": None if self.page_faults_per_frame_by_component is None else dict(
                self.page_faults_per_frame_by_component),
            "density_median": self.density_median,
        }

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ModelResult:
        by = d.get("page_faults_per_frame_by_component")
        return cls(name=d["name"], components=_stats(d["components"]), peer=d.get("peer") or None,
                   runtime=d.get("runtime", "torch"), precision=d.get("precision", "fp32"),
                   config=d.get("config", ""), weights=d.get("weights", ""), backbone=d.get("backbone", ""),
                   head=d.get("head", "dense"), output_shape=tuple(d.get("output_shape") or ()),
                   back_to_back=_stats(d.get("back_to_back")), median_frame_ms=dict(d.get("median_frame_ms") or {}),
                   min_frame_ms=dict(d.get("min_frame_ms") or {}),
                   detections_per_frame=d.get("detections_per_frame", 0.0),
                   page_faults_per_frame=d.get("page_faults_per_frame", 0.0),
                   page_faults_per_frame_by_component=None if by is None else dict(by),
                   density_median=d.get("density_median"))


@dataclass(frozen=True)
class Skipped:
    """A model x runtime x precision not timed, and why."""

    name: str
    runtime: str
    precision: str
    reason: str

    def to_json(self) -> dict[str, str]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Skipped:
        return cls(name=d["name"], runtime=d["runtime"], precision=d["precision"], reason=d["reason"])


@dataclass(frozen=True)
class Headline:
    """The like-for-like headline: the fastest sparse row against the fastest dense row (any runtime and precision)
    and against the fastest fp32 dense row, by name; their mean total ms and the two speed-ups (dense / sparse).
    ``excluded``: ``"<row>: <reason>"`` of every row the AP guard kept out of the picks (:mod:`detector.bench.pick`;
    only where the caller knew the rows' AP), written to JSON only when there is one."""

    fastest_dense: str
    fastest_sparse: str
    fastest_fp32_dense: str
    dense_total_ms: float
    sparse_total_ms: float
    fp32_dense_total_ms: float
    speedup: float
    speedup_vs_fp32_dense: float
    excluded: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        if self.excluded:
            d["excluded"] = list(self.excluded)
        else:  # files of a bench without AP keep the keys they always had
            del d["excluded"]
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Headline:
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k != "excluded"},
                   excluded=tuple(d.get("excluded", ())))


@dataclass(frozen=True)
class DensityGrid:
    """The grid D was counted on: ``point_cloud_range`` (sensor frame, m), ``voxel_size`` (m) and the padded canvas
    ``output_shape``."""

    point_cloud_range: tuple[float, ...]
    voxel_size: tuple[float, ...]
    output_shape: tuple[int, ...]

    def to_json(self) -> dict[str, list]:
        return {"point_cloud_range": list(self.point_cloud_range), "voxel_size": list(self.voxel_size),
                "output_shape": list(self.output_shape)}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> DensityGrid:
        return cls(point_cloud_range=tuple(d["point_cloud_range"]), voxel_size=tuple(d["voxel_size"]),
                   output_shape=tuple(d["output_shape"]))


@dataclass(frozen=True)
class BenchDensity:
    """D (non-empty pillars / canvas cells) over the first row's frames: count, median, mean, min, max, and its grid."""

    frames: int
    median: float
    mean: float
    min: float
    max: float
    geometry: DensityGrid

    def to_json(self) -> dict[str, Any]:
        return {"frames": self.frames, "median": self.median, "mean": self.mean, "min": self.min, "max": self.max,
                "geometry": self.geometry.to_json()}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> BenchDensity:
        return cls(frames=d["frames"], median=d["median"], mean=d["mean"], min=d["min"], max=d["max"],
                   geometry=DensityGrid.from_json(d["geometry"]))


@dataclass(frozen=True)
class BenchProtocol:
    """How the result was measured: data folder, split, frames (and their ids), peer, trials, warm-up frames, batch,
    interleaving, the components timed back to back, the workspace and std notes, the runtimes and precisions asked
    for and the int8 calibration (``{"split", "frames"}`` or None). ``precision``: a key of files from before
    ``--precision`` existed (None in newer ones)."""

    data: str
    split: str
    frames: int
    trials: int
    warmup: int
    frame_ids: tuple[str, ...] = ()
    peer: str | None = None
    batch_size: int = 1
    interleaved: bool = True
    back_to_back: tuple[str, ...] = ()
    workspace: str | None = None
    std: str | None = None
    runtimes: tuple[str, ...] = ("torch",)
    precisions: tuple[str, ...] = ("fp32",)
    calibration: Mapping[str, Any] | None = None
    precision: str | None = None

    def to_json(self) -> dict[str, Any]:
        out = {"data": self.data, "split": self.split, "frames": self.frames, "frame_ids": list(self.frame_ids),
               "peer": self.peer, "trials": self.trials, "warmup": self.warmup, "batch_size": self.batch_size,
               "interleaved": self.interleaved, "back_to_back": list(self.back_to_back), "workspace": self.workspace,
               "std": self.std, "runtimes": list(self.runtimes), "precisions": list(self.precisions),
               "calibration": None if self.calibration is None else dict(self.calibration)}
        return out if self.precision is None else {**out, "precision": self.precision}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> BenchProtocol:
        calibration = d.get("calibration")
        return cls(data=d.get("data", ""), split=d["split"], frames=d["frames"], trials=d["trials"],
                   warmup=d["warmup"], frame_ids=tuple(d.get("frame_ids") or ()), peer=d.get("peer"),
                   batch_size=d.get("batch_size", 1), interleaved=d.get("interleaved", True),
                   back_to_back=tuple(d.get("back_to_back") or ()), workspace=d.get("workspace"), std=d.get("std"),
                   runtimes=tuple(d.get("runtimes") or ("torch",)), precisions=tuple(d.get("precisions") or ("fp32",)),
                   calibration=None if calibration is None else dict(calibration), precision=d.get("precision"))


@dataclass(frozen=True)
class BenchMachine:
    """The machine record of a bench (:class:`detector.device.Machine`) with what the bench adds: the CPU's native
    bf16 / int8 flags (``precision_flags``: precision -> flags; None in files from before), the library of the eager
    fp32 GEMMs (``gemm``: ``onednn`` / ``mkl``; files from before the key ran every such GEMM in MKL) and
    ``versions``: Open3D's when a peer ran, each deployed runtime's (by the key the file gives it)."""

    machine: Machine
    precision_flags: Mapping[str, tuple[str, ...]] | None = None
    gemm: str = "mkl"
    versions: Mapping[str, str] = field(default_factory=dict)

    def native_flags(self) -> set[str]:
        """Every native bf16 / int8 flag named (empty without ``precision_flags``)."""
        return {f for names in (self.precision_flags or {}).values() for f in names}

    def to_json(self) -> dict[str, Any]:
        out = self.machine.to_json()
        if self.precision_flags is not None:
            out["precision_flags"] = {p: list(f) for p, f in self.precision_flags.items()}
        return {**out, "gemm": self.gemm, **self.versions}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> BenchMachine:
        flags = d.get("precision_flags")
        known = {*MACHINE_KEYS, "precision_flags", "gemm"}
        return cls(machine=Machine.from_json(d),
                   precision_flags=None if flags is None else {p: tuple(f) for p, f in flags.items()},
                   gemm=d.get("gemm", "mkl"), versions={k: v for k, v in d.items() if k not in known})


@dataclass(frozen=True)
class BenchResult:
    """Every row of one bench in its order, the skipped combinations, the headline (None without both a dense and a
    sparse row of ours), D of the frames, the machine and the protocol (the last three None only in hand-made partial
    files)."""

    models: tuple[ModelResult, ...]
    skipped: tuple[Skipped, ...] = ()
    headline: Headline | None = None
    density: BenchDensity | None = None
    machine: BenchMachine | None = None
    protocol: BenchProtocol | None = None

    def ours(self) -> dict[str, ModelResult]:
        """Our rows (not the peer's), by name."""
        return {m.name: m for m in self.models if not m.peer}

    def peers(self) -> dict[str, ModelResult]:
        """The peer rows, by name."""
        return {m.name: m for m in self.models if m.peer}

    def to_json(self) -> dict[str, Any]:
        """The file's data (``json.dumps(..., indent=2)`` is ``detector bench --json``'s text)."""
        return {"models": [m.to_json() for m in self.models], "skipped": [s.to_json() for s in self.skipped],
                "headline": None if self.headline is None else self.headline.to_json(),
                "density": None if self.density is None else self.density.to_json(),
                "machine": None if self.machine is None else self.machine.to_json(),
                "protocol": None if self.protocol is None else self.protocol.to_json()}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> BenchResult:
        """The result of :meth:`to_json`'s data (or of a file from an earlier version: missing keys take their
        defaults)."""

        def opt(key: str, kind: Any) -> Any:
            return None if d.get(key) is None else kind.from_json(d[key])

        return cls(models=tuple(ModelResult.from_json(m) for m in d["models"]),
                   skipped=tuple(Skipped.from_json(s) for s in d.get("skipped") or ()),
                   headline=opt("headline", Headline), density=opt("density", BenchDensity),
                   machine=opt("machine", BenchMachine), protocol=opt("protocol", BenchProtocol))
