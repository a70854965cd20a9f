"""Experiment configs (detector.config), the builder, and a tiny dense training run (detector.models)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from test_sparse_backbone import dense_reference, randomise_norms

from detector.config import ModelConfig, check_model_config, load_experiment
from detector.models import build_model
from detector.models.box_coder import decode_boxes
from detector.models.sparse_backbone import SparseBackboneNeck
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError

CONFIGS = sorted((Path(__file__).resolve().parents[1] / "detector" / "configs").glob("*.yaml"))


def test_config_folder_has_every_experiment() -> None:
    names = {p.stem for p in CONFIGS}
    for stem in (
        "mpchair_dense",
        "mpchair_sparse",
        "kitti_car_dense",
        "kitti_car_sparse",
        "kitti_car_sparse1_dense23",
        "kitti_car_sparse12_dense3",
        "kitti_car_sparse_wide",
        "kitti_car_sparse_wide_down",
        "mpchair_dense_smoke",
        "mpchair_sparse_smoke",
        "mpchair_dense_cpu",
        "mpchair_sparse_cpu",
    ):
        assert stem in names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_every_config_loads_and_checks(path: Path) -> None:
    cfg = load_experiment(path)
    check_model_config(cfg.model)
    assert cfg.model.num_classes == len(cfg.data.classes)
    assert cfg.model.backbone in path.stem or (cfg.model.backbone == "sparse" and "sparse" in path.stem)
    assert cfg.train.epochs == (250 if "sparse" in path.stem else 200) or "_smoke" in path.stem or "_cpu" in path.stem


def test_paper_values() -> None:
    m = load_experiment(CONFIGS[0].parent / "mpchair_dense.yaml").model
    assert m.output_shape == (768, 512) and m.voxel_size == (0.05, 0.05, 4.0) and m.in_channels == 3
    k = load_experiment(CONFIGS[0].parent / "kitti_car_dense.yaml")
    assert k.model.output_shape == (504, 440) and k.model.anchor_sizes == ((3.9, 1.6, 1.56),)
    assert (k.model.neg_iou_thr, k.model.pos_iou_thr) == (0.45, 0.6) and k.eval.iou_thresholds == (0.7,)
    # the reference's steps_per_epoch_train: 5000 samples per epoch, on both datasets, for every paper model
    for path in CONFIGS:
        if path.stem.startswith("kitti_car") or path.stem in ("mpchair_dense", "mpchair_sparse",
                                                              "mpchair_sparse_exact"):
            assert load_experiment(path).train.samples_per_epoch == 5000, path.stem


def test_config_errors_are_input_errors(tmp_path: Path) -> None:
    base = to_dict(load_experiment(CONFIGS[0].parent / "mpchair_dense_smoke.yaml"))
    import yaml

    def write(mutate) -> Path:
        data = yaml.safe_load(yaml.safe_dump(base))
        mutate(data)
        p = tmp_path / "c.yaml"
        p.write_text(yaml.safe_dump(data))
        return p

    cases = [
        (lambda d: d["model"].update(bogus=1), "unknown key"),
        (lambda d: d["model"].update(backbone="dense2"), "backbone"),
        (lambda d: d["model"].update(output_shape=[88, 64]), "smaller than the real grid"),
        (lambda d: d["model"].update(output_shape=[100, 64]), "multiple"),
        (lambda d: d["model"].update(in_channels=5), "in_channels"),
        (lambda d: d["model"].update(voxel_size=[0.3, 0.1, 4.0]), "whole number"),
        (lambda d: d["data"].update(classes=["Chair", "Table"]), "num_classes"),
    ]
    for mutate, msg in cases:
        with pytest.raises(InputError, match=msg):
            load_experiment(write(mutate))


def test_build_matterport_dense_anchor_count_and_stage_shapes() -> None:
    cfg = load_experiment(CONFIGS[0].parent / "mpchair_dense.yaml").model
    model = build_model(cfg)
    assert model.anchors.shape == (196_608, 7) and model.neck is not None
    assert model.anchor_head.conv_cls.in_channels == 384 and model.anchor_head.conv_reg.out_channels == 14


def _tiny_config(**kw) -> ModelConfig:
    """32 x 32 pillars of 10 cm; the architecture's shape with quarter-width channels (fast on CPU)."""
    return ModelConfig(
        point_cloud_range=(0.0, -1.6, -1.0, 3.2, 1.6, 1.0),
        voxel_size=(0.1, 0.1, 2.0),
        output_shape=(32, 32),
        pfn_channels=16,
        layer_channels=(16, 32, 64),
        neck_channels=(32, 32, 32),
        anchor_range=(0.0, -1.6, -1.0, 3.2, 1.6, -1.0),
        **kw,
    )


