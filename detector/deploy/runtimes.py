"""Run an exported graph in ONNX Runtime or OpenVINO: one session per model, one output, numpy in and out.

Both sessions run on ``threads`` intra-op threads and one stream (batch 1, latency), the way ``detector bench`` runs
the eager models (``torch.set_num_threads``):

- ONNX Runtime: the CPU execution provider, every graph optimisation, sequential execution, and its thread pool's
  spin-wait off (``session.intra_op.allow_spinning = 0``): a pool that spins after each run takes a core from the
  next row of an interleaved benchmark, and from the robot's other processes.
- OpenVINO: the CPU plugin with ``INFERENCE_PRECISION_HINT`` set explicitly (f32 or bf16: on CPUs with AMX it
  picks bf16 by default), the LATENCY hint, one stream and no CPU pinning (the eager rows pin nothing either). An int8
  model (NNCF's quantized IR) runs its quantized ops in int8 and the rest in f32.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from detector.deploy.extra import require

#: OpenVINO's ``INFERENCE_PRECISION_HINT`` of each bench precision (int8 comes from the quantized model itself).
OPENVINO_HINTS: dict[str, str] = {"fp32": "f32", "bf16": "bf16", "int8": "f32"}


class GraphSession(Protocol):
    """A compiled graph: ``run({input name: array})`` → its one output (valid until the next ``run``)."""

    def run(self, feed: dict[str, np.ndarray]) -> np.ndarray: ...


def onnxruntime_options(threads: int):
    """ONNX Runtime's ``SessionOptions`` as the module docstring says: ``threads`` intra-op threads, sequential, every
    graph optimisation, no spin-wait, errors only."""
    ort = require("onnxruntime", "--runtime onnxruntime")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.log_severity_level = 3  # errors only: its shape-inference notes are not ours to print
    return options


class OnnxRuntimeSession:
    """An ONNX file in ONNX Runtime's CPU execution provider on ``threads`` threads."""

    def __init__(self, path: str | Path, threads: int) -> None:
        ort = require("onnxruntime", "--runtime onnxruntime")
        options = onnxruntime_options(threads)
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        self.output = self.session.get_outputs()[0].name

    def run(self, feed: dict[str, np.ndarray]) -> np.ndarray:
        return self.session.run([self.output], feed)[0]


class OpenVinoSession:
    """An ONNX or IR file compiled by OpenVINO's CPU plugin in ``precision`` on ``threads`` threads."""

    def __init__(self, path: str | Path, precision: str, threads: int) -> None:
        ov = require("openvino", "--runtime openvino")
        config = {
            "INFERENCE_PRECISION_HINT": OPENVINO_HINTS[precision],
            "INFERENCE_NUM_THREADS": int(threads),
            "PERFORMANCE_HINT": "LATENCY",
            "NUM_STREAMS": 1,
            "ENABLE_CPU_PINNING": False,
        }
        self.compiled = ov.Core().compile_model(str(path), "CPU", config)
        self.request = self.compiled.create_infer_request()
        self.precision = str(self.compiled.get_property("INFERENCE_PRECISION_HINT"))

    def run(self, feed: dict[str, np.ndarray]) -> np.ndarray:
        # inputs and the output share memory with the arrays (no copies); the output is overwritten by the next run
        self.request.infer(feed, share_inputs=True, share_outputs=True)
        return self.request.get_output_tensor(0).data


def open_session(path: str | Path, runtime: str, precision: str, threads: int) -> GraphSession:
    """A :class:`GraphSession` of the graph at ``path`` in ``runtime`` (``onnxruntime`` | ``openvino``)."""
    if runtime == "onnxruntime":
        return OnnxRuntimeSession(path, threads)
    if runtime == "openvino":
        return OpenVinoSession(path, precision, threads)
    raise ValueError(f"unknown deployed runtime {runtime!r}")
