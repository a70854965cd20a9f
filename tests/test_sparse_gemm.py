"""The one-GEMM forms of every sparse conv, and the inference workspace, against dense convolution (float64, 1e-9).

Every conv (SubM, 2x2 / 4x4 down, 9x9 wide down, transposed) in both its "gemm" and "rulebook" forms must equal
the dense ``torch.nn.functional`` conv on the active sites, forward and backward (the input and weight gradients of a
random linear loss); with a workspace (inference) every op and the whole backbone must give the values of the
allocating path, frame after frame, while reusing its memory.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from detector.models.sparse_backbone import SparseBackboneNeck
from detector.sparse import SparseConv2d, SparseConvTranspose2d, SparseTensor, SubMConv2d
from detector.sparse.conv import conv_matrix, gather_gemm, padded_rows, transposed_matrix
from detector.sparse.synthetic import clustered_sites, uniform_sites
from detector.sparse.workspace import Workspace
from tests.test_sparse_backbone import randomise_norms

TOL = 1e-9
ALGORITHMS = ("gemm", "rulebook")


def sites(pattern: str, shape: tuple[int, int], density: float, seed: int, batch: int = 2) -> SparseTensor:
    """Active sites (rows shuffled: the ops must not rely on sorted input) with float64 features that need grad."""
    make = clustered_sites if pattern == "clustered" else uniform_sites
    coords = make(shape, density, batch_size=batch, seed=seed)
    coords = coords[torch.randperm(coords.shape[0], generator=torch.Generator().manual_seed(seed))]
    feats = torch.randn(coords.shape[0], 3, dtype=torch.float64, generator=torch.Generator().manual_seed(seed + 1))
    return SparseTensor(feats.requires_grad_(True), coords, shape, batch)


def at_sites(dense: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    return dense[coords[:, 0], :, coords[:, 1], coords[:, 2]]


def check_forward_backward(sparse_out: torch.Tensor, dense_out: torch.Tensor, x: SparseTensor, weight: nn.Parameter,
                           dense_weight: torch.Tensor, dense_x: torch.Tensor) -> None:
    """Values equal, and so do the gradients of a random linear loss w.r.t. the input features and the weight."""
    torch.testing.assert_close(sparse_out, dense_out, atol=TOL, rtol=0)
    r = torch.randn(sparse_out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    gs = torch.autograd.grad((sparse_out * r).sum(), (x.features, weight))
    gd = torch.autograd.grad((dense_out * r).sum(), (dense_x, dense_weight))
    torch.testing.assert_close(gs[0], at_sites(gd[0], x.coords), atol=TOL, rtol=0)
    torch.testing.assert_close(gs[1], gd[1], atol=TOL, rtol=0)
    assert float(gs[1].abs().sum()) > 0  # the loss reaches the weight, so the comparison means something


def dense_twin(x: SparseTensor, weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The zero-filled canvas (a leaf that needs grad) and a contiguous copy of the weight (a leaf)."""
    d = x.dense().detach().requires_grad_(True)
    return d, weight.detach().clone().contiguous().requires_grad_(True)


