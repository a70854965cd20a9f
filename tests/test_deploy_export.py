"""Exported networks equal the eager ones: the dense graph (BatchNorm folded) and the sparse graph over rulebook tables
given as inputs, in ONNX Runtime and OpenVINO, fp32, within 1e-4 on the head maps (random weights with perturbed
BatchNorm statistics, and a briefly trained model); what the sparse graph holds; ``detector export``'s folder."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_detector import detector_cli as _cli
from helpers_detector import make_tiny_dataset, write_test_config
from helpers_tools import load_tool

from detector.checkpoint import load_model
from detector.config import load_experiment
from detector.data.experiment import load_eval_frames
from detector.deploy.deployed import build_deployed
from detector.deploy.export import write_onnx
from detector.deploy.quantize import QUANTIZED_OPS, head_nodes
from detector.deploy.sparse_graph import SparseGraph, build_tables
from detector.models import build_model
from detector.sparse.synthetic import clustered_sites

pytest.importorskip("onnxruntime")
pytest.importorskip("openvino")
onnx = pytest.importorskip("onnx")

DENSE = "detector/configs/mpchair_dense_smoke.yaml"
SPARSE = "detector/configs/mpchair_sparse_smoke.yaml"
RUNTIMES = ("onnxruntime", "openvino")
TOL = 1e-4


@pytest.fixture(scope="module")
def slim(tmp_path_factory) -> dict[str, Path]:
    """The smoke geometry (96 x 64) with the tests' slim network (32/32/64 channels, one conv per block): configs of
    the dense and the sparse model."""
    base = tmp_path_factory.mktemp("slim")
    return {b: write_test_config(base / f"{b}.yaml", model=dict(backbone=b)) for b in ("dense", "sparse")}


def _model(config: str | Path, seed: int = 0, **overrides):
    """A model in eval mode with seeded random weights and BatchNorm statistics away from (0, 1), so a wrongly folded
    BatchNorm shows."""
    cfg = load_experiment(config)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = build_model(dataclasses.replace(cfg.model, **overrides)).eval()
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.data.uniform_(0.5, 1.5)
                m.bias.data.uniform_(-0.3, 0.3)
    return model


def _frames(n: int = 3, seed: int = 0) -> list[np.ndarray]:
    """Point clouds in the smoke configs' range (sensor frame, m): a floor, walls and a few box-shaped clusters, so
    the pillars form clusters and gaps like a scan."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        parts = [np.column_stack([rng.uniform(0.2, 6.2, 1500), rng.uniform(-4.6, 4.6, 1500), rng.normal(-1.0, 0.02,
                                                                                                        1500)])]
        for _ in range(4):
            c = rng.uniform([1.0, -4.0, -1.0], [6.0, 4.0, 0.0])
            parts.append(c + rng.uniform(-0.4, 0.4, (300, 3)))
        out.append(np.concatenate(parts).astype(np.float32))
    return out


def _max_diff(eager, deployed, frames) -> float:
    """max |deployed - eager| over the cls / reg / dir maps of every frame."""
    worst = 0.0
    with torch.no_grad():
        for pts in frames:
            ref = eager.forward([torch.from_numpy(pts)])
            out = deployed.forward([torch.from_numpy(pts)])[0]
            assert [t.shape for t in out] == [t.shape for t in ref]
            worst = max(worst, *((a - b).abs().max().item() for a, b in zip(ref, out)))
    return worst


@pytest.mark.parametrize("runtime", RUNTIMES)
@pytest.mark.parametrize("kind, overrides", [
    ("dense", {}),
    ("sparse", {}),                                   # sparse backbone, dense head (scatter + 1x1 over the map)
    ("sparse", {"head": "sparse_exact"}),             # the exact sparse head: rows on the block-1 sites
    ("sparse", {"backbone": "sparse_wide", "head": "sparse_exact"}),       # 9x9 first SubM of every block
    ("sparse", {"backbone": "sparse_wide_down", "head": "sparse_exact"}),  # 9x9 stride-2 down-convs
], ids=["dense", "sparse", "sparse-exact", "sparse-wide", "sparse-wide-down"])
def test_fp32_export_equals_eager_on_the_head_maps(runtime, kind, overrides, slim, tmp_path):
    model = _model(slim[kind], **overrides)
    deployed = build_deployed(model, runtime, "fp32", tmp_path, threads=1)
    assert _max_diff(model, deployed, _frames()) <= TOL


