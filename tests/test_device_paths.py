"""The GPU path, tested: every check runs on each device there is, ``cpu`` always and ``cuda`` when torch sees a GPU
(skipped otherwise, with the reason), so a GPU machine runs exactly what the CPU suite runs, plus the comparison with
the CPU.

Covered: sparse SubM / down / wide-down / transposed convolutions equal the dense ``torch.nn.functional`` ops on the
active sites, forward and backward (float64, as ``tests/test_sparse_ops.py``, whose helpers build the inputs); the
voxelizer; rotated NMS and the IoUs; one training step of each model (dense, sparse, sparse with the exact head) in
fp32 and under autocast; deterministic reruns; the head maps, post-processing and evaluation of device outputs. Every
device's numbers are compared with the CPU's (the ``cpu`` parameter compares the CPU with itself, and asserts the
numbers themselves like every other parameter). TF32 is off where a GPU result is compared with the CPU's
(:func:`exact_fp32`), so float32 tolerances stay float32's.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers_detector import IMAGE_SIZE, make_frame, make_tiny_dataset, write_test_config
from test_sparse_ops import TOL, at_sites, make_tensor

from detector.config import load_experiment
from detector.data import KittiDataset
from detector.device import (
    autocast_dtype,
    deterministic,
    needs_grad_scaler,
    peak_memory_bytes,
    reset_peak_memory,
    synced_clock,
    synchronize,
)
from detector.eval import evaluate
from detector.infer import detections_to_labels, evaluate_model
from detector.models import Detections, build_model
from detector.models.assign import axis_aligned_iou, nearest_bev
from detector.models.voxelizer import voxelize
from detector.ops import rotated_iou_bev, rotated_nms
from detector.sparse import SparseConv2d, SparseConvTranspose2d, SparseTensor, SubMConv2d
from mpchair.geometry import pillar_coords

CUDA_SKIP = ("no CUDA device here (torch.cuda.is_available() is False); the cuda half of this file runs on a GPU "
             "machine: tools/device_check.sh")
DEVICES = [pytest.param("cpu", id="cpu"),
           pytest.param("cuda", id="cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason=CUDA_SKIP))]
CPU = torch.device("cpu")
#: float32 agreement between devices without TF32: summation order only (measured on CPU threads: ~1e-6 relative).
F32 = dict(rtol=1e-4, atol=1e-5)


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)


@pytest.fixture
def exact_fp32():
    """TF32 off for the test (cuDNN convolutions and cuBLAS matmuls on Ampere+ GPUs use it by default: ~1e-3
    relative, which would hide a real difference behind the tolerance); the flags are restored afterwards."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


# --- sparse convolutions ------------------------------------------------------------------------------------------
def _leaf(x: SparseTensor, device: torch.device) -> SparseTensor:
    """``x`` on ``device`` with fresh leaf features that record their gradient."""
    return SparseTensor(x.features.detach().to(device).requires_grad_(True), x.coords.to(device), x.spatial_shape,
                        x.batch_size)


