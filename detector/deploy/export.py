"""Export a PointPillars network to ONNX (and from there to OpenVINO IR): what ``detector export`` writes.

The exported graph is the network between the pre- and post-processing that stay in Python, as every PointPillars
deployment keeps them (voxelization, pillar net, scatter, box decoding and NMS):

- dense model: :class:`~detector.deploy.dense_graph.DenseGraph`, canvas (1, C, ny, nx) → ``head`` (1, O, H, W);
- all-sparse model: :class:`~detector.deploy.sparse_graph.SparseGraph`, pillar features + the rulebook tables of
  :func:`~detector.deploy.sparse_graph.build_tables` → ``head_rows`` (N_1, O) (exact sparse head) or ``head``
  (dense head), every site count a dynamic dimension.

ONNX comes from ``torch.onnx.export``'s TorchScript tracer (opset 17): the graphs have no data-dependent control flow
(the tables are inputs), so a trace is the whole graph, and it needs no package beyond ``onnx``. OpenVINO IR is
converted from that ONNX file (``openvino.convert_model``), so both runtimes run the same graph.
"""

from __future__ import annotations

import errno
import os
import shutil
import warnings
from pathlib import Path

import torch
from torch import Tensor, nn

from detector.deploy.dense_graph import DenseGraph
from detector.deploy.extra import require
from detector.deploy.sparse_graph import SparseGraph, build_tables
from detector.models import PointPillars
from detector.sparse.synthetic import clustered_sites

FORMATS: tuple[str, ...] = ("onnx", "openvino")
#: The graph file of each format inside an export folder (OpenVINO's weights sit beside it in ``model.bin``).
GRAPH_FILES: dict[str, str] = {"onnx": "model.onnx", "openvino": "model.xml"}
OPSET = 17
#: Density of the synthetic sites a sparse graph is traced on (only the shapes matter: every site count is dynamic).
TRACE_DENSITY = 0.01


def graph_module(model: PointPillars) -> DenseGraph | SparseGraph:
    """The exportable network of ``model`` (eval mode, BatchNorm folded): dense or all-sparse backbone."""
    return SparseGraph(model) if model.sparse_input else DenseGraph(model)


def graph_inputs(graph: DenseGraph | SparseGraph, features: Tensor, coords: Tensor) -> dict[str, Tensor]:
    """The graph's inputs for one frame's pillar ``features`` (P, C) at ``coords`` (P, 3) int64 ``[0, iy, ix]``:
    the NCHW canvas (dense) or the features and rulebook tables (sparse)."""
    if isinstance(graph, SparseGraph):
        return build_tables(graph.spec, features, coords).inputs
    from detector.models.scatter import scatter_to_canvas

    return {"canvas": scatter_to_canvas(features, coords, 1, graph.canvas_shape, channels_last=False)}


def example_inputs(model: PointPillars, graph: DenseGraph | SparseGraph, seed: int = 0) -> dict[str, Tensor]:
    """Inputs to trace ``graph`` with: random pillar features on :data:`TRACE_DENSITY` of ``model``'s canvas
    (clustered sites, :func:`detector.sparse.synthetic.clustered_sites`); the values do not matter, only the shapes.

    The sites sit at even coordinates: ``downsample: reference_quirk`` rounds an odd coordinate up, which on an
    unpadded grid's last row would fall off the grid (a real frame of such a config stays inside its padding)."""
    ny, nx = model.output_shape
    coords = clustered_sites((ny // 2, nx // 2), TRACE_DENSITY, seed=seed) * torch.tensor([1, 2, 2])
    gen = torch.Generator().manual_seed(seed)
    features = torch.randn(coords.shape[0], model.pillar_encoder.out_channels, generator=gen)
    return graph_inputs(graph, features, coords)


def _dynamic_axes(names: list[str], output: str, sparse: bool) -> dict[str, dict[int, str]]:
    """Every sparse input's first axis is its block's site count (``n0`` pillars, ``n1``... after block i), but
    ``canvas_rows``'s, one entry per cell of the head map (static)."""
    if not sparse:
        return {}
    axes: dict[str, dict[int, str]] = {}
    for name in names:
        if name == "features":
            axes[name] = {0: "n0"}
        elif name.startswith(("down", "subm")):  # down{i}, subm{i}_k{k}: block i's sites
            axes[name] = {0: f"n{name[4]}"}
        elif name.startswith("up"):  # up{i}: one row per block-1 site
            axes[name] = {0: "n1"}
    if output == "head_rows":
        axes[output] = {0: "n1"}
    return axes


def write_onnx(model: PointPillars, path: Path, seed: int = 0) -> tuple[list[str], str]:
    """Trace ``model``'s graph and write it to ``path`` (ONNX, opset :data:`OPSET`); returns (input names, output
    name)."""
    require("onnx", "ONNX export")
    graph = graph_module(model)
    feed = example_inputs(model, graph, seed)
    names = list(feed)
    output = graph.spec.output_name if isinstance(graph, SparseGraph) else "head"
    with warnings.catch_warnings():
        # torch >= 2.9 calls the TorchScript exporter legacy; it traces these loop-free graphs completely and needs
        # no onnxscript, so its deprecation notice would only be noise on the command line
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", UserWarning)
        torch.onnx.export(_Positional(graph), tuple(feed.values()), str(path), input_names=names,
                          output_names=[output], dynamic_axes=_dynamic_axes(names, output, isinstance(graph,
                                                                                                       SparseGraph)),
                          opset_version=OPSET, do_constant_folding=True, dynamo=False)
    return names, output


class _Positional(nn.Module):
    """The graph with positional inputs (what the tracer feeds), the dense one taking its single canvas."""

    def __init__(self, graph: DenseGraph | SparseGraph) -> None:
        super().__init__()
        self.graph = graph

    def forward(self, *inputs: Tensor) -> Tensor:
        return self.graph(*inputs)


def write_openvino(onnx_path: Path, xml_path: Path) -> None:
    """Convert an ONNX graph to OpenVINO IR at ``xml_path`` (weights in the ``.bin`` beside it, fp32 kept: the
    precision is chosen when the model is compiled, :mod:`detector.deploy.runtimes`)."""
    ov = require("openvino", "OpenVINO export")
    model = ov.convert_model(str(onnx_path))
    try:
        ov.save_model(model, str(xml_path), compress_to_fp16=False)
    except RuntimeError as e:
        # OpenVINO's C++ writer reports a failed write as a bare "basic_ios::clear: iostream error" (no errno, no
        # file); its .bin holds the weights, about the ONNX file's size, so less room than that is a full disk
        room = shutil.disk_usage(xml_path.parent).free
        if room < onnx_path.stat().st_size:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(xml_path)) from None
        raise OSError(errno.EIO, f"OpenVINO could not write the model ({' '.join(str(e).split())[:200]})",
                      str(xml_path)) from None