@pytest.mark.slow
@pytest.mark.parametrize("config, head", [(DENSE, "dense"), (SPARSE, "sparse_exact")], ids=["dense", "sparse-exact"])
def test_the_full_architecture_exports_exactly(config, head, tmp_path):
    """The paper's widths and depths (64/128/256 channels, 3/5/5 layers) on the smoke grid, in both runtimes."""
    model = _model(config, head=head)
    for runtime in RUNTIMES:
        deployed = build_deployed(model, runtime, "fp32", tmp_path / runtime, threads=1)
        assert _max_diff(model, deployed, _frames(2)) <= TOL, runtime


@pytest.mark.slow
def test_a_trained_model_exports_exactly(tmp_path):
    """A few training steps move every weight away from its init (BatchNorm running statistics included)."""
    from detector.train import train

    data = make_tiny_dataset(tmp_path / "ds", n_frames=4, seed=1)
    for backbone, head in (("dense", "dense"), ("sparse", "sparse_exact")):
        cfg_path = write_test_config(tmp_path / f"{backbone}.yaml", model=dict(backbone=backbone, head=head),
                                     train=dict(batch_size=2, epochs=2))
        train(cfg_path, data, tmp_path / backbone, threads=1, progress=False, log=lambda _: None)
        model = load_model(load_experiment(cfg_path), tmp_path / backbone / "last.pt", "cpu")
        untrained = build_model(load_experiment(cfg_path).model)
        moved = [k for k, v in model.state_dict().items() if not torch.equal(v, untrained.state_dict()[k])]
        assert any("running_mean" in k for k in moved) and any("weight" in k for k in moved)
        frames = [f.points for f in load_eval_frames(load_experiment(cfg_path), data, "train", 4)]
        for runtime in RUNTIMES:
            deployed = build_deployed(model, runtime, "fp32", tmp_path / f"{backbone}-{runtime}", threads=1)
            assert _max_diff(model, deployed, frames) <= TOL, (backbone, runtime)


def test_the_sparse_graph_holds_gather_and_matmul_only_with_dynamic_sites(slim, tmp_path):
    model = _model(slim["sparse"], head="sparse_exact")
    path = tmp_path / "sparse.onnx"
    names, output = write_onnx(model, path)
    graph = onnx.load(str(path)).graph
    ops = {n.op_type for n in graph.node}
    assert {"Gather", "MatMul", "Relu"} <= ops
    # none of what the eager code needs when exported as it is (Unique, NonZero, ScatterND, ...), no conv, no loop
    assert not ops & {"Unique", "NonZero", "ScatterND", "ScatterElements", "GatherND", "Conv", "Loop", "If",
                      "TopK", "Where"}, ops
    assert output == "head_rows" and names[0] == "features"
    dims = {i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim] for i in graph.input}
    assert dims["features"] == ["n0", 32] and dims["down1"] == ["n1", 4] and dims["subm3_k3"] == ["n3", 9]
    assert dims["up2"] == ["n1"]
    assert all(i.type.tensor_type.elem_type == onnx.TensorProto.INT64 for i in graph.input if i.name != "features")


@pytest.mark.parametrize("head", ["dense", "sparse_exact"])
def test_the_sparse_graph_computes_no_shapes_at_run_time(head, slim, tmp_path):
    """Every shape but the site counts is a constant: no Shape / ConstantOfShape chain per conv (the zero rows are
    initializers), and the dense head's canvas is one Gather at ``canvas_rows`` (no zero fill + ScatterND, which
    copies the 151 MB Matterport canvas), its 1x1 conv one MatMul giving the planar map without a Transpose after it."""
    model = _model(slim["sparse"], head=head)
    path = tmp_path / "sparse.onnx"
    names, output = write_onnx(model, path)
    graph = onnx.load(str(path)).graph
    ops = [n.op_type for n in graph.node]
    assert not set(ops) & {"Shape", "ConstantOfShape", "ScatterND", "ScatterElements", "Cast", "Div", "Unsqueeze"}, ops
    convs = sum(len(b.subm_kernels) + 1 for b in SparseGraph(model).spec.blocks)
    levels = len(SparseGraph(model).spec.up_strides)
    # one MatMul per conv, per neck level and for the head; one Gather per conv, per upsampled level (and the canvas)
    assert ops.count("MatMul") == convs + levels + 1
    assert ops.count("Gather") == convs + levels - 1 + (head == "dense")
    if head == "dense":
        assert names[-1] == "canvas_rows" and output == "head"
        dims = {i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim] for i in graph.input}
        h, w = SparseGraph(model).spec.head_shape
        assert dims["canvas_rows"] == [h * w]  # one entry per cell of the head map: static
        producer = {o: n for n in graph.node for o in n.output}
        last = producer[graph.output[0].name]
        while last.op_type in ("Reshape", "Add"):
            last = producer[last.input[0]]
        assert last.op_type == "MatMul"


