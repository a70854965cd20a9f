"""How far the sparse backbone + neck is from its limit: its exact work at the rate oneDNN's dense convolution reaches
on the same machine, measured in one run (issue 49, target 2: within 2x of the limit).

One run (``tools/bench_limit.py``), on the frames of :func:`limit_frames` (default: clustered synthetic sites at the
paper's Matterport-Chair median D on the 768 x 512 grid of ``mpchair_sparse.yaml``, the network the CPU configs
train), prints and returns (:class:`LimitResult`):

- **work** (:func:`frame_work`, from ``detector.opcount``): per frame and per layer, the *exact* multiply-adds (only
  products of an active input site with a weight tap that lands on an active output site: SubM (site, active
  neighbour) pairs, one tap per down-conv input, one tap per neck target with an active parent; x ``C_in C_out``),
  the *GEMM form*'s (what ``detector.sparse`` multiplies, zero rows of absent neighbours and unused transposed slots
  included) and the *executed* ones (the GEMM form at oneDNN's bucketed row counts, ``detector.ops.gemm.bucket_rows``,
  where the products run in oneDNN);
- **the dense rate**, per thread count: ``F.conv2d`` of one 3 x 3 stride-1 layer per block of the dense backbone (its
  shapes on this grid: ``C_i`` channels at ``H / 2^i x W / 2^i``, channels-last as the dense model's canvas, fp32),
  MACs over median time; the rate is all three layers' MACs over their summed medians;
- **the sparse time**, per thread count: the model's ``backbone_neck`` (the paper's Backbone timer: tables, blocks,
  neck, todense and the active mask; a fresh ``SparseTensor`` per call so every table is built; fp32, eager, with
  its inference workspace), interleaved with the dense convs in every repeat (:func:`detector.bench.timing.
  time_calls`), median per frame; the **limit** of a frame is its exact MACs at the dense rate, and the **ratio**
  time / limit (the target: at most :data:`TARGET_RATIO`), median over frames;
- **the profile**, per thread count: ``profile_repeats`` more passes over the frames with a
  :class:`detector.sparse.phases.PhaseRecorder` (table building, gathers, GEMMs, BN / ReLU, scatter, and ``other``:
  the Python between them); the phases plus ``other`` sum to the profiled wall time by construction, and their sum
  per frame is checked against the unprofiled mean time within :data:`PHASE_TOLERANCE` (the timers' own cost and
  run-to-run noise). The GEMM phase's rate (executed MACs over its time) sits beside oneDNN's conv rate.

JSON (``--json-out``, :meth:`LimitResult.to_json`): ``{"header", "frames", "layers", "runs", "summary"}``; header:
:data:`HEADER_KEYS`; each frame :class:`FrameWork`'s fields; each layer :class:`LayerWork`'s; each run
:class:`ThreadRun`'s (its ``dense`` a list of :class:`ConvRate`, its ``phases`` of :class:`PhaseRow`); summary:
:data:`SUMMARY_KEYS`. Times in ms, rates in GMAC/s (1e9 multiply-adds per second), MACs as integers. Numbers from
a busy machine are not the instrument's: run it on a quiet one (docs/sparse.md, "The limit").
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from detector.bench.spconv_peer import SiteFrame, dataset_frames, randomise_batchnorm_, synthetic_frames
from detector.bench.timing import time_calls
from detector.checkpoint import load_model
from detector.config import ExperimentConfig, load_experiment
from detector.device import load_1m, machine_info, oversubscription_warning, usable_cores, use_device
from detector.models import PointPillars
from detector.opcount import LayerCount, sparse_counts
from detector.ops.gemm import bucket_rows, library
from detector.sparse.phases import OTHER, PHASES, PhaseRecorder, recording
from detector.sparse.workspace import Workspace
from mpchair.core.atomic import check_writable, write_text
from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError
from mpchair.paper import MATTERPORT_CHAIR_DENSITY

#: The issue's target: the sparse backbone + neck within this factor of its exact MACs at oneDNN's conv rate.
TARGET_RATIO = 2.0
#: How far the profile's phase sum (phases + ``other``, mean per frame) may lie from the unprofiled mean time.
PHASE_TOLERANCE = 0.10
#: The default network and grid: the paper's 768 x 512 Matterport-Chair geometry (the CPU configs' network).
DEFAULT_CONFIG = "mpchair_sparse"
HEADER_KEYS = ("config", "checkpoint", "grid", "frames_source", "weights", "precision", "runtime", "gemm_library",
               "threads", "repeats", "profile_repeats", "warmup", "target_ratio", "phase_tolerance", "machine",
               "warnings")
SUMMARY_KEYS = ("exact_macs_median", "gemm_macs_median", "executed_macs_median", "gemm_over_exact", "ratio",
                "meets_target", "phases_within_tolerance")


@dataclass(frozen=True)
class FrameWork:
    """One frame's work: ``pillars`` input sites at density ``density`` (sites / grid cells), the active sites after
    each block (``sites``), and multiply-adds (exact, GEMM form, executed; module docstring)."""

    name: str
    pillars: int
    density: float
    sites: tuple[int, ...]
    exact_macs: int
    gemm_macs: int
    executed_macs: int


@dataclass(frozen=True)
class LayerWork:
    """One conv layer's multiply-adds, mean over the frames: ``kind`` as ``detector.opcount.LayerCount.kind``."""

    name: str
    kind: str
    c_in: int
    c_out: int
    exact_macs: float
    gemm_macs: float


