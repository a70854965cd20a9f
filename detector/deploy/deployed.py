"""A PointPillars whose network runs as an exported graph in ONNX Runtime or OpenVINO, with the eager pre- and
post-processing around it, and the same stage methods as :class:`detector.models.PointPillars`.

So ``detector bench`` times a deployed model with the same stamps (:func:`detector.bench.timing.time_frame`) and
``detector eval`` predicts with it through the same :func:`detector.infer.evaluate_model`. The stages, by the paper's
timers:

| stage (timer) | deployed model |
|---|---|
| Feature Extract | the eager ``voxelize`` + ``pillar_net`` (torch) |
| Feature Net | the graph's inputs: the NCHW canvas (dense; torch scatter), or the rulebook tables (sparse;
  :func:`detector.deploy.sparse_graph.build_tables`) |
| Backbone | the graph: backbone + neck + head (one runtime call) |
| Head | the head maps from the graph's output: a view (dense head), or the bias-filled map with the active rows
  scattered in (exact sparse head, as :class:`detector.models.head.SparseExactHead`) |
| BBox Extract | the eager ``postprocess`` (decode + rotated NMS) |

Batch 1: a batch of B point clouds runs frame by frame.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from detector.checkpoint import load_model
from detector.config import ExperimentConfig
from detector.data.experiment import load_eval_frames
from detector.deploy.cpu import cpu_flags, skip_reason
from detector.deploy.export import graph_inputs, graph_module, write_onnx, write_openvino
from detector.deploy.quantize import quantize_onnx, quantize_openvino
from detector.deploy.runtimes import GraphSession, open_session
from detector.deploy.sparse_graph import SparseGraph, SparseSpec, build_tables
from detector.models import Detections, HeadOutput, PointPillars
from detector.models.voxelizer import Voxels
from mpchair.core.errors import InputError


class GraphFeed(NamedTuple):
    """One frame's graph inputs (numpy, as the runtimes take them) and, for the sparse graph, the block-1 sites
    ``(N_1, 3)`` where the head rows land (None for the dense graph)."""

    arrays: dict[str, np.ndarray]
    sites: torch.Tensor | None


class DeployedPointPillars(nn.Module):
    """``eager``'s pre- and post-processing around ``session``, the exported network (see the module docstring).

    ``runtime`` / ``precision`` are what the bench and the evaluation record (e.g. ``openvino`` / ``bf16``)."""

    def __init__(self, eager: PointPillars, session: GraphSession, runtime: str, precision: str) -> None:
        super().__init__()
        self.eager = eager.eval()
        self.session = session
        self.runtime, self.precision = runtime, precision
        graph = graph_module(eager)
        self.spec: SparseSpec | None = graph.spec if isinstance(graph, SparseGraph) else None
        self._graph = graph  # builds the feeds (tables / canvas); its weights are the session's, folded
        _, bias = eager.anchor_head.fused()
        self.register_buffer("head_bias", bias.detach().clone(), persistent=False)
        self.head_shape = _head_shape(eager, self.spec)

    # --- Feature Extract: eager ------------------------------------------------------------------------------
    def voxelize(self, points_list: Sequence[torch.Tensor]) -> Voxels:
        """As :meth:`PointPillars.voxelize` (test pillar cap)."""
        return self.eager.voxelize(points_list)

    def pillar_net(self, voxels: Voxels) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`PointPillars.pillar_net`."""
        return self.eager.pillar_net(voxels)

    # --- Feature Net: the graph's inputs ---------------------------------------------------------------------
    def feature_net(self, features: torch.Tensor, coords: torch.Tensor, batch_size: int) -> GraphFeed:
        """Pillar features (P, C) at coords (P, 3) ``[0, iy, ix]`` → the graph's inputs (batch 1)."""
        if batch_size != 1:
            raise ValueError(f"a deployed model runs batch 1, got {batch_size}")
        if isinstance(self._graph, SparseGraph):
            tables = build_tables(self._graph.spec, features, coords)
            return GraphFeed({k: v.numpy() for k, v in tables.inputs.items()}, tables.sites)
        return GraphFeed({k: v.numpy() for k, v in graph_inputs(self._graph, features, coords).items()}, None)

    def graph_feed(self, points: np.ndarray) -> GraphFeed:
        """One frame's points (N, C) float32, sensor frame → its graph inputs (calibration frames for int8)."""
        voxels = self.voxelize([torch.from_numpy(points)])
        features, coords = self.pillar_net(voxels)
        return self.feature_net(features, coords, 1)

    # --- Backbone: the graph -------------------------------------------------------------------------------------
    def backbone_neck(self, x: GraphFeed) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The runtime call: ``(graph output, block-1 sites or None)``; a frame without pillars gives the bias map
        (every site inactive) without a call."""
        if x.sites is not None and x.sites.shape[0] == 0:
            h, w = self.head_shape
            return self.head_bias[None, :, None, None].expand(1, -1, h, w).contiguous(), None
        return torch.from_numpy(self.session.run(x.arrays)), x.sites

    # --- Head: the maps ---------------------------------------------------------------------------------------------
    def head(self, x: torch.Tensor, active: torch.Tensor | None = None) -> HeadOutput:
        """Graph output → :class:`HeadOutput` ((1, H, W, C) views of one channel-planar map)."""
        if x.dim() == 4:  # (1, O, H, W): the dense head's map, or an empty frame's bias map
            return self.eager.anchor_head.split(x.permute(0, 2, 3, 1))
        # exact sparse head: (N_1, O) rows on the block-1 sites, the bias everywhere else
        h, w = self.head_shape
        out = self.head_bias[None, :, None, None].expand(1, -1, h, w).clone()
        out[0, :, active[:, 1], active[:, 2]] = x.t()
        return self.eager.anchor_head.split(out.permute(0, 2, 3, 1))

    # --- BBox Extract: eager -------------------------------------------------------------------------------------
    def postprocess(self, cls: torch.Tensor, reg: torch.Tensor, dir: torch.Tensor) -> list[Detections]:
        """As :meth:`PointPillars.postprocess` (sensor-frame boxes)."""
        return self.eager.postprocess(cls, reg, dir)

    def forward(self, points_list: Sequence[torch.Tensor]) -> list[HeadOutput]:
        """Point clouds (N_i, C) (sensor frame, m) → head maps per frame."""
        outs = []
        for pts in points_list:
            voxels = self.voxelize([pts])
            features, coords = self.pillar_net(voxels)
            outs.append(self.head(*self.backbone_neck(self.feature_net(features, coords, 1))))
        return outs

    @torch.no_grad()
    def predict(self, points_list: Sequence[torch.Tensor]) -> list[Detections]:
        """All five stages, frame by frame (as :meth:`PointPillars.predict`)."""
        return [self.postprocess(*out)[0] for out in self.forward(points_list)]


def calibration_feeds(eager: PointPillars, frames: Sequence[np.ndarray]) -> list[dict[str, np.ndarray]]:
    """The graph inputs of calibration ``frames`` (points (N, C) float32, sensor frame), made by the inference
    pre-processing (pillar net, scatter or rulebook tables)."""
    probe = DeployedPointPillars(eager, _NoSession(), "none", "fp32")
    with torch.no_grad():
        return [probe.graph_feed(p).arrays for p in frames]


def write_graph(eager: PointPillars, fmt: str, precision: str, work_dir: str | Path, *,
                calibration: Sequence[np.ndarray] = (), seed: int = 0) -> Path:
    """Write ``eager``'s network in ``fmt`` (``onnx`` | ``openvino``) for ``precision`` into ``work_dir`` and return
    the graph file: the fp32 graph for fp32 and bf16 (bf16 is chosen when OpenVINO compiles it), the int8 graph
    quantized over the ``calibration`` frames (points (N, C) float32, sensor frame) for int8."""
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        return _write_graph(eager, fmt, precision, work, calibration, seed)
    except OSError as e:
        if e.filename is None:  # torch.onnx / onnx write to an open file (a full disk) and name none: name the folder
            e.filename = str(work)
        raise


def _write_graph(eager: PointPillars, fmt: str, precision: str, work: Path, calibration: Sequence[np.ndarray],
                 seed: int) -> Path:
    onnx_path = work / "fp32.onnx"
    with torch.no_grad():
        write_onnx(eager, onnx_path, seed=seed)
    if precision == "int8":
        if not calibration:
            raise ValueError("int8 needs calibration frames")
        feeds = calibration_feeds(eager, calibration)
        path = work / ("int8.xml" if fmt == "openvino" else "int8.onnx")
        (quantize_openvino if fmt == "openvino" else quantize_onnx)(onnx_path, path, feeds)
        return path
    if fmt == "openvino":
        path = work / "fp32.xml"
        write_openvino(onnx_path, path)
        return path
    return onnx_path


@contextlib.contextmanager
def graph_work_dir(prefix: str) -> Iterator[Path]:
    """A temporary folder (in ``TMPDIR``) for the graphs a command exports for itself (``bench``, ``eval --runtime``),
    removed afterwards. A write that fails in it (a full ``TMPDIR``) is an ``OSError`` naming the file or folder and
    saying that it is the temporary folder, so the user knows which disk to free or which ``TMPDIR`` to set."""
    with tempfile.TemporaryDirectory(prefix=prefix) as work:
        try:
            yield Path(work)
        except OSError as e:
            name = "" if e.filename is None else str(e.filename)
            if name != work and not name.startswith(work + "/"):
                raise
            raise OSError(e.errno, f"{e.strerror or e} (a temporary folder for the exported graphs: free space there "
                          "or set TMPDIR to a folder with room)", name) from None


def build_deployed(eager: PointPillars, runtime: str, precision: str, work_dir: str | Path, *, threads: int,
                   calibration: Sequence[np.ndarray] = (), seed: int = 0) -> DeployedPointPillars:
    """Export ``eager``'s network into ``work_dir`` (:func:`write_graph`, the runtime's own format) and open it in
    ``runtime`` (``onnxruntime`` | ``openvino``) in ``precision`` on ``threads`` threads."""
    fmt = "openvino" if runtime == "openvino" else "onnx"
    path = write_graph(eager, fmt, precision, work_dir, calibration=calibration, seed=seed)
    return DeployedPointPillars(eager, open_session(path, runtime, precision, threads), runtime, precision)


def _head_shape(eager: PointPillars, spec: SparseSpec | None) -> tuple[int, int]:
    """(H, W) of the head map: the pseudo-image at the first block's stride over the first neck level's."""
    if spec is not None:
        return spec.head_shape
    ny, nx = eager.output_shape
    s = eager.backbone.blocks[0][0].stride[0] // eager.neck.deblocks[0][0].stride[0]
    return ny // s, nx // s


class _NoSession:
    """The session of a model that only builds feeds (calibration), never runs."""

    def run(self, feed: dict[str, np.ndarray]) -> np.ndarray:
        raise RuntimeError("this deployed model only builds graph inputs")


def deploy_checkpoint(cfg: ExperimentConfig, checkpoint: str | Path | None, runtime: str, precision: str,
                      work_dir: str | Path, *, threads: int, data: str | Path | None = None,
                      calibration_split: str = "train", calibration_frames: int = 8,
                      seed: int = 0) -> DeployedPointPillars:
    """The model of experiment ``cfg`` (weights from ``checkpoint``, or seeded random ones) deployed in ``runtime`` /
    ``precision`` (:func:`build_deployed`, files in ``work_dir``); int8 calibrates on the first
    ``calibration_frames`` frames of ``calibration_split`` of ``data``. A combination this CPU does not compute
    natively, or a model the export cannot take, is an :class:`InputError`."""
    why = skip_reason(runtime, precision, cpu_flags())
    if why is not None:
        raise InputError(f"cannot run {runtime} {precision} here: {why}")
    eager = load_model(cfg, checkpoint, "cpu", seed=seed)
    frames = []
    if precision == "int8":
        if data is None or calibration_frames < 1:
            raise InputError("int8 needs calibration frames (a dataset and --calibration-frames >= 1)")
        frames = [f.points for f in load_eval_frames(cfg, data, calibration_split, calibration_frames)]
    try:
        return build_deployed(eager, runtime, precision, work_dir, threads=threads, calibration=frames, seed=seed)
    except ValueError as e:
        raise InputError(f"cannot deploy this model: {e}") from None
