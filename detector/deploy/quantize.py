"""Post-training int8 quantization of an exported graph from calibration frames (the paper's future work,
"quantization in tandem with our pipeline").

- OpenVINO: NNCF (``nncf.quantize``) on the IR, the performance preset (symmetric int8 weights per output channel,
  int8 activations per tensor), its statistics gathered by running the calibration frames. The quantized IR runs its
  convolutions / MatMuls in int8 (VNNI or AMX-INT8 kernels).
- ONNX Runtime: ``onnxruntime.quantization.quantize_static`` in QDQ format, per-channel int8 weights, uint8
  activations, MinMax calibration over the same frames; only Conv / ConvTranspose / MatMul are quantized (a Gather
  of the sparse graph moves rows and gains nothing from int8), and not the head: the quantizer would give its output
  one uint8 scale shared by the class logits, the seven box residuals and the direction logits (256 steps over the
  widest of those ranges, so the narrower residuals get few steps), which cost the dense model 12 3D AP points on the
  2026-12-03 run and 0.16 with the head in fp32, same weights (``docs/results.md``). The head is a 1x1 conv (a MatMul
  over the active sites in the sparse graph), ~0.1 % of the dense backbone's MACs, so fp32 there should cost little
  (its latency is not re-measured); NNCF already leaves the output layer's result in fp32 (no quantizer on a graph
  output).

Calibration frames are graph feeds (``{input name: array}``) made from real frames by the same pre-processing as
inference (:meth:`detector.deploy.deployed.DeployedPointPillars.graph_feed`), so the sparse graph sees real site
counts and real neighbour tables.
"""

from __future__ import annotations

import contextlib
import io
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from detector.deploy.extra import require

Feed = dict[str, np.ndarray]


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Hold back the quantizers' chatter: NNCF draws progress bars on stdout (where a bench table goes) and ONNX
    Runtime's quantizer logs advice on the root logger; errors still raise."""
    logging.disable(logging.WARNING)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        logging.disable(logging.NOTSET)


def quantize_openvino(onnx_path: Path, xml_path: Path, calibration: Sequence[Feed]) -> None:
    """NNCF int8 quantization of the ONNX graph at ``onnx_path`` over ``calibration`` feeds → IR at ``xml_path``."""
    if not calibration:
        raise ValueError("int8 quantization needs at least one calibration frame")
    ov = require("openvino", "int8 quantization for OpenVINO")
    nncf = require("nncf", "int8 quantization for OpenVINO")
    model = ov.convert_model(str(onnx_path))
    with _quiet():
        quantized = nncf.quantize(model, nncf.Dataset(list(calibration)),
                                  preset=nncf.QuantizationPreset.PERFORMANCE, subset_size=len(calibration))
    ov.save_model(quantized, str(xml_path), compress_to_fp16=False)


QUANTIZED_OPS = ("Conv", "ConvTranspose", "MatMul")


def head_nodes(model) -> list[str]:
    """Names of the quantizable nodes (:data:`QUANTIZED_OPS`) whose result reaches a graph output through
    non-quantizable ops only (bias Add, Transpose, Reshape): the detection head of an exported ONNX ``model``."""
    producer = {out: node for node in model.graph.node for out in node.output}
    found: list[str] = []
    todo = [o.name for o in model.graph.output]
    seen: set[str] = set()
    while todo:
        node = producer.get(todo.pop())
        if node is None or node.name in seen:
            continue
        seen.add(node.name)
        if node.op_type in QUANTIZED_OPS:
            found.append(node.name)
        else:
            todo.extend(node.input)
    return found


def quantize_onnx(onnx_path: Path, out_path: Path, calibration: Sequence[Feed]) -> None:
    """ONNX Runtime static int8 quantization (QDQ) of ``onnx_path`` over ``calibration`` feeds → ``out_path``."""
    if not calibration:
        raise ValueError("int8 quantization needs at least one calibration frame")
    q = require("onnxruntime.quantization", "int8 quantization for ONNX Runtime")

    class Reader(q.CalibrationDataReader):
        """The calibration feeds, one per ``get_next``, then None."""

        def __init__(self) -> None:
            self.feeds = iter(calibration)

        def get_next(self) -> Feed | None:
            return next(self.feeds, None)

    onnx = require("onnx", "int8 quantization for ONNX Runtime")
    head = head_nodes(onnx.load(str(onnx_path), load_external_data=False))
    with _quiet():
        q.quantize_static(str(onnx_path), str(out_path), Reader(), quant_format=q.QuantFormat.QDQ,
                          per_channel=True, activation_type=q.QuantType.QUInt8, weight_type=q.QuantType.QInt8,
                          op_types_to_quantize=list(QUANTIZED_OPS), nodes_to_exclude=head,
                          calibrate_method=q.CalibrationMethod.MinMax)