@dataclass(frozen=True)
class ConvRate:
    """A dense 3 x 3 stride-1 conv of ``channels`` -> ``channels`` on a ``height`` x ``width`` map (batch 1, fp32,
    channels-last): ``macs`` per call, median ``ms``, ``gmacs`` = GMAC/s."""

    channels: int
    height: int
    width: int
    macs: int
    median_ms: float
    gmacs: float


@dataclass(frozen=True)
class PhaseRow:
    """One phase of the profile: mean ``ms`` per frame, ``share`` of the phases' sum, entries per frame."""

    phase: str
    ms: float
    share: float
    calls: float


@dataclass(frozen=True)
class ThreadRun:
    """Everything measured at one thread count (module docstring); ``ratio`` and ``ratio_gemm_form`` are medians over
    frames of time / (MACs / ``dense_gmacs``); ``phase_gap`` = phase sum / ``sparse_mean_ms`` - 1."""

    threads: int
    dense: tuple[ConvRate, ...]
    dense_gmacs: float
    sparse_median_ms: float
    sparse_mean_ms: float
    frame_median_ms: tuple[float, ...]
    limit_ms: float
    ratio: float
    ratio_gemm_form: float
    phases: tuple[PhaseRow, ...]
    phase_sum_ms: float
    phase_gap: float
    phases_within_tolerance: bool
    gemm_phase_gmacs: float


@dataclass(frozen=True)
class LimitResult:
    """A run's result; :meth:`to_json` is the one definition of the tool's JSON."""

    header: dict
    frames: tuple[FrameWork, ...]
    layers: tuple[LayerWork, ...]
    runs: tuple[ThreadRun, ...]

    def summary(self) -> dict:
        """:data:`SUMMARY_KEYS`: median MACs per frame, the ratio per thread count, whether each meets the target and
        each profile's phases sum to its time within the tolerance."""
        exact = statistics.median(f.exact_macs for f in self.frames)
        gemm = statistics.median(f.gemm_macs for f in self.frames)
        return {
            "exact_macs_median": exact,
            "gemm_macs_median": gemm,
            "executed_macs_median": statistics.median(f.executed_macs for f in self.frames),
            "gemm_over_exact": gemm / max(exact, 1),
            "ratio": {str(r.threads): r.ratio for r in self.runs},
            "meets_target": {str(r.threads): r.ratio <= TARGET_RATIO for r in self.runs},
            "phases_within_tolerance": {str(r.threads): r.phases_within_tolerance for r in self.runs},
        }

    def to_json(self) -> dict:
        return {"header": self.header, "frames": [asdict(f) for f in self.frames],
                "layers": [asdict(lw) for lw in self.layers], "runs": [asdict(r) for r in self.runs],
                "summary": self.summary()}


# --- work ----------------------------------------------------------------------------------------------------------

def executed_macs(layer: LayerCount, onednn: bool) -> int:
    """``layer.macs_computed`` at oneDNN's bucketed row count (:func:`detector.ops.gemm.bucket_rows`) where
    ``onednn`` and the layer runs its GEMM form: rows = sites (SubM), outputs (down-conv), coarse sites (a
    transposed conv; + the appended zero row when it writes another site set), each row ``k^2 C_in C_out`` MACs.
    A rulebook form's count is not bucketed."""
    width = layer.kernel**2 * layer.c_in * layer.c_out
    if layer.kind in ("subm", "sparse_down"):
        rows = gemm_rows = layer.out_sites
    elif layer.kind == "sparse_convT":
        gemm_rows = layer.in_sites
        rows = gemm_rows + (1 if layer.kernel > 1 else 0)
    else:
        return layer.macs_computed
    if not onednn or layer.macs_computed != gemm_rows * width or gemm_rows == 0:
        return layer.macs_computed
    return bucket_rows(rows) * width