def _sparse_vs_dense(op: str, device: torch.device) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Run one sparse op and its dense twin on ``device`` (float64), forward and backward of the same random
    read-out of the output sites: ``{what: (sparse value, dense value at the active sites)}``, all on the CPU."""
    torch.manual_seed(0)
    if op == "transposed":
        x = _leaf(make_tensor("clustered", channels=4, shape=(5, 4), seed=2), device)
        target = make_tensor("uniform", channels=1, shape=(10, 8), seed=5)
        layer = SparseConvTranspose2d(4, 3, 2, 2, bias=True).double().to(device)
        y = layer(x, SparseTensor(target.features.to(device), target.coords.to(device), target.spatial_shape,
                                  target.batch_size))
    else:
        x = _leaf(make_tensor("clustered", shape=(14, 12), seed=1), device)
        layer = {"subm_gemm": lambda: SubMConv2d(3, 4, 3, bias=True, algorithm="gemm"),
                 "subm_rulebook": lambda: SubMConv2d(3, 4, 5, bias=True, algorithm="rulebook"),
                 "down": lambda: SparseConv2d(3, 4, 2, 2, bias=True),
                 "wide_down": lambda: SparseConv2d(3, 4, 3, 2, bias=True)}[op]().double().to(device)
        y = layer(x)
    dense_in = x.dense().detach().requires_grad_(True)
    w = layer.weight.detach().clone().requires_grad_(True)
    b = layer.bias.detach().clone().requires_grad_(True)
    if op == "transposed":
        ref = F.conv_transpose2d(dense_in, w, b, stride=2)
    elif op.startswith("subm"):
        ref = F.conv2d(dense_in, w, b, padding=layer.kernel_size // 2)
    else:
        ref = F.conv2d(dense_in, w, b, stride=2, padding=layer.kernel_size // 2 if op == "wide_down" else 0)
    ref_at = at_sites(ref, y.coords)
    probe = torch.randn(y.features.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(7)).to(device)
    (y.features * probe).sum().backward()
    (ref_at * probe).sum().backward()
    pairs = {"forward": (y.features, ref_at), "grad_input": (x.features.grad, at_sites(dense_in.grad, x.coords)),
             "grad_weight": (layer.weight.grad, w.grad), "grad_bias": (layer.bias.grad, b.grad)}
    return {k: (a.detach().cpu(), r.detach().cpu()) for k, (a, r) in pairs.items()}


@pytest.mark.parametrize("op", ["subm_gemm", "subm_rulebook", "down", "wide_down", "transposed"])
def test_sparse_conv_equals_dense_conv_forward_and_backward(device, op):
    got = _sparse_vs_dense(op, device)
    for what, (sparse, dense) in got.items():
        assert sparse.numel() > 0 and float(sparse.abs().max()) > 0, what  # real work, not an empty comparison
        torch.testing.assert_close(sparse, dense, atol=TOL, rtol=0, msg=f"{op} {what}")
    # the same numbers as on the CPU (float64: cuDNN and cuBLAS differ from the CPU by summation order only)
    for what, (sparse, _) in (got if device == CPU else _sparse_vs_dense(op, CPU)).items():
        torch.testing.assert_close(got[what][0], sparse, atol=TOL, rtol=0, msg=f"{op} {what} vs cpu")


# --- voxelizer ----------------------------------------------------------------------------------------------------
SMOKE_GRID = dict(point_cloud_range=(0.0, -4.8, -2.0, 6.4, 4.8, 2.0), voxel_size=(0.1, 0.1, 4.0), output_shape=(96, 64))


def test_voxelizer_on_device(device):
    """Pillars of a 2-sample batch (one sample empty) equal the CPU's bit for bit and the indexing rule's numbers."""
    points, _, _ = make_frame(np.random.default_rng(3), 3)
    batch = [torch.from_numpy(points).to(device), torch.zeros((0, 4), device=device)]
    v = voxelize(batch, **SMOKE_GRID, max_points=16, max_pillars=4000)
    assert v.pillars.device.type == device.type and v.batch_size == 2
    ref = voxelize([p.cpu() for p in batch], **SMOKE_GRID, max_points=16, max_pillars=4000)
    for a, b in zip(v[:3], ref[:3]):
        assert torch.equal(a.cpu(), b)
    # the numbers of the project's one indexing rule (mpchair.geometry.pillar_coords), counted here with numpy
    cells, keep = pillar_coords(points[:, :3].astype(np.float64), SMOKE_GRID["point_cloud_range"],
                                SMOKE_GRID["voxel_size"])
    uniq, first, counts = np.unique(cells, axis=0, return_index=True, return_counts=True)
    assert keep.sum() > 1000 and v.coords.shape[0] == len(uniq) > 100
    order = np.argsort(first)  # pillars are numbered by their first point
    assert np.array_equal(v.coords[:, 1:].cpu().numpy(), uniq[order])
    assert np.array_equal(v.num_points.cpu().numpy(), np.minimum(counts[order], 16))
    assert bool((v.coords[:, 0] == 0).all())  # the empty sample adds no pillar


# --- NMS and IoU --------------------------------------------------------------------------------------------------
#: [x, y, z, l, w, h, yaw] (sensor frame, m, rad) and scores: box 1 lies almost on box 0, box 3 overlaps box 0 by
#: 0.1 m of its width (BEV IoU 0.2 / 3.8 = 0.0526), box 2 is far away.
NMS_BOXES = [[0.0, 0.0, 0.5, 2.0, 1.0, 1.0, 0.0], [0.1, 0.0, 0.5, 2.0, 1.0, 1.0, 0.05],
             [5.0, 5.0, 0.5, 2.0, 1.0, 1.0, 1.0], [0.0, 0.9, 0.5, 2.0, 1.0, 1.0, 0.0]]
NMS_SCORES = [0.9, 0.8, 0.7, 0.95]


def test_nms_and_iou_on_device(device):
    boxes = torch.tensor(NMS_BOXES, dtype=torch.float32, device=device)
    scores = torch.tensor(NMS_SCORES, device=device)
    kept = rotated_nms(boxes, scores, 0.1)
    assert kept.device.type == device.type and kept.tolist() == [3, 0, 2]
    assert rotated_nms(boxes, scores, 0.01).tolist() == [3, 2]  # 0.0526 > 0.01: box 0 goes too
    assert torch.equal(kept.cpu(), torch.from_numpy(rotated_nms(np.array(NMS_BOXES), np.array(NMS_SCORES), 0.1)))
    # the evaluator's exact rotated IoU of device boxes (it reads them on the host, in float64; the float32 boxes
    # hold 0.9 as 0.89999998, hence 1e-6)
    iou = rotated_iou_bev(boxes.cpu().double().numpy(), boxes.cpu().double().numpy())
    assert iou[0, 0] == 1.0 and iou[0, 2] == 0.0
    assert iou[0, 3] == pytest.approx(0.2 / 3.8, rel=1e-6)
    # the training assignment's axis-aligned IoU runs on the device: a 90-degree turn swaps l and w
    turned = torch.tensor([[0.0, 0.0, 0.5, 2.0, 1.0, 1.0, math.pi / 2]], device=device)
    aa = axis_aligned_iou(nearest_bev(boxes[:1]), nearest_bev(torch.cat([boxes[3:4], turned])))
    assert aa.device.type == device.type
    torch.testing.assert_close(aa.cpu(), torch.tensor([[0.2 / 3.8, 1.0 / 3.0]]), rtol=1e-6, atol=0)


# --- one training step of each model ------------------------------------------------------------------------------
MODELS = {"dense": dict(backbone="dense"), "sparse": dict(backbone="sparse"),
          "sparse_exact": dict(backbone="sparse", head="sparse_exact")}


def _tiny_batch(device: torch.device) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """Two synthetic rooms (xyz points, chair boxes in the sensor frame, labels 0) on ``device``."""
    rng = np.random.default_rng(11)
    points, boxes, labels = [], [], []
    for n in (3, 4):
        pts, b, names = make_frame(rng, n)
        chairs = names == "Chair"
        points.append(torch.from_numpy(pts[:, :3].copy()).to(device))
        boxes.append(torch.from_numpy(b[chairs].astype(np.float32)).to(device))
        labels.append(torch.zeros(int(chairs.sum()), dtype=torch.int64, device=device))
    return points, boxes, labels


def _train_step(cfg_path, device: torch.device, autocast: torch.dtype | None = None) -> dict:
    """One AdamW step of the config's model from its seeded initial weights on the tiny batch: the loss, positives,
    gradient norm, largest weight change, and whether every gradient is finite."""
    cfg = load_experiment(cfg_path)
    torch.manual_seed(0)
    model = build_model(cfg.model).to(device).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    before = [p.detach().clone() for p in model.parameters()]
    points, boxes, labels = _tiny_batch(device)
    scaler = torch.amp.GradScaler(device.type) if autocast is not None and needs_grad_scaler(autocast) else None
    with torch.autocast(device.type, dtype=autocast or torch.bfloat16, enabled=autocast is not None):
        preds = model(points)
    losses = model.loss(type(preds)(*(p.float() for p in preds)), boxes, labels)
    opt.zero_grad()
    (scaler.scale(losses.total) if scaler else losses.total).backward()
    if scaler:
        scaler.unscale_(opt)
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    norm = float(torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads])))
    scaler.step(opt) if scaler else opt.step()
    synchronize(device)
    return {"loss": losses.total.item(), "num_pos": int(model.targets(boxes, labels).pos.sum()), "grad_norm": norm,
            "finite": all(bool(torch.isfinite(g).all()) for g in grads), "grads": len(grads),
            "moved": max(float((p.detach() - b).abs().max()) for p, b in zip(model.parameters(), before)),
            "params": sum(1 for p in model.parameters() if p.requires_grad)}


@pytest.mark.parametrize("name", list(MODELS))
def test_one_training_step_of_each_model(device, name, tmp_path, exact_fp32):
    cfg = write_test_config(tmp_path / f"{name}.yaml", model=MODELS[name])
    step = _train_step(cfg, device)
    assert step["finite"] and step["grads"] == step["params"]  # every parameter got a finite gradient
    assert step["num_pos"] > 5 and 0 < step["loss"] < 100 and 0 < step["grad_norm"] < 1e4
    assert 0 < step["moved"] <= 1.5e-3  # AdamW moves a weight by about lr in its first step
    cpu = step if device == CPU else _train_step(cfg, CPU)
    assert step["num_pos"] == cpu["num_pos"]  # assignment is exact on every device
    np.testing.assert_allclose(step["loss"], cpu["loss"], **F32)
    np.testing.assert_allclose(step["grad_norm"], cpu["grad_norm"], rtol=1e-3)


@pytest.mark.parametrize("name", list(MODELS))
def test_training_step_under_autocast(device, name, tmp_path):
    """Mixed precision in the device's dtype (bf16 on the CPU and Ampere+, fp16 with loss scaling before): a finite
    step whose loss stays within a few percent of fp32's."""
    dtype = autocast_dtype(device)
    assert dtype == torch.bfloat16 or device.type == "cuda"
    cfg = write_test_config(tmp_path / f"{name}.yaml", model=MODELS[name])
    mixed, full = _train_step(cfg, device, autocast=dtype), _train_step(cfg, device)
    assert mixed["finite"] and mixed["num_pos"] == full["num_pos"] > 5
    np.testing.assert_allclose(mixed["loss"], full["loss"], rtol=0.05)


