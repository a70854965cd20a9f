"""``detector export``'s output folder: the graph file(s) and ``deploy.json``, which says what they are.

``DIR/model.onnx`` (``--format onnx``) or ``DIR/model.xml`` + ``model.bin`` (``--format openvino``), fp32 or int8
(quantized over calibration frames, :mod:`detector.deploy.quantize`), and ``DIR/deploy.json``: the format, the
precision, the model (config, backbone, head, weights), the graph's inputs and output (names, dtypes, shapes, with
the dynamic site counts named ``n0``.. ``n3``) and the versions. The folder is filled under a hidden work name,
checked (:func:`verify_export`: every file the graph refers to is inside it, and the graph loads) and swapped into
place when everything is written, under a lock, so a failed or killed export leaves no partial folder (the next
export removes a killed one's work folder). Only a folder ``detector export`` made (:mod:`mpchair.core.owned`'s
marker, or an older export whose ``deploy.json`` lists every file it holds) is replaced; anything else is refused.
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
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
from mpchair.core.owned import check_replaceable, clear_leftovers, replace_folder, work_dir

MANIFEST = "deploy.json"
#: The command named in the export folder's ownership marker.
COMMAND = "detector export"
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
    out = export_path(Path(out_dir))
    check_output(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with folder_lock(out.parent / f".{out.name}.export.lock", "detector export", folder=out):
        clear_leftovers(out, COMMAND, legacy=_legacy_export)
        try:
            work = work_dir(out.parent, f".{out.name}.work", COMMAND)
            try:
                return _export_into(work, out, eager, cfg, fmt, precision, frames, config=config,
                                    checkpoint=checkpoint, data=data, calibration_split=calibration_split, seed=seed)
            finally:
                shutil.rmtree(work, ignore_errors=True)
        except OSError as e:
            if e.filename is not None and f"{os.sep}.{out.name}.work" not in str(e.filename):
                raise
            # a write in the hidden work folder (a full disk): name the export asked for, not the work folder
            raise OSError(e.errno, f"{e.strerror or e}; nothing was replaced", str(out)) from None


def _export_into(work: Path, out: Path, eager, cfg, fmt: str, precision: str, frames: list, *, config, checkpoint,
                 data, calibration_split: str, seed: int) -> ExportRecord:
    """Write the graph in ``work``, gather it (with every file it refers to) and ``deploy.json`` in ``work/stage``,
    verify them and swap the stage in at ``out``."""
    graph = write_graph(eager, fmt, precision, work / "graph", calibration=frames, seed=seed)
    inputs, output = _io_records(work / "graph" / "fp32.onnx")
    stage = work / "stage"
    stage.mkdir()
    files = [GRAPH_FILES[fmt]]
    for extra in _external_files(graph, fmt):  # ONNX weights stored outside the graph (a model over 2 GiB)
        os.replace(graph.parent / extra, stage / extra)
        files.append(extra)
    os.replace(graph, stage / files[0])
    if fmt == "openvino":
        files.append("model.bin")
        os.replace(graph.with_suffix(".bin"), stage / "model.bin")
    record = ExportRecord(
        format=fmt, precision=precision, files=files, config=str(config), backbone=cfg.model.backbone,
        head=cfg.model.head, weights=str(checkpoint) if checkpoint else f"random (seed {seed}; untrained)",
        inputs=inputs, output=output,
        calibration=({"data": str(data), "split": calibration_split, "frames": len(frames)} if frames else None),
        opset=OPSET, versions=_versions(fmt, precision))
    write_text(stage / MANIFEST, json.dumps(asdict(record), indent=2) + "\n")
    verify_export(stage, fmt, files, shown=out)
    replace_folder(stage, out, COMMAND, legacy=_legacy_export)
    return record


def export_path(out: Path) -> Path:
    """Where the export goes: ``out``, or the folder a symlink ``out`` names (the link then names the new export)."""
    return Path(os.path.realpath(out)) if out.is_symlink() else out


def _legacy_export(folder: Path) -> set[str] | None:
    """The files of an export written before ownership markers: its ``deploy.json`` lists them. None when ``folder``
    holds no such ``deploy.json``."""
    try:
        meta = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    files = meta.get("files") if isinstance(meta, dict) else None
    if not isinstance(files, list) or not files or not all(isinstance(f, str) and "/" not in f for f in files):
        return None
    return {*files, MANIFEST}


def check_output(out: Path) -> None:
    """:class:`InputError` unless ``out`` can become an export folder: missing, empty, or an export this command made
    (nothing added to it), in a writable folder. Anything else is never replaced."""
    check_replaceable(export_path(out), COMMAND, legacy=_legacy_export)
    check_writable(export_path(out), folder=True)


def _external_files(graph: Path, fmt: str) -> list[str]:
    """The files an ONNX graph keeps its weights in besides itself (relative to its folder; none below 2 GiB)."""
    if fmt != "onnx":
        return []
    onnx = require("onnx", "ONNX export")
    from onnx.external_data_helper import _get_all_tensors, uses_external_data

    model = onnx.load(str(graph), load_external_data=False)
    names = []
    for t in _get_all_tensors(model):
        if uses_external_data(t):
            loc = next((e.value for e in t.external_data if e.key == "location"), "")
            if loc and loc not in names:
                names.append(loc)
    return names


def verify_export(folder: Path, fmt: str, files: list[str], *, shown: Path | None = None) -> None:
    """Check a written export before it is reported: every file it lists is a regular file inside ``folder``, every
    file the graph refers to is one of them, and the graph loads (ONNX: the checker over the file, external data
    included; OpenVINO: the weights file is not empty). A failure is an error naming the folder, never a ``wrote``
    line; weights that are not all finite give a warning. Both name ``shown`` (default ``folder``): the export asked
    for, when ``folder`` is the hidden stage it is checked in (a user never sees that name)."""
    shown = folder if shown is None else shown
    for name in files:
        path = folder / name
        if path.is_symlink() or not path.is_file() or path.resolve().parent != folder.resolve():
            raise InputError(f"the export did not produce {name} inside the folder; nothing was replaced", shown)
    if fmt == "onnx":
        onnx = require("onnx", "ONNX export")
        graph = folder / files[0]
        outside = [f for f in _external_files(graph, fmt) if f not in files]
        if outside:
            raise InputError(f"the graph refers to {outside[0]}, which is not in the export; nothing was replaced",
                             shown)
        try:
            onnx.checker.check_model(str(graph))
            model = onnx.load(str(graph), load_external_data=True)
        except Exception as e:  # the checker's own error types differ by version
            raise InputError(f"the written graph does not load ({type(e).__name__}: {str(e).splitlines()[0]}); "
                             "nothing was replaced", shown) from None
        from onnx.numpy_helper import to_array

        bad = [t.name for t in model.graph.initializer if not _finite(to_array(t))]
    else:
        if (folder / "model.bin").stat().st_size == 0:
            raise InputError("the written OpenVINO weights file model.bin is empty; nothing was replaced", shown)
        bad = []
    if bad:
        warnings.warn(f"{shown}: the exported weights hold NaN or infinite values ({bad[0]}"
                      + (f" and {len(bad) - 1} more tensors" if len(bad) > 1 else "") + "): the model will not "
                      "detect anything; was the checkpoint trained with a diverging loss?", stacklevel=2)


def _finite(a) -> bool:
    import numpy as np

    return a.dtype.kind not in "fc" or bool(np.isfinite(a).all())