def frame_work(model: PointPillars, cfg: ExperimentConfig, frame: SiteFrame) -> tuple[FrameWork, list[LayerCount]]:
    """The work of ``frame`` through ``model``'s sparse backbone + neck (module docstring), float32, autograd off."""
    layers = sparse_counts(model, frame.coords, cfg.model)
    onednn = library() == "onednn"
    ny, nx = cfg.model.output_shape
    n = int(frame.coords.shape[0])
    return FrameWork(
        name=frame.name, pillars=n, density=n / (ny * nx),
        sites=tuple(lc.out_sites for lc in layers if lc.kind == "sparse_down"),
        exact_macs=sum(lc.macs for lc in layers), gemm_macs=sum(lc.macs_computed for lc in layers),
        executed_macs=sum(executed_macs(lc, onednn) for lc in layers),
    ), layers


def mean_layers(per_frame: Sequence[Sequence[LayerCount]]) -> tuple[LayerWork, ...]:
    """Per layer (same order in every frame), the mean exact and GEMM-form MACs over the frames."""
    out = []
    for same in zip(*per_frame):
        lc = same[0]
        out.append(LayerWork(lc.name, lc.kind, lc.c_in, lc.c_out, statistics.fmean(x.macs for x in same),
                             statistics.fmean(x.macs_computed for x in same)))
    return tuple(out)


# --- frames and model ------------------------------------------------------------------------------------------

def limit_frames(net: PointPillars, cfg: ExperimentConfig, *, data: str | Path | None, split: str, frames: int,
                 density: float, seed: int) -> tuple[list[SiteFrame], str]:
    """(frames, a description): the first ``frames`` frames of ``split`` of ``data`` through ``net``'s voxelizer and
    pillar net, or (``data`` None) ``frames`` clustered synthetic site sets at ``density`` on the config's grid with
    features in [0, 1) (:func:`detector.bench.spconv_peer.synthetic_frames`, seeded ``seed + k``)."""
    if data is not None:
        out = dataset_frames(net, cfg, str(data), split, frames)
        if not out:
            raise InputError(f"no frames in the {split} split", data)
        return out, f"{len(out)} frame(s) of {data} {split}"
    shape = (int(cfg.model.output_shape[0]), int(cfg.model.output_shape[1]))
    return (synthetic_frames(shape, density, frames, cfg.model.pfn_channels, seed),
            f"{frames} synthetic clustered frame(s) at D {density:g}")


def dense_shapes(cfg: ExperimentConfig) -> tuple[tuple[int, int, int], ...]:
    """``(channels, height, width)`` of one stride-1 3 x 3 conv per block of the dense backbone on the config's grid
    (block i: ``layer_channels[i]`` at the grid halved ``i + 1`` times)."""
    ny, nx = cfg.model.output_shape
    return tuple((int(c), int(ny) >> (i + 1), int(nx) >> (i + 1)) for i, c in enumerate(cfg.model.layer_channels))


def dense_calls(shapes: Sequence[tuple[int, int, int]], seed: int) -> dict[str, Callable[[], object]]:
    """One ``F.conv2d`` call per shape (random input and weight, seeded; fp32; channels-last), named ``dense_CxHxW``."""
    g = torch.Generator().manual_seed(seed)
    calls: dict[str, Callable[[], object]] = {}
    for c, h, w in shapes:
        x = torch.rand(1, c, h, w, generator=g).contiguous(memory_format=torch.channels_last)
        weight = (torch.randn(c, c, 3, 3, generator=g) * 0.05).contiguous(memory_format=torch.channels_last)
        calls[f"dense_{c}x{h}x{w}"] = lambda x=x, weight=weight: F.conv2d(x, weight, padding=1)
    return calls


def sparse_call(net: PointPillars, frame: SiteFrame) -> Callable[[], object]:
    """``net``'s Backbone on ``frame``: a fresh ``SparseTensor`` (so every table is built), then ``backbone_neck``."""
    return lambda: net.backbone_neck(net.feature_net(frame.features, frame.coords, 1))


