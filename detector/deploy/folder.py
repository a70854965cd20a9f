"""``detector export``'s output folder: the graph file(s) and ``deploy.json``, which says what they are.

``DIR/model.onnx`` (``--format onnx``) or ``DIR/model.xml`` + ``model.bin`` (``--format openvino``), fp32 or int8
(quantized over calibration frames, :mod:`detector.deploy.quantize`), and ``DIR/deploy.json``: the format, the
precision, the model (config, backbone, head, weights), the graph's inputs and output (names, dtypes, shapes, with
the dynamic site counts named ``n0``.. ``n3``) and the versions. The folder is filled under a temporary name and
renamed into place when everything is written (an older export there is replaced), under a lock, so a failed or
killed export leaves no partial folder.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from detector.checkpoint import load_model
from detector.config import load_experiment
from detector.data.experiment import load_eval_frames
from detector.deploy.deployed import write_graph
from detector.deploy.export import FORMATS, GRAPH_FILES, OPSET, graph_module
from detector.deploy.extra import require
from mpchair.core.atomic import check_writable, write_text
from mpchair.core.errors import InputError
from mpchair.core.lock import folder_lock

MANIFEST = "deploy.json"
EXPORT_PRECISIONS = ("fp32", "int8")


@dataclass(frozen=True)
class ExportRecord:
    """What ``deploy.json`` holds (see the module docstring)."""

    format: str
    precision: str
    files: list[str]
    config: str
    backbone: str
    head: str
    weights: str
    inputs: list[dict]
    output: dict
    calibration: dict | None
    opset: int
    versions: dict[str, str]


def _io_records(path: Path) -> tuple[list[dict], dict]:
    """Names, element types and shapes (dynamic axes by name) of an ONNX file's inputs and first output."""
    onnx = require("onnx", "ONNX export")
    graph = onnx.load(str(path), load_external_data=False).graph

    def record(v) -> dict:
        t = v.type.tensor_type
        dims = [d.dim_param or d.dim_value for d in t.shape.dim]
        return {"name": v.name, "dtype": onnx.helper.tensor_dtype_to_np_dtype(t.elem_type).name, "shape": dims}

    return [record(v) for v in graph.input], record(graph.output[0])


def _versions(fmt: str, precision: str) -> dict[str, str]:
    """The versions of the packages that made the files."""
    out = {"torch": torch.__version__, "onnx": require("onnx", "ONNX export").__version__}
    if fmt == "openvino":
        out["openvino"] = require("openvino", "OpenVINO export").__version__
        if precision == "int8":
            out["nncf"] = require("nncf", "int8 quantization for OpenVINO").__version__
    elif precision == "int8":
        out["onnxruntime"] = require("onnxruntime", "int8 quantization for ONNX Runtime").__version__
    return out


def export_folder(config: str | Path, checkpoint: str | Path | None, fmt: str, out_dir: str | Path, *,
                  precision: str = "fp32", data: str | Path | None = None, calibration_split: str = "train",
                  calibration_frames: int = 8, seed: int = 0) -> ExportRecord:
    """Export the network of ``config`` (trained weights from ``checkpoint``, or seeded random ones) as ``fmt`` in
    ``precision`` into ``out_dir``; int8 calibrates on the first ``calibration_frames`` frames of
    ``calibration_split`` of ``data``. Returns what ``deploy.json`` records."""
    if fmt not in FORMATS:
        raise InputError(f"unknown format {fmt!r} (choose from {', '.join(FORMATS)})")
    if precision not in EXPORT_PRECISIONS:
        raise InputError(f"export precision {precision!r}: choose fp32 or int8 (bf16 is chosen when OpenVINO compiles "
                         "the fp32 graph: detector bench / eval --runtime openvino --precision bf16)")
    if precision == "int8" and (data is None or calibration_frames < 1):
        raise InputError("--precision int8 needs calibration frames: --data DATASET (and --calibration-frames >= 1)")
    require("onnx", "ONNX export")
    if fmt == "openvino":
        require("openvino", "OpenVINO export")
    cfg = load_experiment(config)
    eager = load_model(cfg, checkpoint, "cpu", seed=seed)
    try:
        graph_module(eager)  # refuses the sparse + dense ablations before any file is written
    except ValueError as e:
        raise InputError(f"cannot export this model: {e}", config) from None
    frames = ([f.points for f in load_eval_frames(cfg, data, calibration_split, calibration_frames)]
              if precision == "int8" else [])
    out = Path(out_dir)
    check_output(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with folder_lock(out.parent / f".{out.name}.export.lock", "detector export"), \
            tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.work") as work:
        graph = write_graph(eager, fmt, precision, work, calibration=frames, seed=seed)
        inputs, output = _io_records(Path(work) / "fp32.onnx")
        stage = Path(work) / "stage"
        stage.mkdir()
        files = [GRAPH_FILES[fmt]]
        os.replace(graph, stage / files[0])
        if fmt == "openvino":
            files.append("model.bin")
            os.replace(graph.with_suffix(".bin"), stage / files[1])
        record = ExportRecord(
            format=fmt, precision=precision, files=files, config=str(config), backbone=cfg.model.backbone,
            head=cfg.model.head,
            weights=str(checkpoint) if checkpoint else f"random (seed {seed}; untrained)", inputs=inputs,
            output=output,
            calibration=({"data": str(data), "split": calibration_split, "frames": len(frames)} if frames else None),
            opset=OPSET, versions=_versions(fmt, precision))
        write_text(stage / MANIFEST, json.dumps(asdict(record), indent=2) + "\n")
        _swap_in(stage, out)
    return record


def check_output(out: Path) -> None:
    """:class:`InputError` unless ``out`` can become an export folder: missing, empty, or an older export (it holds
    ``deploy.json``), in a writable folder. Anything else is never replaced."""
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a folder", out)
    if out.is_dir() and any(out.iterdir()) and not (out / MANIFEST).is_file():
        raise InputError(f"folder is not empty and holds no {MANIFEST} (not an export to replace); choose another "
                         "--out", out)
    check_writable(out, folder=True)


def _swap_in(stage: Path, out: Path) -> None:
    """Rename the finished ``stage`` folder to ``out``, replacing an older folder there."""
    if out.exists():
        old = out.parent / f".{out.name}.old{os.getpid()}"
        out.rename(old)
        stage.rename(out)
        shutil.rmtree(old)
    else:
        stage.rename(out)