def _scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    floor = torch.rand(300, 3, generator=g) * torch.tensor([3.2, 3.2, 0.05]) + torch.tensor([0.0, -1.6, -1.0])
    chair = torch.rand(200, 3, generator=g) * torch.tensor([0.9, 0.6, 0.85]) + torch.tensor([1.15, -0.1, -0.95])
    box = torch.tensor([[1.6, 0.2, -0.55, 0.9, 0.6, 0.85, 0.1]])
    return torch.cat([floor, chair]), box


def test_tiny_dense_model_trains_and_predicts() -> None:
    torch.manual_seed(0)
    model = build_model(_tiny_config())
    pts, box = _scene()
    labels = torch.zeros(1, dtype=torch.int64)
    assert int(model.targets([box], [labels]).pos.sum()) >= 1
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, betas=(0.95, 0.99), weight_decay=0.01)
    losses = []
    model.train()
    for _ in range(8):
        preds = model([pts])
        assert preds.cls.shape == (1, 16, 16, 2) and preds.reg.shape == (1, 16, 16, 14)
        loss = model.loss(preds, [box], [labels])
        opt.zero_grad()
        loss.total.backward()
        opt.step()
        losses.append(float(loss.total.detach()))
    assert all(torch.isfinite(torch.tensor(losses)))
    assert losses[-1] < 0.8 * losses[0] and losses == sorted(losses, reverse=True), losses  # 2.80 → 2.02 measured
    model.eval()
    dets = model.predict([pts, pts[:0]])
    assert len(dets) == 2 and dets[1].boxes.shape == (0, 7) and dets[1].scores.shape == (0,)
    # 8 steps leave every score under the config's 0.1 threshold (max 0.010 measured), so look at all of them: the
    # best detection is the best anchor of the forward pass, decoded from its own residuals and direction bin.
    assert dets[0].boxes.shape == (0, 7)
    model.score_thr = 0.0
    with torch.no_grad():  # direction bin 1 wins at every anchor, so the direction fix must add pi
        model.anchor_head.conv_dir.bias.copy_(torch.tensor([-5.0, 5.0]).repeat(2))
    dets = model.predict([pts])
    with torch.no_grad():
        out = model([pts])
    probs = torch.sigmoid(out.cls).reshape(-1)  # (H * W * A,) for one class, in the anchors' order
    best = int(torch.argmax(probs))
    assert dets[0].scores[0] == probs[best] and dets[0].scores.tolist() == sorted(dets[0].scores.tolist(), reverse=True)
    expect = decode_boxes(out.reg.reshape(-1, 7)[best], model.anchors[best])
    assert int(out.dir.reshape(-1, 2)[best].argmax()) == 1
    expect[6] = torch.remainder(expect[6], math.pi) + math.pi  # the direction fix (dir offsets 0)
    torch.testing.assert_close(dets[0].boxes[0], expect, atol=1e-5, rtol=0)