def test_profile_export_graph_prints_node_counts_and_shares(capsys):
    main = load_tool("profile_export_graph").main
    assert main(["--config", SPARSE, "--density", "0.02", "--frames", "1", "--repeats", "1", "--top", "2"]) == 0
    out = capsys.readouterr().out
    assert "exported nodes 168: " in out and "ScatterND" not in out and "Shape" not in out
    shares = [float(line.split()[-2]) for line in out.splitlines() if line.startswith("  ") and line.endswith("%")]
    assert len(shares) >= 4 and all(0 <= x <= 100 for x in shares)


def test_the_canvas_rows_put_every_site_at_its_cell(slim):
    model = _model(slim["sparse"])
    spec = SparseGraph(model).spec
    coords = clustered_sites(model.output_shape, 0.05, seed=5)
    tables = build_tables(spec, torch.zeros(coords.shape[0], 32), coords)
    rows, sites = tables.inputs["canvas_rows"], tables.sites
    h, w = spec.head_shape
    n1 = sites.shape[0]
    assert rows.dtype == torch.int64 and rows.shape == (h * w,)
    assert torch.equal(rows[sites[:, 1] * w + sites[:, 2]], torch.arange(n1))
    assert int((rows == n1).sum()) == h * w - n1  # every other cell: the appended zero row


def test_tables_point_missing_neighbours_at_the_sentinel_row(slim):
    model = _model(slim["sparse"], head="sparse_exact")
    spec = SparseGraph(model).spec
    coords = clustered_sites(model.output_shape, 0.05, seed=3)
    tables = build_tables(spec, torch.zeros(coords.shape[0], 32), coords)
    n1 = tables.inputs["subm1_k3"].shape[0]
    t = tables.inputs["subm1_k3"]
    assert t.dtype == torch.int64 and int(t.max()) == n1 and int(t.min()) >= 0  # n1 = the appended zero row
    assert torch.equal(t[:, 4], torch.arange(n1))  # the centre tap is the site itself
    down = tables.inputs["down1"]
    assert int(down.max()) == coords.shape[0]  # some 2x2 window has an empty cell
    # every pillar lands in exactly one (output, slot) cell of the first down-conv
    real = down[down < coords.shape[0]]
    assert torch.equal(real.sort().values, torch.arange(coords.shape[0]))
    assert tables.sites.shape == (n1, 3)


def test_an_empty_frame_gives_the_bias_maps(slim, tmp_path):
    model = _model(slim["sparse"], head="sparse_exact")
    deployed = build_deployed(model, "onnxruntime", "fp32", tmp_path, threads=1)
    empty = np.zeros((0, 3), dtype=np.float32)
    assert _max_diff(model, deployed, [empty]) <= TOL



