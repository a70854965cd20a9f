"""Per-component runtime of dense and sparse PointPillars: the paper's Tables II / IV protocol, made measurable.

The components and their stamps are :mod:`detector.bench.timing`'s; Open3D-ML's own PointPillars can be timed as a
peer row (:mod:`detector.bench.peer`); :mod:`detector.bench.report` prints the result as the paper's tables.

Runtimes and precisions (:class:`Variant`): every model x runtime (eager ``torch``, ``onnxruntime``, ``openvino``) x
precision (``fp32``, ``bf16``, ``int8``) is one row, all interleaved per frame. A deployed row is a
:class:`detector.deploy.deployed.DeployedPointPillars`: the same stage methods around the exported graph, so the same
stamps time it (Backbone = the graph: backbone + neck + head). A combination this CPU does not compute natively is
skipped with the reason (:func:`detector.deploy.cpu.skip_reason`); ``headline`` compares the fastest sparse row with
the fastest dense row.

Protocol: every model is warmed up on the first frames, then ``trials`` passes over the same ``frames`` frames are
timed. Within a pass the models are **interleaved per frame** (the order alternates from frame to frame), so load
spikes of a shared machine hit all models alike. A trial's value of a component is its mean over the frames (the
per-instance runtime); the reported mean ± std is over trials (population std), as the paper's tables. On CUDA the
device is synchronised before every stamp; stamps are ``time.perf_counter``.

Back to back: a component runs at the speed of the state the stage before it left (caches, predictors, allocator). The
paper calls the Head and BBox Extract identical in both models, yet in the per-frame pipeline each one follows a
model-specific backbone: on a 2-core AMX Xeon the same post-processing took 1.6x as long after the dense backbone
(400 ms of oneDNN convolutions) as after the sparse one on identical work (random weights; 1.25-2.5x on trained ones),
even a single ``amax`` over the class map did, and the gap vanished when a tiny dummy call warmed the code path first
(the paper saw the same effect on GPUs and put it down to pipelining). So after the timed passes, ``trials`` more passes
time these :data:`~detector.bench.timing.SHARED` components **back to back**: per frame every model runs to its neck
(untimed), then every model's Head, then every model's BBox Extract, each on its own maps, in an order rotated from
frame to frame, so each model's component follows the same kind of stage as the others'. The per-frame columns stay the
paper's protocol (what a pipeline pays); the back-to-back columns are the components' own cost, the one to compare
between models.

The result records the data's pseudo-image density ``D`` (pillars indexed by :func:`mpchair.geometry.pillar_coords`,
over the model's ``output_shape`` canvas) and the machine (:func:`detector.device.machine_info`): CPU model, threads,
torch version, GPU, load average, the glibc allocator settings ``MALLOC_MMAP_MAX_`` / ``MALLOC_TRIM_THRESHOLD_`` (they
can dominate CPU timings, see ``docs/benchmarks.md``) and page faults per frame of each model (``resource.getrusage``,
whole process).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from detector.bench import peer as open3d_peer
from detector.bench.pick import ap_exclusion, fastest_within_ap
from detector.bench.result import (
    BenchDensity,
    BenchMachine,
    BenchProtocol,
    BenchResult,
    DensityGrid,
    Headline,
    ModelResult,
    Skipped,
    Stat,
)
from detector.bench.timing import COMPONENTS, SHARED, page_faults, time_frame, time_shared
from detector.checkpoint import load_model
from detector.config import ExperimentConfig, load_experiment, pseudoimage_geometry
from detector.data.experiment import EvalFrame, load_eval_frames
from detector.deploy.cpu import PRECISIONS, RUNTIMES, cpu_flags, precision_flags, skip_reason
from detector.deploy.deployed import graph_work_dir
from detector.device import Machine, use_device
from detector.models import PointPillars
from detector.ops.gemm import library as gemm_library
from detector.sparse.workspace import Workspace
from mpchair.core.errors import InputError
from mpchair.geometry import frame_density

#: One frame's points (N, C) float32, sensor frame → ``({component: ms}, detections)``.
FrameTimer = Callable[[np.ndarray], tuple[dict[str, float], int]]


@dataclass(frozen=True)
class BenchModel:
    """One model to time: display ``name``, its ``config`` path and optional ``checkpoint``."""

    name: str
    config: str
    checkpoint: str | None = None


def bench_checkpoints(configs: Sequence[str], checkpoints: Sequence[str]) -> list[str | None]:
    """The weights of each ``--config`` from the ``--checkpoint`` options (``-`` or none at all: random weights, None);
    an :class:`InputError` unless there is one per config or none."""
    if checkpoints and len(checkpoints) != len(configs):
        raise InputError(f"give one --checkpoint per --config ('-' for random weights): {len(checkpoints)} "
                         f"checkpoint(s) for {len(configs)} config(s)")
    return [None if c in ("-", "") else c for c in checkpoints] or [None] * len(configs)


class TimedRow(NamedTuple):
    """One row of the result: its display ``name``, the ``model`` / ``cfg`` it was built from (the peer: the first
    model's), a description of its ``weights``, ``peer`` (None for ours), its ``timer`` and the ``frames`` it is fed
    with their pseudo-image ``densities`` (pillars / canvas cells); ``faults`` collects ours' page faults per
    component; the ``runtime`` (``torch``, ``onnxruntime``, ``openvino``; the peer's is torch) and ``precision``
    (``fp32``, ``bf16``, ``int8``) it runs in."""

    name: str
    model: BenchModel
    cfg: ExperimentConfig
    weights: str
    peer: str | None
    timer: FrameTimer
    frames: list[EvalFrame]
    densities: list[float]
    faults: dict[str, int] | None = None  # page faults per component, filled by the timer (ours; None: the peer)
    runtime: str = "torch"
    precision: str = "fp32"


@dataclass(frozen=True)
class Variant:
    """How to run the models: every model x ``runtimes`` x ``precisions`` is one row (a combination this CPU cannot
    compute natively is skipped with the reason, :func:`detector.deploy.cpu.skip_reason`); int8 calibrates on the
    first ``calibration_frames`` frames of ``calibration_split``."""

    runtimes: tuple[str, ...] = ("torch",)
    precisions: tuple[str, ...] = ("fp32",)
    calibration_split: str = "train"
    calibration_frames: int = 8


@dataclass(frozen=True)
class Timings:
    """The timed passes of every row: ``per_frame`` (rows, trials, frames, components) ms, ``trial_means`` (rows,
    trials, components) ms (a trial's mean over its frames), ``faults`` and ``detections`` (rows,) summed over every
    timed frame; ``back_to_back`` (our models, trials, shared components) ms, per trial the mean over frames, or None
    when fewer than two of our models ran."""

    per_frame: np.ndarray
    trial_means: np.ndarray
    faults: np.ndarray
    detections: np.ndarray
    back_to_back: np.ndarray | None


def density_summary(values: Sequence[float]) -> dict[str, float]:
    """``{"frames", "median", "mean", "min", "max"}`` of per-frame densities."""
    v = np.asarray(values, dtype=np.float64)
    return {"frames": int(v.size), "median": float(np.median(v)), "mean": float(v.mean()), "min": float(v.min()),
            "max": float(v.max())}


def default_name(cfg: ExperimentConfig, path: str | Path) -> str:
    """``dense`` / ``sparse`` / ... from the backbone, plus ``+sparse_head`` for the exact sparse head."""
    name = cfg.model.backbone
    if cfg.model.head != "dense":
        name += "+sparse_head"
    return name


def display_names(models: Sequence[BenchModel], cfgs: Sequence[ExperimentConfig]) -> list[str]:
    """Each model's row name: its ``name``, else :func:`default_name`; names that repeat get ``:<config stem>``."""
    names = [m.name or default_name(c, m.config) for m, c in zip(models, cfgs)]
    if len(set(names)) != len(names):
        # two configs with the same backbone (e.g. a shape sweep): fall back to file stems
        names = [n if names.count(n) == 1 else f"{n}:{Path(m.config).stem}" for n, m in zip(names, models)]
    return names


def run_bench(
    models: Sequence[BenchModel],
    data_dir: str | Path,
    *,
    split: str = "test",
    frames: int = 20,
    trials: int = 3,
    warmup: int = 3,
    device: str = "cpu",
    threads: int | None = None,
    seed: int = 0,
    peer: str | None = None,
    progress: bool = False,
    variant: Variant = Variant(),
) -> BenchResult:
    """Time every model on the first ``frames`` frames of ``split``: a :class:`detector.bench.result.BenchResult`
    (its ``to_json()`` is ``detector bench --json``'s file). ``progress``: bars on stderr (loading, warm-up and timed
    frames) when it is a terminal. ``variant``: the runtimes and precisions of every model (default: eager torch
    fp32), one row each, all interleaved per frame. ``headline``: :func:`headline_record`.

    ``peer="open3d-ml"`` adds Open3D-ML's own PointPillars as the last row (``"peer": "open3d-ml"``; ours have
    ``"peer": None``): built with the first model's architecture and grid and its weights (:mod:`detector.bench.peer`;
    the first model must be dense), fed the first model's frames, interleaved per frame with the others. CPU only.
    """
    if not models:
        raise InputError("bench needs at least one --config")
    if frames < 1 or trials < 1 or warmup < 0:
        raise InputError(f"need frames >= 1, trials >= 1, warmup >= 0 (got {frames}, {trials}, {warmup})")
    check_variant(variant, device)
    dev = use_device(device, threads)
    _check_peer(peer, device)
    with graph_work_dir("detector-bench-") as work:  # the exported graphs, for this run only
        rows, nets, skipped = build_rows(models, dev, data_dir, split, frames, seed, progress, variant, work)
        if peer is not None:
            first = next((j for j, r in enumerate(rows) if r.runtime == "torch"), None)
            if first is None:
                raise InputError("--peer needs a torch row (its weights are copied from the first eager model)")
            rows.append(peer_row(rows[first], nets[first], peer))

        n = len(rows[0].frames)
        # one bar step = one frame through every model; stderr, so a table or Markdown on stdout stays clean
        bar = tqdm(total=min(warmup, n) + trials * n * (2 if len(nets) > 1 else 1), desc="bench warm-up",
                   unit="frame", disable=None if progress else True, leave=False)
        warm_up(rows, min(warmup, n), bar)
        timings = time_rows(rows, trials, bar)
        if len(nets) > 1:  # the shared components back to back (ours only: the peer's stages are not ours to split)
            timings = replace(timings, back_to_back=time_back_to_back(nets, rows[: len(nets)], trials, dev, bar))
        bar.close()
    records = tuple(model_record(row, j, timings) for j, row in enumerate(rows))
    return BenchResult(
        models=records,
        skipped=tuple(skipped),
        headline=headline_record(records),
        density=density_record(rows[0]),
        machine=machine_record(dev, peer, variant),
        protocol=protocol_record(rows[0], data_dir, split, peer, trials, min(warmup, n), len(nets) > 1, variant),
    )


def check_variant(variant: Variant, device: str) -> None:
    """:class:`InputError` for an unknown runtime or precision, a deployed runtime off the CPU, or int8 without
    calibration frames."""
    for r in variant.runtimes:
        if r not in RUNTIMES:
            raise InputError(f"unknown runtime {r!r} (choose from {', '.join(RUNTIMES)})")
    for p in variant.precisions:
        if p not in PRECISIONS:
            raise InputError(f"unknown precision {p!r} (choose from {', '.join(PRECISIONS)})")
    if not variant.runtimes or not variant.precisions:
        raise InputError("bench needs at least one --runtime and one --precision")
    if device != "cpu" and set(variant.runtimes) - {"torch"}:
        raise InputError(f"--runtime onnxruntime / openvino run on the CPU here; drop --device {device}")
    if "int8" in variant.precisions and variant.calibration_frames < 1:
        raise InputError("int8 needs --calibration-frames >= 1")


def build_rows(models: Sequence[BenchModel], device: torch.device, data_dir: str | Path, split: str, frames: int,
               seed: int, progress: bool, variant: Variant, work: Path) -> tuple[list[TimedRow], list, list[Skipped]]:
    """Every model x runtime x precision this CPU computes natively, as rows (deployed graphs exported into
    ``work``), the model object of each row (an eager :class:`PointPillars` or a
    :class:`detector.deploy.deployed.DeployedPointPillars`) and the skipped combinations; an :class:`InputError`
    when every one is skipped."""
    cfgs = [load_experiment(m.config) for m in models]
    names = display_names(models, cfgs)
    eager = [load_model(c, m.checkpoint, device, seed=seed) for c, m in zip(cfgs, models)]
    for net in eager:
        # a long-running process's steady state: every model reuses its inference buffers from frame to frame (the
        # stages' outputs are consumed before the next frame), see detector.sparse.workspace
        net.workspace = Workspace()
    base = our_rows(models, cfgs, names, eager, device, data_dir, split, frames, seed, progress)
    flags = cpu_flags()
    rows: list[TimedRow] = []
    nets: list = []
    skipped: list[Skipped] = []
    calibration: dict[int, list[np.ndarray]] = {}
    for i, (row, net) in enumerate(zip(base, eager)):
        for runtime in variant.runtimes:
            for precision in variant.precisions:
                why = skip_reason(runtime, precision, flags)
                if why is not None:
                    skipped.append(Skipped(row.name, runtime, precision, why))
                    continue
                if runtime == "torch" and precision == "fp32":
                    rows.append(row)
                    nets.append(net)
                    continue
                if runtime == "torch":  # eager bf16: the same weights in a copy whose stages run under autocast
                    variant_net = copy.deepcopy(net)
                    variant_net.workspace = Workspace()
                    variant_net.precision = precision  # type: ignore[assignment]
                else:
                    if precision == "int8" and i not in calibration:
                        calibration[i] = [f.points for f in load_eval_frames(
                            row.cfg, data_dir, variant.calibration_split, variant.calibration_frames)]
                    variant_net = deploy_row(net, row, runtime, precision, work / f"{i}-{runtime}-{precision}",
                                             torch.get_num_threads(), calibration.get(i, []), seed)
                faults: dict[str, int] = {}
                rows.append(row._replace(name=variant_name(row.name, runtime, precision), runtime=runtime,
                                         precision=precision, faults=faults,
                                         timer=lambda pts, net=variant_net, faults=faults: time_frame(
                                             net, pts, device, faults)))
                nets.append(variant_net)
    if not rows:
        raise InputError("every model x runtime x precision asked for is skipped on this CPU: "
                         + "; ".join(f"{s.name} {s.runtime} {s.precision}: {s.reason}" for s in skipped))
    return rows, nets, skipped


def deploy_row(net: PointPillars, row: TimedRow, runtime: str, precision: str, work: Path, threads: int,
               calibration: list[np.ndarray], seed: int):
    """``net`` exported and opened in ``runtime`` / ``precision`` (:func:`detector.deploy.deployed.build_deployed`);
    a model the export cannot take is an :class:`InputError` naming its config."""
    from detector.deploy.deployed import build_deployed

    try:
        return build_deployed(net, runtime, precision, work, threads=threads, calibration=calibration, seed=seed)
    except ValueError as e:
        raise InputError(f"cannot run {row.name} in {runtime}: {e}", row.model.config) from None


def variant_name(name: str, runtime: str, precision: str) -> str:
    """A row's display name: the model's for eager torch fp32 (as before runtimes existed), else
    ``<model> (<runtime> <precision>)``."""
    return name if (runtime, precision) == ("torch", "fp32") else f"{name} ({runtime} {precision})"


def headline_record(models: Sequence[ModelResult], ap_3d: Mapping[str, float] | None = None) -> Headline | None:
    """The like-for-like headline: the fastest sparse row against the fastest dense row (mean total ms, our rows of
    any runtime and precision), and against the fastest fp32 dense row; None without both kinds.

    ``ap_3d``: 3D AP (Overall R40) by row name, where the caller has evaluated the rows (a bench alone has not). A row
    whose AP and whose model's eager fp32 AP (its torch fp32 row: the name without the `` (runtime precision)``
    suffix, :func:`variant_name`) are both known is picked only within :data:`detector.bench.pick.AP_TOLERANCE` of
    it; the rows left out are the headline's ``excluded``."""
    ap_3d = ap_3d or {}
    ours = [m for m in models if not m.peer]

    def eager_ap(m: ModelResult) -> float | None:
        return ap_3d.get(m.name.removesuffix(f" ({m.runtime} {m.precision})"))

    reasons = {m.name: ap_exclusion(ap_3d.get(m.name), eager_ap(m)) for m in ours}

    def fastest(rows: list[ModelResult]) -> ModelResult | None:
        return fastest_within_ap(rows, lambda m: m.components["total"].mean_ms, lambda m: reasons[m.name])

    dense = fastest([m for m in ours if m.backbone == "dense"])
    sparse = fastest([m for m in ours if m.backbone != "dense"])
    fp32 = fastest([m for m in ours if m.backbone == "dense" and m.precision == "fp32"])
    if dense is None or sparse is None or fp32 is None:
        return None
    ms = {k: m.components["total"].mean_ms for k, m in (("dense", dense), ("sparse", sparse), ("fp32", fp32))}
    return Headline(fastest_dense=dense.name, fastest_sparse=sparse.name, fastest_fp32_dense=fp32.name,
                    dense_total_ms=ms["dense"], sparse_total_ms=ms["sparse"], fp32_dense_total_ms=ms["fp32"],
                    speedup=ms["dense"] / ms["sparse"], speedup_vs_fp32_dense=ms["fp32"] / ms["sparse"],
                    excluded=tuple(f"{n}: {r}" for n, r in reasons.items() if r is not None))


def _check_peer(peer: str | None, device: str) -> None:
    """:class:`InputError` unless ``peer`` is None or a known peer timed on the CPU."""
    if peer is not None and peer not in open3d_peer.PEERS:
        raise InputError(f"unknown peer {peer!r} (choose from {', '.join(open3d_peer.PEERS)})")
    if peer is not None and device != "cpu":
        raise InputError(f"--peer {peer} times the CPU only (open3d-cpu); drop --device {device}")


def our_rows(models: Sequence[BenchModel], cfgs: Sequence[ExperimentConfig], names: Sequence[str],
             nets: Sequence[PointPillars], device: torch.device, data_dir: str | Path, split: str, frames: int,
             seed: int, progress: bool) -> list[TimedRow]:
    """One row per model of ours: its first ``frames`` frames of ``split`` (each model's own transform) and their
    densities over its canvas, timed by :func:`detector.bench.timing.time_frame` on ``device``."""
    data = [load_eval_frames(c, data_dir, split, frames, progress=progress) for c in cfgs]
    rows = []
    for model, cfg, name, net, fs in zip(models, cfgs, names, nets, data):
        geometry = pseudoimage_geometry(cfg.model)
        weights = str(model.checkpoint) if model.checkpoint else f"random (seed {seed}; untrained, timing only)"
        faults: dict[str, int] = {}
        rows.append(TimedRow(name=name, model=model, cfg=cfg, weights=weights, peer=None,
                             timer=lambda pts, net=net, faults=faults: time_frame(net, pts, device, faults), frames=fs,
                             densities=[frame_density(f.points, geometry)[2] for f in fs], faults=faults))
    return rows


def peer_row(first: TimedRow, first_net: PointPillars, peer: str) -> TimedRow:
    """The peer's row: Open3D-ML's PointPillars built like our ``first`` row's (dense) model with its weights, fed its
    frames. Raises :class:`InputError` if Open3D-ML is missing or the architectures differ."""
    peer_net = open3d_peer.build_peer(first.cfg.model, first_net)
    # looked up per call, not bound here: the module's timer is the one that runs (tests spy on it)
    return first._replace(name=open3d_peer.PEER_NAME, weights=f"{first.name}'s weights, copied: {first.weights}",
                          peer=peer, timer=lambda pts: open3d_peer.time_peer_frame(peer_net, pts), faults=None)


def warm_up(rows: Sequence[TimedRow], frames: int, bar: tqdm) -> None:
    """Run every row's timer on its first ``frames`` frames, untimed (kernels, caches and the allocator settle)."""
    for i in range(frames):
        for row in rows:
            row.timer(row.frames[i].points)
        bar.update(1)


def time_rows(rows: Sequence[TimedRow], trials: int, bar: tqdm) -> Timings:
    """``trials`` timed passes over every row's frames, the rows interleaved per frame with the order alternating
    from frame to frame; page faults counted around each call (``back_to_back`` None)."""
    k, n = len(rows), len(rows[0].frames)
    trial_means = np.zeros((k, trials, len(COMPONENTS)))
    per_frame = np.zeros((k, trials, n, len(COMPONENTS)))
    faults = np.zeros((k,), dtype=np.int64)
    dets = np.zeros((k,), dtype=np.int64)
    for row in rows:  # per-component counts of the timed passes only (the warm-up filled them too)
        if row.faults is not None:
            row.faults.clear()
    for t in range(trials):
        bar.set_description(f"bench trial {t + 1}/{trials}")
        for i in range(n):
            order = range(k) if (t * n + i) % 2 == 0 else reversed(range(k))  # alternate who goes first
            for j in order:
                f0 = page_faults()
                ms, nd = rows[j].timer(rows[j].frames[i].points)
                faults[j] += page_faults() - f0
                dets[j] += nd
                per_frame[j, t, i] = [ms[c] for c in COMPONENTS]
            bar.update(1)
        trial_means[:, t] = per_frame[:, t].mean(axis=1)
    return Timings(per_frame=per_frame, trial_means=trial_means, faults=faults, detections=dets, back_to_back=None)


def time_back_to_back(nets: Sequence[PointPillars], rows: Sequence[TimedRow], trials: int, device: torch.device,
                      bar: tqdm) -> np.ndarray:
    """``trials`` passes of :func:`detector.bench.timing.time_shared` over our rows' frames, the first model rotated
    from frame to frame: (models, trials, shared components) ms, per trial the mean over frames."""
    n = len(rows[0].frames)
    back = np.zeros((len(nets), trials, len(SHARED)))
    for t in range(trials):
        bar.set_description(f"bench back to back {t + 1}/{trials}")
        back[:, t] = np.mean([time_shared(nets, [r.frames[i].points for r in rows], device, (t * n + i) % len(nets))
                              for i in range(n)], axis=0)
        bar.update(n)
    return back


def model_record(row: TimedRow, j: int, timings: Timings) -> ModelResult:
    """The record of row ``j``: mean ± std over trials per component, back to back (ours, two or more models),
    median / min single-frame ms, detections, page faults and the median density per frame."""
    means, frames = timings.trial_means[j], timings.per_frame[j]
    count = frames.shape[0] * frames.shape[1]  # trials x frames
    back = None if row.peer is not None or timings.back_to_back is None else timings.back_to_back[j]
    return ModelResult(
        name=row.name,
        peer=row.peer,
        runtime=row.runtime,
        precision=row.precision,
        config=str(row.model.config),
        weights=row.weights,
        backbone=row.cfg.model.backbone,
        head=row.cfg.model.head,
        output_shape=tuple(row.cfg.model.output_shape),
        components={key: Stat(float(means[:, ci].mean()), float(means[:, ci].std()))
                    for ci, key in enumerate(COMPONENTS)},
        back_to_back=None if back is None else {
            key: Stat(float(back[:, si].mean()), float(back[:, si].std())) for si, key in enumerate(SHARED)},
        median_frame_ms={key: float(np.median(frames[:, :, ci])) for ci, key in enumerate(COMPONENTS)},
        min_frame_ms={key: float(frames[:, :, ci].min()) for ci, key in enumerate(COMPONENTS)},
        detections_per_frame=float(timings.detections[j]) / count,
        page_faults_per_frame=float(timings.faults[j]) / count,
        page_faults_per_frame_by_component=None if not row.faults else {
            key: row.faults.get(key, 0) / count for key in COMPONENTS},
        density_median=float(np.median(row.densities)),
    )


def density_record(row: TimedRow) -> BenchDensity:
    """:func:`density_summary` of a row's frames plus the grid they were counted on (range, pillar size in m, canvas
    cells)."""
    m = row.cfg.model
    return BenchDensity(**density_summary(row.densities), geometry=DensityGrid(
        tuple(m.point_cloud_range), tuple(m.voxel_size), tuple(m.output_shape)))


def protocol_record(first: TimedRow, data_dir: str | Path, split: str, peer: str | None, trials: int, warmup: int,
                    back_to_back: bool, variant: Variant = Variant()) -> BenchProtocol:
    """How the result was measured: data, split, the ``first`` row's frames, peer, trials, warm-up frames, batch,
    interleaving, the components timed back to back (none with a single model), what the std is over, the runtimes
    and precisions asked for and the int8 calibration frames."""
    return BenchProtocol(
        data=str(data_dir), split=split, frames=len(first.frames), frame_ids=tuple(f.frame_id for f in first.frames),
        peer=peer, trials=trials, warmup=warmup, batch_size=1, interleaved=True,
        back_to_back=tuple(SHARED) if back_to_back else (),
        workspace="every eager model of ours reuses its inference buffers (PointPillars.workspace)",
        std="population std over trials of the per-trial mean over frames",
        runtimes=tuple(variant.runtimes), precisions=tuple(variant.precisions),
        calibration=({"split": variant.calibration_split, "frames": variant.calibration_frames}
                     if "int8" in variant.precisions else None))


def machine_record(device: torch.device, peer: str | None, variant: Variant = Variant()) -> BenchMachine:
    """:meth:`detector.device.Machine.here`, the CPU's native bf16 / int8 flags, the library of the eager fp32 GEMMs
    (:func:`detector.ops.gemm.library`), and the versions of Open3D (when a peer ran) and of the deployed runtimes
    asked for."""
    versions = {}
    if peer is not None:
        import open3d

        versions["open3d"] = open3d.__version__
    for runtime in set(variant.runtimes) - {"torch"}:
        from detector.deploy.extra import require

        versions[runtime] = require(runtime, f"--runtime {runtime}").__version__
    flags = {p: tuple(f) for p, f in precision_flags(cpu_flags()).items()}
    return BenchMachine(machine=Machine.here(device), precision_flags=flags,
                        gemm=gemm_library(), versions=versions)