def conv_macs(c: int, h: int, w: int) -> int:
    """MACs of a ``c`` -> ``c`` 3 x 3 stride-1 padded conv on an ``h`` x ``w`` map."""
    return h * w * 9 * c * c


# --- measurement -------------------------------------------------------------------------------------------------

@torch.no_grad()
def profile_phases(net: PointPillars, frames: Sequence[SiteFrame], repeats: int) -> tuple[PhaseRecorder, int]:
    """``repeats`` passes of :func:`sparse_call` over ``frames`` with a :class:`PhaseRecorder`: (the recorder, the
    number of forwards)."""
    rec = PhaseRecorder()  # CPU: an op has finished when it returns, so no synchronisation
    calls = [sparse_call(net, f) for f in frames]
    with recording(rec):
        for _ in range(repeats):
            for call in calls:
                rec.begin()
                call()
                rec.end()
    return rec, repeats * len(calls)


def phase_rows(rec: PhaseRecorder, forwards: int) -> tuple[tuple[PhaseRow, ...], float]:
    """(the rows of :data:`PHASES` and ``other``, mean ms per forward; their sum in ms)."""
    names = (*PHASES, OTHER)
    total = sum(rec.seconds[k] for k in names)
    rows = tuple(PhaseRow(k, 1e3 * rec.seconds[k] / forwards, rec.seconds[k] / total if total else 0.0,
                          rec.calls[k] / forwards) for k in names)
    return rows, 1e3 * total / forwards


@torch.no_grad()
def measure_threads(net: PointPillars, frames: Sequence[SiteFrame], work: Sequence[FrameWork],
                    shapes: Sequence[tuple[int, int, int]], *, threads: int, repeats: int, profile_repeats: int,
                    warmup: int, seed: int) -> ThreadRun:
    """Everything at ``threads`` threads (module docstring): the dense convs and the sparse frames interleaved in
    every repeat, then the profile."""
    use_device("cpu", threads)
    calls = dense_calls(shapes, seed)
    names = [f"sparse_{i}" for i in range(len(frames))]
    calls.update({n: sparse_call(net, f) for n, f in zip(names, frames)})
    times = time_calls(calls, repeats, warmup=warmup)
    dense = tuple(ConvRate(c, h, w, conv_macs(c, h, w), times[f"dense_{c}x{h}x{w}"]["median_ms"],
                           conv_macs(c, h, w) / (1e6 * max(times[f"dense_{c}x{h}x{w}"]["median_ms"], 1e-9)))
                  for c, h, w in shapes)
    rate = sum(d.macs for d in dense) / (1e6 * sum(d.median_ms for d in dense))  # GMAC/s
    frame_ms = [times[n]["median_ms"] for n in names]
    limit = [fw.exact_macs / (1e6 * rate) for fw in work]  # ms
    sparse_mean = statistics.fmean(frame_ms)
    rec, forwards = profile_phases(net, frames, profile_repeats)
    rows, phase_sum = phase_rows(rec, forwards)
    gap = phase_sum / sparse_mean - 1 if sparse_mean > 0 else 0.0
    gemm_ms = next(r.ms for r in rows if r.phase == "gemm")
    executed = statistics.fmean(fw.executed_macs for fw in work)
    return ThreadRun(
        threads=threads, dense=dense, dense_gmacs=rate, sparse_median_ms=statistics.median(frame_ms),
        sparse_mean_ms=sparse_mean, frame_median_ms=tuple(frame_ms), limit_ms=statistics.median(limit),
        ratio=statistics.median(t / max(lim, 1e-12) for t, lim in zip(frame_ms, limit)),
        ratio_gemm_form=statistics.median(t * rate * 1e6 / max(fw.gemm_macs, 1) for t, fw in zip(frame_ms, work)),
        phases=rows, phase_sum_ms=phase_sum, phase_gap=gap, phases_within_tolerance=abs(gap) <= PHASE_TOLERANCE,
        gemm_phase_gmacs=executed / (1e6 * gemm_ms) if gemm_ms > 0 else 0.0,
    )


@dataclass(frozen=True)
class LimitOptions:
    """What one run measures (the tool's options; module docstring)."""

    config: str = DEFAULT_CONFIG
    checkpoint: str | None = None
    data: Path | None = None
    split: str = "test"
    frames: int = 8
    density: float = MATTERPORT_CHAIR_DENSITY.median
    threads: tuple[int, ...] = (1, 2)
    repeats: int = 7
    profile_repeats: int = 3
    warmup: int = 2
    seed: int = 0