def test_deterministic_reruns(device, tmp_path):
    """Under :func:`detector.device.deterministic` two sparse steps from the same seed agree bit for bit (on CUDA
    this also proves that every op of the step has a deterministic implementation: torch raises otherwise)."""
    cfg = write_test_config(tmp_path / "sparse.yaml", model=MODELS["sparse"])
    before = torch.are_deterministic_algorithms_enabled()
    with deterministic():
        assert torch.are_deterministic_algorithms_enabled()
        a, b = _train_step(cfg, device), _train_step(cfg, device)
    assert torch.are_deterministic_algorithms_enabled() == before
    assert a == b and a["finite"]


# --- inference and evaluation of device outputs -------------------------------------------------------------------
def test_eval_of_device_outputs(device, tmp_path, exact_fp32):
    """Head maps and detections made on the device equal the CPU's; results written from device tensors evaluate
    to the same AP as from CPU tensors; ``evaluate_model`` runs end to end on the device."""
    data = make_tiny_dataset(tmp_path / "data", n_frames=2, seed=4)
    cfg_path = write_test_config(tmp_path / "dense.yaml", model=dict(score_thr=0.05))
    cfg = load_experiment(cfg_path)
    torch.manual_seed(0)
    model = build_model(cfg.model).eval()
    with torch.no_grad():
        model.anchor_head.conv_cls.bias.fill_(-1.0)  # sigmoid 0.27 > score_thr: untrained weights still detect
    frames = KittiDataset(data, "val", classes=cfg.data.classes)
    frame = frames[0]
    pts = torch.from_numpy(frame.points[:, :3].copy())
    with torch.no_grad():
        maps_dev = [m.cpu() for m in model.to(device)([pts.to(device)])]
        model.to(CPU)
        maps_cpu = list(model([pts]))
        dets_cpu = model.postprocess(*maps_cpu)[0]
        # post-processing on the device, of the CPU's maps: the same candidates (logits within 1e-7 could swap two
        # near-equal anchors at the top-k cut), so the same detections up to float32 arithmetic
        model.to(device)
        dets_dev = model.postprocess(*(m.to(device) for m in maps_cpu))[0]
    for a, b in zip(maps_dev, maps_cpu):
        torch.testing.assert_close(a, b, **F32)
    assert dets_dev.boxes.device.type == device.type and len(dets_cpu.boxes) > 0
    for a, b in zip(dets_dev, dets_cpu):
        torch.testing.assert_close(a.cpu(), b, **F32)

    # the ground truth itself as device detections: AP from device tensors == AP from host tensors, and high
    classes = cfg.data.classes
    gts, from_dev, from_cpu = [], [], []
    for fr in (frames[0], frames[1]):
        boxes = torch.from_numpy(fr.boxes.astype(np.float32))
        scores = torch.linspace(0.9, 0.5, len(boxes))
        det = Detections(boxes, scores, torch.zeros(len(boxes), dtype=torch.int64))
        from_cpu.append(detections_to_labels(det, fr, classes, IMAGE_SIZE))
        from_dev.append(detections_to_labels(Detections(*(t.to(device) for t in det)), fr, classes, IMAGE_SIZE))
        gts.append(fr.gt)
    overlaps = {"Chair": (0.5, 0.5, 0.5)}
    res_dev = evaluate(gts, from_dev, classes, overlaps)
    assert res_dev.to_json_dict() == evaluate(gts, from_cpu, classes, overlaps).to_json_dict()
    # perfect detections: precision 1 at every recall slot they reach (the overall row), AP > 0 but capped below 100
    # because n < 41 GT boxes reach only some of the 40 recall steps (docs/evaluation.md; measured 15.0 for 7 boxes)
    n_gt = res_dev.num_gt_overall["Chair"]
    prec = res_dev.precision["Chair"]["3d"][3]
    assert 0 < n_gt < 41 and np.all(prec[prec > 0] == 1.0) and np.count_nonzero(prec) >= n_gt - 1
    assert res_dev.overall["Chair"]["3d"]["R40"] == res_dev.overall["Chair"]["bev"]["R40"] > 0

    model.to(device)
    result = evaluate_model(model, cfg, data, "val", tmp_path / "eval", device=device, progress=False)
    files = sorted((tmp_path / "eval" / "data").glob("*.txt"))
    assert [f.stem for f in files] == frames.ids and (tmp_path / "eval" / "metrics.json").is_file()
    assert sum(len(f.read_text().splitlines()) for f in files) > 0  # the device's detections were written
    assert 0 <= result.overall["Chair"]["bev"]["R40"] <= 100


# --- the helpers the device path needs ----------------------------------------------------------------------------
def test_device_helpers(device):
    t0 = synced_clock(device)
    x = torch.randn(256, 256, device=device)
    reset_peak_memory(device)
    y = x @ x
    synchronize(device)
    assert synced_clock(device) > t0 and torch.isfinite(y).all()
    peak = peak_memory_bytes(device)
    if device.type == "cuda":
        assert peak >= y.numel() * 4  # the product's buffer was live
    else:
        assert peak is None or peak > 10 * 2**20  # a Python process with torch holds tens of MB
    assert needs_grad_scaler(torch.float16) and not needs_grad_scaler(torch.bfloat16)
    assert autocast_dtype(CPU) == torch.bfloat16