def test_export_cli_writes_the_folder_and_its_manifest(slim, tmp_path, capsys):
    out = tmp_path / "exported"
    code, stdout, _ = _cli(["export", "--config", slim["sparse"], "--format", "openvino", "--out", out], capsys)
    assert code == 0 and f"wrote {out}/" in stdout
    assert sorted(p.name for p in out.iterdir()) == [".mpchair-output.json", "deploy.json", "model.bin", "model.xml"]
    record = json.loads((out / "deploy.json").read_text())
    assert record["format"] == "openvino" and record["precision"] == "fp32" and record["backbone"] == "sparse"
    assert record["weights"].startswith("random") and record["output"]["name"] == "head"
    assert [i["name"] for i in record["inputs"]][:3] == ["features", "down1", "subm1_k3"]
    # the IR runs in OpenVINO and gives what the eager model gives
    import openvino as ov

    eager = load_model(load_experiment(slim["sparse"]), None, "cpu")
    graph = SparseGraph(eager)
    coords = clustered_sites(eager.output_shape, 0.05, seed=4)
    feats = torch.randn(coords.shape[0], 32, generator=torch.Generator().manual_seed(0))
    tables = build_tables(graph.spec, feats, coords)
    got = ov.Core().compile_model(str(out / "model.xml"), "CPU", {"INFERENCE_PRECISION_HINT": "f32"})(
        {k: v.numpy() for k, v in tables.inputs.items()})[0]
    with torch.no_grad():
        ref = graph(*tables.inputs.values()).numpy()
    assert np.abs(got - ref).max() <= TOL

    # a second export replaces the first; a folder that is not an export is refused, untouched
    code, _, _ = _cli(["export", "--config", slim["dense"], "--format", "onnx", "--out", out], capsys)
    assert code == 0 and sorted(p.name for p in out.iterdir()) == [".mpchair-output.json", "deploy.json", "model.onnx"]
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    code, _, err = _cli(["export", "--config", DENSE, "--format", "onnx", "--out", other], capsys)
    assert code == 2 and err.count("\n") == 1 and "will not replace this folder" in err
    assert [p.name for p in other.iterdir()] == ["keep.txt"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp folder left behind


def test_export_cli_errors_are_one_line(tmp_path, capsys):
    code, _, err = _cli(["export", "--config", "detector/configs/kitti_car_sparse1_dense23.yaml", "--format", "onnx",
                         "--out", tmp_path / "x"], capsys)
    assert code == 2 and err.count("\n") == 1 and "all-sparse backbone" in err
    code, _, err = _cli(["export", "--config", DENSE, "--format", "onnx", "--precision", "int8", "--out",
                         tmp_path / "y"], capsys)
    assert code == 2 and err.count("\n") == 1 and "calibration" in err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_int8_export_is_calibrated_on_the_dataset(slim, tmp_path, capsys):
    data = make_tiny_dataset(tmp_path / "ds", n_frames=2, seed=2)
    out = tmp_path / "int8"
    code, _, _ = _cli(["export", "--config", slim["sparse"], "--format", "onnx", "--precision", "int8", "--data", data,
                       "--calibration-frames", "2", "--out", out], capsys)
    assert code == 0
    record = json.loads((out / "deploy.json").read_text())
    assert record["precision"] == "int8" and record["calibration"] == {"data": str(data), "split": "train",
                                                                      "frames": 2}
    ops = {n.op_type for n in onnx.load(str(out / "model.onnx")).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear", "MatMul"} <= ops


@pytest.mark.parametrize("kind", ["dense", "sparse"])
def test_int8_keeps_the_head_in_fp32(kind, slim, tmp_path, capsys):
    # one uint8 scale over class logits and box residuals together cost 12 3D AP points (docs/results.md): the head's
    # weights stay fp32 initializers and no Quantize/DequantizeLinear lies between it and the graph outputs
    data = make_tiny_dataset(tmp_path / "ds", n_frames=2, seed=3)
    out = tmp_path / "int8"
    code, _, _ = _cli(["export", "--config", slim[kind], "--format", "onnx", "--precision", "int8", "--data", data,
                       "--calibration-frames", "2", "--out", out], capsys)
    assert code == 0
    model = onnx.load(str(out / "model.onnx"))
    nodes = {n.name: n for n in model.graph.node}
    assert sum(n.op_type == "QuantizeLinear" for n in model.graph.node) > 3  # the backbone is quantized
    head = head_nodes(model)
    assert head and all(nodes[h].op_type in QUANTIZED_OPS for h in head)
    initializers = {i.name for i in model.graph.initializer}
    producer = {o: n for n in model.graph.node for o in n.output}
    for h in head:  # its weight: an fp32 initializer (the dense head of the sparse graph takes it as MatMul's A)
        weights = [i for i in nodes[h].input if i in initializers and i not in producer]
        assert weights, h
    todo, seen = [o.name for o in model.graph.output], set()
    while todo:  # from each output back to the head: no quantizer on the way
        node = producer.get(todo.pop())
        if node is None or node.name in seen or node.name in head:
            continue
        seen.add(node.name)
        assert node.op_type not in ("QuantizeLinear", "DequantizeLinear"), node.name
        todo.extend(node.input)


def test_head_nodes_walks_back_through_the_bias_and_reshapes():
    from onnx import TensorProto, helper
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2])
    w1 = helper.make_tensor("w1", TensorProto.FLOAT, [4, 4], [0.0] * 16)
    w2 = helper.make_tensor("w2", TensorProto.FLOAT, [4, 2], [0.0] * 8)
    b = helper.make_tensor("b", TensorProto.FLOAT, [2], [0.0] * 2)
    graph = helper.make_graph([
        helper.make_node("MatMul", ["x", "w1"], ["h"], name="body"),
        helper.make_node("Relu", ["h"], ["r"], name="relu"),
        helper.make_node("MatMul", ["r", "w2"], ["m"], name="head"),
        helper.make_node("Add", ["m", "b"], ["a"], name="bias"),
        helper.make_node("Identity", ["a"], ["y"], name="out"),
    ], "g", [x], [y], [w1, w2, b])
    assert head_nodes(helper.make_model(graph)) == ["head"]