def check_options(opts: LimitOptions) -> None:
    """:class:`InputError` (one line) for options no run can use."""
    if opts.frames < 1 or opts.repeats < 1 or opts.profile_repeats < 1 or opts.warmup < 0:
        raise InputError(f"need --frames, --repeats and --profile-repeats >= 1 and --warmup >= 0, got "
                         f"{opts.frames}, {opts.repeats}, {opts.profile_repeats}, {opts.warmup}")
    if not 0 < opts.density <= 1:
        raise InputError(f"--density must be in (0, 1], got {opts.density}")
    if not opts.threads or min(opts.threads) < 1:
        raise InputError(f"--threads must be positive integers, got {list(opts.threads)}")


def run_limit(opts: LimitOptions) -> LimitResult:
    """One run of the instrument (module docstring)."""
    check_options(opts)
    cfg = load_experiment(opts.config)
    if cfg.model.backbone != "sparse":
        raise InputError(f"needs the all-sparse model (backbone: sparse), the config has {cfg.model.backbone!r}",
                         opts.config)
    device = use_device("cpu", opts.threads[0])
    net = load_model(cfg, opts.checkpoint, device, seed=opts.seed).eval()
    if opts.checkpoint is None:
        randomise_batchnorm_(net.backbone, opts.seed)
    frames, source = limit_frames(net, cfg, data=opts.data, split=opts.split, frames=opts.frames,
                                  density=opts.density, seed=opts.seed)
    counted = [frame_work(net, cfg, f) for f in frames]
    work = [w for w, _ in counted]
    net.workspace = Workspace()
    shapes = dense_shapes(cfg)
    runs, warnings = [], []
    for t in opts.threads:
        w = oversubscription_warning(t, usable_cores(), load_1m())
        if w:
            warnings.append(w)
        runs.append(measure_threads(net, frames, work, shapes, threads=t, repeats=opts.repeats,
                                    profile_repeats=opts.profile_repeats, warmup=opts.warmup, seed=opts.seed))
    header = {
        "config": str(opts.config), "checkpoint": opts.checkpoint, "grid": list(cfg.model.output_shape),
        "frames_source": source, "weights": opts.checkpoint or f"random (seed {opts.seed}, BatchNorm seeded)",
        "precision": "float32", "runtime": "eager PyTorch, inference workspace", "gemm_library": library(),
        "threads": list(opts.threads), "repeats": opts.repeats, "profile_repeats": opts.profile_repeats,
        "warmup": opts.warmup, "target_ratio": TARGET_RATIO, "phase_tolerance": PHASE_TOLERANCE,
        "machine": machine_info(device), "warnings": warnings,
    }
    return LimitResult(header, tuple(work), mean_layers([layers for _, layers in counted]), tuple(runs))


# --- report --------------------------------------------------------------------------------------------------------

def _m(macs: float) -> str:
    return f"{macs / 1e6:,.1f} M"