def test_stage_methods_chain_like_forward() -> None:
    torch.manual_seed(0)
    model = build_model(_tiny_config()).eval()
    pts, _ = _scene(1)
    with torch.no_grad():
        v = model.voxelize([pts, pts])
        feats, coords = model.pillar_net(v)
        assert feats.shape == (v.pillars.shape[0], 16) and coords.shape[1] == 3
        canvas = model.feature_net(feats, coords, v.batch_size)
        assert canvas.shape == (2, 16, 32, 32)
        x, active = model.backbone_neck(canvas)
        assert x.shape == (2, 96, 16, 16) and active is None
        staged = model.head(x, active)
        whole = model([pts, pts])
    assert all(torch.equal(a, b) for a, b in zip(staged, whole))
    assert torch.equal(whole.cls[0], whole.cls[1])  # samples are independent in eval mode


def test_canvas_layout_channels_last_except_fp32_training() -> None:
    torch.manual_seed(0)
    model = build_model(_tiny_config()).eval()
    pts, _ = _scene(1)
    with torch.no_grad():
        feats, coords = model.pillar_net(model.voxelize([pts, pts]))
        infer = model.feature_net(feats, coords, 2)  # inference: channels-last, like the sparse model's head input
        x, _ = model.backbone_neck(infer)
        head_fp32 = model([pts])
    train_fp32 = model.feature_net(feats, coords, 2)  # autograd on, fp32: the reference's NCHW
    with torch.autocast("cpu", dtype=torch.bfloat16):
        train_bf16 = model.feature_net(feats, coords, 2)
        head_bf16 = model([pts])
    assert infer.is_contiguous(memory_format=torch.channels_last) and not infer.is_contiguous()
    assert x.is_contiguous(memory_format=torch.channels_last)  # the layout runs through backbone + neck
    assert train_fp32.is_contiguous() and train_bf16.is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(infer, train_fp32) and torch.equal(infer, train_bf16)  # same values, only strides differ
    # The bf16 forward on the channels-last canvas is the fp32 forward up to bf16 rounding. Tolerances per map, about
    # 4x the measured max |difference| (cls 4.5e-3 on logits near -4.6, reg 5e-5 and dir 5.5e-4 on values up to 7e-3
    # and 0.09 at init): an all-zero regression or direction map, or a dropped bias, is far outside them.
    for a, b, tol in zip(head_fp32, head_bf16, (2e-2, 2e-4, 2e-3)):
        assert a.shape == b.shape and b.dtype == torch.bfloat16
        torch.testing.assert_close(b.float(), a, atol=tol, rtol=0)


def test_dense_and_sparse_share_the_head_and_postprocess_path() -> None:
    """At inference both models give the one head a channels-last map, so the head's fused conv and the one
    post-processing run on identically laid-out tensors; fed the same map, the two heads give identical output."""
    torch.manual_seed(0)
    dense = build_model(_tiny_config()).eval()
    sparse = build_model(_tiny_config(backbone="sparse")).eval()
    sparse.anchor_head.load_state_dict(dense.anchor_head.state_dict())
    assert type(dense.anchor_head) is type(sparse.anchor_head)
    pts, _ = _scene(2)
    maps, outs = [], []
    with torch.no_grad():
        for model in (dense, sparse):
            v = model.voxelize([pts])
            x, active = model.backbone_neck(model.feature_net(*model.pillar_net(v), v.batch_size))
            out = model.head(x, active)
            maps.append(x)
            outs.append(out)
            model.postprocess(*out)
        same_input = [m.head(maps[0]) for m in (dense, sparse)]
    for x in maps:
        assert x.shape == (1, 96, 16, 16) and x.is_contiguous(memory_format=torch.channels_last)
    for a, b in zip(*outs):
        assert a.shape == b.shape and a.stride() == b.stride()  # the same views of one (B, H, W, O) output
        assert a.storage_offset() == b.storage_offset()
    for a, b in zip(*same_input):
        assert torch.equal(a, b)
    # the fused inference conv equals the three training convs
    three = dense.anchor_head(maps[0].detach().requires_grad_(True))
    for a, b in zip(three, outs[0]):
        torch.testing.assert_close(a.detach(), b, atol=1e-5, rtol=1e-5)