@pytest.mark.parametrize("pattern", ["clustered", "uniform"])
@pytest.mark.parametrize("kernel_size", [1, 3, 5, 9])
@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_subm_forward_backward(pattern: str, kernel_size: int, algorithm: str) -> None:
    x = sites(pattern, (17, 13), 0.25, seed=kernel_size)
    conv = SubMConv2d(3, 4, kernel_size, algorithm=algorithm).double()
    d, w = dense_twin(x, conv.weight)
    ref = at_sites(F.conv2d(d, w, padding=kernel_size // 2), x.coords)
    check_forward_backward(conv(x).features, ref, x, conv.weight, w, d)


@pytest.mark.parametrize("pattern", ["clustered", "uniform"])
@pytest.mark.parametrize("stride", [2, 4])
@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_down_forward_backward(pattern: str, stride: int, algorithm: str) -> None:
    x = sites(pattern, (17, 13), 0.25, seed=stride)
    conv = SparseConv2d(3, 4, stride, stride, algorithm=algorithm).double()
    d, w = dense_twin(x, conv.weight)
    y = conv(x)
    check_forward_backward(y.features, at_sites(F.conv2d(d, w, stride=stride), y.coords), x, conv.weight, w, d)


@pytest.mark.parametrize("pattern", ["clustered", "uniform"])
@pytest.mark.parametrize("kernel_size", [3, 9])
@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_wide_down_forward_backward(pattern: str, kernel_size: int, algorithm: str) -> None:
    x = sites(pattern, (18, 14), 0.2, seed=kernel_size)
    conv = SparseConv2d(3, 4, kernel_size, 2, algorithm=algorithm).double()
    d, w = dense_twin(x, conv.weight)
    y = conv(x)
    ref = at_sites(F.conv2d(d, w, stride=2, padding=kernel_size // 2), y.coords)
    check_forward_backward(y.features, ref, x, conv.weight, w, d)


@pytest.mark.parametrize("stride", [1, 2, 4])
@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_transposed_forward_backward(stride: int, algorithm: str) -> None:
    coarse = sites("clustered", (6, 5), 0.4, seed=stride)
    # the target set includes sites whose parent is inactive: their output is exactly zero (no bias here)
    target = sites("uniform", (6 * stride, 5 * stride), 0.3, seed=10 + stride)
    conv = SparseConvTranspose2d(3, 4, stride, stride, algorithm=algorithm).double()
    d, w = dense_twin(coarse, conv.weight)
    ref = at_sites(F.conv_transpose2d(d, w, stride=stride), target.coords)
    check_forward_backward(conv(coarse, target).features, ref, coarse, conv.weight, w, d)


def test_auto_equals_both_forms_and_the_gemm_form_is_gather_then_matmul() -> None:
    x = sites("clustered", (17, 13), 0.3, seed=3)
    convs = {a: SubMConv2d(3, 4, 3, indice_key="k", algorithm=a).double() for a in ("auto", *ALGORITHMS)}
    for c in convs.values():
        c.load_state_dict(convs["auto"].state_dict())
    outs = {a: c(x).features for a, c in convs.items()}
    for a in ALGORITHMS:
        torch.testing.assert_close(outs[a], outs["auto"], atol=TOL, rtol=0)
    # the exportable form by hand: one Gather of the padded features with the table, one MatMul
    table = convs["gemm"].table(x)
    by_hand = padded_rows(x.features)[table.padded].view(x.num_active, -1) @ conv_matrix(convs["gemm"].weight).t()
    torch.testing.assert_close(gather_gemm(padded_rows(x.features), table.padded, conv_matrix(convs["gemm"].weight)),
                               by_hand, atol=0, rtol=0)
    torch.testing.assert_close(outs["gemm"], by_hand, atol=0, rtol=0)


def test_weights_keep_the_dense_layout_values_and_init() -> None:
    """Weights are stored channels-last (the GEMM matrix is a view) with the dense shape, torch's default init for a
    seed, and their gradients arrive with the weight's own strides."""
    torch.manual_seed(5)
    sparse = SubMConv2d(3, 4, 3, bias=True)
    torch.manual_seed(5)
    dense = nn.Conv2d(3, 4, 3, padding=1)
    assert torch.equal(sparse.weight, dense.weight) and torch.equal(sparse.bias, dense.bias)
    torch.manual_seed(6)
    up = SparseConvTranspose2d(3, 4, 2, 2, bias=True)
    torch.manual_seed(6)
    dense_up = nn.ConvTranspose2d(3, 4, 2, 2)
    assert torch.equal(up.weight, dense_up.weight) and torch.equal(up.bias, dense_up.bias)
    for m, matrix in ((sparse, conv_matrix), (up, transposed_matrix)):
        assert m.weight.is_contiguous(memory_format=torch.channels_last)
        assert matrix(m.weight).data_ptr() == m.weight.data_ptr() and matrix(m.weight)._base is not None
    x = sites("clustered", (9, 7), 0.4, seed=0)
    for m in (SubMConv2d(3, 2, 1), SubMConv2d(3, 2, 3), SparseConv2d(3, 2)):
        m.double()(x).features.sum().backward()
        assert m.weight.grad.stride() == m.weight.stride()
    sd = sparse.state_dict()
    fresh = nn.Conv2d(3, 4, 3, padding=1)
    fresh.load_state_dict(sd)
    assert torch.equal(fresh.weight, sparse.weight)


# --- the workspace ------------------------------------------------------------------------------------------------


def test_workspace_take_reuses_and_grows() -> None:
    ws = Workspace()
    a = ws.take("o", "x", (10, 4), torch.float32, "cpu")
    b = ws.take("o", "x", (8, 4), torch.float32, "cpu")
    assert a.data_ptr() == b.data_ptr() and b.shape == (8, 4) and b.is_contiguous()
    c = ws.take("o", "x", (100, 4), torch.float32, "cpu")  # more than it holds: a new, larger buffer
    assert c.shape == (100, 4) and ws.take("o", "x", (110, 4), torch.float32, "cpu").data_ptr() == c.data_ptr()
    assert ws.take("o", "x", (8, 4), torch.float64, "cpu").data_ptr() != c.data_ptr()  # one buffer per dtype
    assert ws.take("p", "x", (8, 4), torch.float32, "cpu").data_ptr() != c.data_ptr()  # and per owner


def test_workspace_scatter_resets_only_the_last_rows() -> None:
    ws = Workspace()
    rows = torch.tensor([1, 4])
    out = ws.scatter("o", "c", (6, 2), (rows,), torch.ones(2, 2))
    assert torch.equal(out, torch.zeros(6, 2).index_fill_(0, rows, 1.0))
    out2 = ws.scatter("o", "c", (6, 2), (torch.tensor([0]),), torch.full((1, 2), 3.0))
    assert out2.data_ptr() == out.data_ptr()
    assert torch.equal(out2, torch.zeros(6, 2).index_fill_(0, torch.tensor([0]), 3.0))
    # a new fill value refills the whole canvas; a permuted view writes the same rows of the other axis
    fill = torch.tensor([5.0, 6.0])
    out3 = ws.scatter("o", "c", (2, 6), (torch.tensor([2]),), torch.zeros(1, 2), fill=fill, dims=(1, 0))
    expected = fill[:, None].expand(2, 6).clone()
    expected[:, 2] = 0
    assert torch.equal(out3, expected)


def frames() -> list[SparseTensor]:
    """Frames of growing, shrinking and regrowing size (the workspace must grow, then reuse, then reset rows)."""
    out = []
    for seed, density in ((0, 0.10), (1, 0.16), (2, 0.06), (3, 0.12), (4, 0.16)):
        coords = clustered_sites((32, 24), density, batch_size=2, seed=seed)
        feats = torch.randn(coords.shape[0], 4, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
        out.append((feats, coords))
    return out


@pytest.mark.parametrize("down_kernel", [2, 9])
def test_backbone_with_workspace_equals_without(down_kernel: int) -> None:
    """Frame after frame, the backbone with a workspace gives exactly the allocating backbone's map and mask, and
    once it has seen the largest frame it allocates no new buffer (its output is the same memory)."""
    torch.manual_seed(0)
    model = SparseBackboneNeck(in_channels=4, layer_channels=(4, 6, 8), layer_nums=(1, 2, 1), out_channels=(3, 3, 3),
                               down_kernel=down_kernel).double()
    randomise_norms(model, 1)
    model.eval()
    ws = Workspace()
    ptrs, sizes = [], []
    with torch.no_grad():
        for feats, coords in frames():
            ref, ref_mask = model(SparseTensor(feats, coords, (32, 24), 2))
            got, mask = model(SparseTensor(feats, coords, (32, 24), 2, workspace=ws, origin="input"))
            assert torch.equal(got, ref) and torch.equal(mask, ref_mask)
            ptrs.append(got.data_ptr())
            sizes.append(ws.nbytes())
    assert ptrs[-1] == ptrs[-2] == ptrs[-3] and sizes[-1] == sizes[-2] == sizes[-3]


def test_training_ignores_the_workspace() -> None:
    torch.manual_seed(0)
    model = SparseBackboneNeck(in_channels=4, layer_channels=(4, 6, 8), layer_nums=(1, 2, 1),
                               out_channels=(3, 3, 3)).double()
    ws = Workspace()
    feats, coords = frames()[0]
    y, _ = model(SparseTensor(feats.requires_grad_(True), coords, (32, 24), 2, workspace=ws, origin="input"))
    y.sum().backward()
    assert ws.nbytes() == 0 and feats.grad is not None


@pytest.mark.parametrize(("backbone", "head"), [("dense", "dense"), ("sparse", "dense"), ("sparse", "sparse_exact"),
                                                ("sparse1_dense23", "dense")])
def test_model_with_workspace_equals_without(backbone: str, head: str) -> None:
    """Whole models, frame after frame (frames of different sizes): with ``model.workspace`` set, inference gives the
    allocating model's head maps, exactly for the sparse models (the same kernels into reused memory) and up to
    float rounding for the dense one (its neck runs as GEMMs into one map instead of oneDNN deconvolutions)."""
    from detector.models import build_model
    from tests.test_models_build import _scene, _tiny_config

    torch.manual_seed(0)
    plain = build_model(_tiny_config(backbone=backbone, head=head))
    randomise_norms(plain, 2)
    plain.float().eval()
    reused = build_model(_tiny_config(backbone=backbone, head=head))
    reused.load_state_dict(plain.state_dict())
    reused.eval()
    reused.workspace = Workspace()
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for seed, keep in ((0, 500), (1, 120), (2, 500), (3, 260)):
            pts = _scene(seed)[0]
            pts = pts[torch.randperm(pts.shape[0], generator=g)[:keep]]
            ref, got = plain([pts]), reused([pts])
            for a, b in zip(ref, got):
                if backbone == "dense":
                    torch.testing.assert_close(b, a, atol=1e-5, rtol=1e-5)
                else:
                    assert torch.equal(a, b)
            dets = reused.postprocess(*got)
            assert len(dets) == 1
    assert reused.workspace.nbytes() > 0


def test_training_head_on_the_neck_rows_equals_the_head_on_the_canvas() -> None:
    """What ``PointPillars.forward`` trains the all-sparse model with: the head on the neck's active rows gives the
    head maps of the scattered canvas, and the same gradients for the input and every parameter (float64, 1e-9)."""
    from detector.models.head import AnchorHead

    torch.manual_seed(0)
    backbone = SparseBackboneNeck(in_channels=4, layer_channels=(4, 6, 8), layer_nums=(1, 2, 1),
                                  out_channels=(3, 3, 3)).double().train()
    head = AnchorHead(in_channels=9, num_anchors=2, num_classes=1).double().train()
    feats, coords = frames()[1]
    params = [*backbone.parameters(), *head.parameters()]
    results = []
    for rows in (False, True):
        f = feats.clone().requires_grad_(True)
        x = SparseTensor(f, coords, (32, 24), 2)
        out = head.on_sites(backbone.neck_rows(x)) if rows else head(backbone(x)[0])
        r = [torch.randn(o.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(i))
             for i, o in enumerate(out)]
        grads = torch.autograd.grad(sum((o * ri).sum() for o, ri in zip(out, r)), [f, *params])
        results.append(([o.detach() for o in out], grads))
    (out_a, grad_a), (out_b, grad_b) = results
    for a, b in zip(out_a, out_b):
        assert a.shape == b.shape
        torch.testing.assert_close(b, a, atol=TOL, rtol=0)
    for a, b in zip(grad_a, grad_b):
        torch.testing.assert_close(b, a, atol=TOL, rtol=0)
    assert float(grad_a[-1].abs().sum()) > 0  # the dir bias gets gradient from every cell


@pytest.mark.parametrize(("backbone", "head"), [("dense", "dense"), ("sparse", "dense"), ("sparse", "sparse_exact")])
def test_bf16_inference_is_fp32_up_to_bf16_rounding(backbone: str, head: str) -> None:
    """``model.precision = "bf16"``: the head maps come out in bf16, with or without a workspace, equal to the fp32
    maps up to bf16 rounding; the sparse convs take their one-GEMM form (fp32 sums), so a rulebook-only bf16 sum
    cannot hide here. Tolerance 3 % of each map's range (bf16 keeps 8 bits of mantissa; a skipped or wrong layer
    moves the maps by their whole range)."""
    from detector.models import build_model
    from tests.test_models_build import _scene, _tiny_config

    torch.manual_seed(0)
    ref_model = build_model(_tiny_config(backbone=backbone, head=head))
    randomise_norms(ref_model, 4)
    ref_model.float().eval()
    models = []
    for ws in (None, Workspace()):
        m = build_model(_tiny_config(backbone=backbone, head=head))
        m.load_state_dict(ref_model.state_dict())
        m.eval()
        m.workspace, m.precision = ws, "bf16"
        models.append(m)
    pts = _scene(1)[0]
    with torch.no_grad():
        ref = ref_model([pts])
        for m in models:
            for _ in range(2):  # twice: the workspace's second frame resets and reuses
                out = m([pts])
            for a, b in zip(ref, out):
                assert b.dtype == torch.bfloat16 and b.shape == a.shape
                scale = float(a.abs().max())
                torch.testing.assert_close(b.float(), a, atol=0.03 * scale, rtol=0.02)
            assert len(m.postprocess(*out)) == 1
    # training ignores it: fp32 maps with autograd on
    models[0].train()
    assert models[0]([pts]).cls.dtype == torch.float32


def test_subm_gemm_backward_under_bf16_autocast() -> None:
    """bf16 training: the mirrored-kernel backward runs in the gradient's dtype and hands back fp32 gradients equal
    to the fp32 ones up to bf16 rounding."""
    x = sites("clustered", (17, 13), 0.3, seed=8)
    x = x.replace_feature(x.features.detach().float().requires_grad_(True))
    conv = SubMConv2d(3, 4, 3, algorithm="gemm")
    r = torch.randn(x.num_active, 4, generator=torch.Generator().manual_seed(1))
    ref = torch.autograd.grad((conv(x).features * r).sum(), (x.features, conv.weight))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = conv(x).features
    assert y.dtype == torch.bfloat16
    got = torch.autograd.grad((y.float() * r).sum(), (x.features, conv.weight))
    for a, b in zip(ref, got):
        assert b.dtype == torch.float32
        torch.testing.assert_close(b, a, atol=0.03 * float(a.abs().max()), rtol=0.02)