def format_limit(result: LimitResult) -> str:
    """The report: header, work per frame, then per thread count the rate, the time, the ratio and the profile."""
    h, s = result.header, result.summary()
    m = h["machine"]
    lines = [f"# the limit (issue 49, target 2): {h['frames_source']}, grid {h['grid'][0]} x {h['grid'][1]}, "
             f"config {h['config']}, weights {h['weights']}",
             f"# {h['precision']}, {h['runtime']}, GEMMs in {h['gemm_library']}; {m.get('cpu')}; load average (1 min) "
             f"{m.get('loadavg_1m')}; {h['repeats']} interleaved repeats, {h['profile_repeats']} profiled", "",
             "| frame | pillars | D | sites after blocks 1-3 | exact MACs | GEMM-form MACs | executed MACs |",
             "|---|---|---|---|---|---|---|"]
    for f in result.frames:
        lines.append(f"| {f.name} | {f.pillars} | {f.density:.5f} | {' / '.join(map(str, f.sites))} | "
                     f"{_m(f.exact_macs)} | {_m(f.gemm_macs)} | {_m(f.executed_macs)} |")
    lines += ["", f"exact MACs per frame (median): {_m(s['exact_macs_median'])}; GEMM form {_m(s['gemm_macs_median'])}"
              f" ({s['gemm_over_exact']:.2f}x exact); executed {_m(s['executed_macs_median'])}", ""]
    for r in result.runs:
        convs = ", ".join(f"{d.channels}ch {d.height}x{d.width} {d.gmacs:.1f}" for d in r.dense)
        lines += [f"## {r.threads} thread(s)",
                  f"oneDNN dense conv rate: {r.dense_gmacs:.1f} GMAC/s ({convs} GMAC/s)",
                  f"sparse backbone + neck: median {r.sparse_median_ms:.2f} ms (mean {r.sparse_mean_ms:.2f}); limit "
                  f"(exact MACs at that rate) {r.limit_ms:.2f} ms; **ratio {r.ratio:.2f}x** (target <= "
                  f"{TARGET_RATIO:g}x: {'met' if r.ratio <= TARGET_RATIO else 'not met'}); against the GEMM form's "
                  f"MACs {r.ratio_gemm_form:.2f}x", "",
                  "| phase | ms per frame | share | entries per frame |", "|---|---|---|---|"]
        lines += [f"| {p.phase} | {p.ms:.3f} | {100 * p.share:.1f} % | {p.calls:.0f} |" for p in r.phases]
        lines += [f"| sum | {r.phase_sum_ms:.3f} | | |", "",
                  f"phase sum vs unprofiled mean: {100 * r.phase_gap:+.1f} % (tolerance +-{100 * PHASE_TOLERANCE:.0f}"
                  f" %: {'within' if r.phases_within_tolerance else 'OUTSIDE'}); GEMM phase at "
                  f"{r.gemm_phase_gmacs:.1f} GMAC/s of executed MACs ({r.gemm_phase_gmacs / r.dense_gmacs:.0%} of "
                  "the dense conv rate)", ""]
    lines += [f"warning: {w}" for w in h["warnings"]]
    return "\n".join(lines).rstrip()


# --- command line ------------------------------------------------------------------------------------------------

class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are one-line :class:`InputError` s (exit 2 through ``run_script``)."""

    def error(self, message: str):  # type: ignore[override]
        raise InputError(f"{self.prog}: {message}")


def parse_threads(text: str) -> tuple[int, ...]:
    """``"1,2"`` → ``(1, 2)``; an :class:`InputError` for anything but positive integers."""
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        values = ()
    if not values or min(values) < 1:
        raise InputError(f"--threads must be a comma-separated list of positive integers, got {text!r}")
    return values


def parser() -> argparse.ArgumentParser:
    """The options of ``tools/bench_limit.py``."""
    p = _Parser(prog="bench_limit.py", description=__doc__.splitlines()[0])
    p.add_argument("--config", default=DEFAULT_CONFIG, help=f"sparse experiment config, name or YAML (default "
                   f"{DEFAULT_CONFIG}: the 768 x 512 Matterport-Chair grid)")
    p.add_argument("--checkpoint", default=None, help="its weights (default: seeded random weights)")
    p.add_argument("--data", type=Path, default=None, help="KITTI-format dataset: time its frames instead of "
                   "synthetic ones")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--density", type=float, default=MATTERPORT_CHAIR_DENSITY.median,
                   help="synthetic sites' density D (default: the paper's Matterport-Chair median)")
    p.add_argument("--threads", default="1,2", help="thread counts, comma-separated (default 1,2)")
    p.add_argument("--repeats", type=int, default=7, help="timed, interleaved passes (default 7)")
    p.add_argument("--profile-repeats", type=int, default=3, help="profiled passes (default 3)")
    p.add_argument("--warmup", type=int, default=2, help="untimed passes first (default 2)")
    p.add_argument("--seed", type=int, default=0, help="random weights', sites' and dense inputs' seed")
    p.add_argument("--json-out", type=Path, default=None, help="also write the result as JSON to this file")
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the instrument, print its report (and write its JSON); 2 with one ``error:`` line on bad input."""
    return run_script(lambda: _main(argv))


def _main(argv: list[str] | None) -> int:
    args = parser().parse_args(argv)
    opts = LimitOptions(config=args.config, checkpoint=args.checkpoint, data=args.data, split=args.split,
                        frames=args.frames, density=args.density, threads=parse_threads(args.threads),
                        repeats=args.repeats, profile_repeats=args.profile_repeats, warmup=args.warmup,
                        seed=args.seed)
    check_options(opts)
    if args.json_out is not None:
        check_writable(args.json_out)
    result = run_limit(opts)
    if args.json_out is not None:
        write_text(args.json_out, json.dumps(result.to_json(), indent=2) + "\n")
    print(format_limit(result))
    return 0