def test_sparse_variants_build_and_run() -> None:
    """Each sparse variant is built with its number of sparse blocks and first SubM kernel, and its forward equals the
    same network evaluated densely with the active masks applied after every layer; the loss reaches every block."""
    pts, box = _scene(2)
    for backbone, sparse_blocks, kernel in (("sparse", 3, 3), ("sparse1_dense23", 1, 3), ("sparse_wide", 3, 9)):
        torch.manual_seed(0)
        model = build_model(_tiny_config(backbone=backbone, head="sparse_exact"))
        assert isinstance(model.backbone, SparseBackboneNeck) and model.sparse_input and model.neck is None
        assert model.backbone.sparse_blocks == sparse_blocks
        assert model.backbone.blocks[0][3].kernel_size == kernel  # stride-2 conv, BN, ReLU, then the first SubM
        randomise_norms(model.backbone, 3)
        model.eval()
        with torch.no_grad():
            x = model.feature_net(*model.pillar_net(model.voxelize([pts])), 1)
            ref = model.anchor_head.conv_cls(dense_reference(model.backbone, x)).permute(0, 2, 3, 1)
            preds = model([pts])
        assert preds.cls.shape == (1, 16, 16, 2)
        torch.testing.assert_close(preds.cls, ref, atol=1e-5, rtol=1e-5)
        model.train()
        loss = model.loss(model([pts]), [box], [torch.zeros(1, dtype=torch.int64)])
        loss.total.backward()
        assert torch.isfinite(loss.total)
        for block in model.backbone.blocks:  # gradients reach the first and the last conv of every block
            assert block[0].weight.grad.abs().sum() > 0 and block[-3].weight.grad.abs().sum() > 0, backbone
    # the released code's Sparse+WideConv: 9x9 stride-2 down-convs (grown active sets), 3x3 SubMs
    torch.manual_seed(0)
    wide = build_model(_tiny_config(backbone="sparse_wide_down"))
    downs = [m for m in wide.modules() if type(m).__name__ == "SparseConv2d"]
    subms = [m for m in wide.modules() if type(m).__name__ == "SubMConv2d"]
    assert [m.kernel_size for m in downs] == [9, 9, 9] and {m.kernel_size for m in subms} == {3}
    preds = wide([pts])
    assert preds.cls.shape == (1, 16, 16, 2)
    wide.loss(preds, [box], [torch.zeros(1, dtype=torch.int64)]).total.backward()
    with pytest.raises(InputError, match="downsample"):
        check_model_config(_tiny_config(backbone="sparse_wide_down", downsample="reference_quirk"))


@pytest.mark.parametrize(("backbone", "head"), [("dense", "dense"), ("sparse", "dense"), ("sparse", "sparse_exact")])
def test_weight_gradients_have_the_weights_strides(backbone: str, head: str) -> None:
    """Every weight's gradient has the weight's own strides, in fp32 and bf16 training (channels-last canvas): DDP
    compares them exactly with its bucket views and warned "Grad strides do not match bucket view strides" once per
    rank for the 1x1 transposed convs (a permute in the sparse one, a channels-last input in the dense one)."""
    pts, box = _scene(1)
    for bf16 in (False, True):
        torch.manual_seed(0)
        model = build_model(_tiny_config(backbone=backbone, head=head)).train()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            preds = model([pts])
        model.loss(preds, [box], [torch.zeros(1, dtype=torch.int64)]).total.backward()
        wrong = [(name, tuple(p.grad.stride()), tuple(p.stride())) for name, p in model.named_parameters()
                 if p.grad is not None and p.grad.stride() != p.stride()]
        assert not wrong, (bf16, wrong)
