"""The inference GEMM (``detector.ops.gemm``): oneDNN for float32 CPU inference, ``torch.mm`` (MKL) elsewhere; the same
values up to float rounding, for the op and for whole models (the sparse convs, the exact head, the dense neck)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from detector.models.neck import SecondFPN
from detector.ops import gemm
from detector.sparse.workspace import Workspace
from tests.test_sparse_backbone import randomise_norms

pytestmark = pytest.mark.skipif(not gemm._HAVE_ONEDNN, reason="this torch build has no oneDNN")


@pytest.mark.parametrize(("m", "k", "o"), [(0, 8, 4), (1, 5, 3), (37, 64, 17), (300, 576, 64), (64, 256, 512)])
@pytest.mark.parametrize("transposed_weight", [False, True])
@pytest.mark.parametrize("with_bias", [False, True])
@pytest.mark.parametrize("relu", [False, True])
def test_linear_equals_the_float64_product(m: int, k: int, o: int, transposed_weight: bool, with_bias: bool,
                                           relu: bool) -> None:
    g = torch.Generator().manual_seed(m + k + o)
    x = torch.randn(m, k, generator=g)
    w = torch.randn(o, k, generator=g)
    if transposed_weight:  # an (O, K) view of a (K, O) matrix, as the transposed convs hand it in
        w = w.t().contiguous().t()
    b = torch.randn(o, generator=g) if with_bias else None
    with torch.no_grad():
        assert gemm.uses_onednn(x, w)
        got = gemm.linear(x, w, b, relu=relu)
    ref = x.double() @ w.double().t() + (0 if b is None else b.double())
    ref = ref.clamp_min(0) if relu else ref
    assert got.shape == (m, o) and got.dtype == torch.float32
    scale = float(ref.abs().max()) if ref.numel() else 0.0
    torch.testing.assert_close(got.double(), ref, atol=1e-5 * max(1.0, scale), rtol=1e-5)


def test_only_float32_cpu_outside_autocast_takes_onednn(monkeypatch: pytest.MonkeyPatch) -> None:
    x, w = torch.randn(4, 3), torch.randn(2, 3)
    assert gemm.uses_onednn(x, w)
    assert not gemm.uses_onednn(x.double(), w.double())  # oneDNN has no float64 GEMM: the exactness tests keep mm
    assert not gemm.uses_onednn(x.bfloat16(), w.bfloat16())  # bf16 mm is oneDNN already
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not gemm.uses_onednn(x, w)
    monkeypatch.setattr(gemm, "BACKEND", "mkl")
    assert not gemm.uses_onednn(x, w)


@pytest.mark.parametrize("weight_view", [False, True])
def test_onednn_backward_gives_the_float64_gradients(weight_view: bool) -> None:
    """Training through :class:`gemm.OneDNNLinear`: the gradients of x, the weight (a transposed view too, as the
    transposed convs pass it) and the bias equal the float64 ones, and come back in the leaves' shapes."""
    g = torch.Generator().manual_seed(5)
    x = torch.randn(50, 24, generator=g, requires_grad=True)
    w_leaf = torch.randn(24, 16, generator=g, requires_grad=True) if weight_view else \
        torch.randn(16, 24, generator=g, requires_grad=True)
    b = torch.randn(16, generator=g, requires_grad=True)
    r = torch.randn(50, 16, generator=g)
    w = w_leaf.t() if weight_view else w_leaf
    y = gemm.linear(x, w, b)
    assert y.grad_fn is not None and "OneDNNLinear" in type(y.grad_fn).__name__
    grads = torch.autograd.grad((y * r).sum(), (x, w_leaf, b))
    xd, wd, bd = (t.detach().double().requires_grad_(True) for t in (x, w_leaf, b))
    yd = xd @ (wd if weight_view else wd.t()) + bd
    ref = torch.autograd.grad((yd * r.double()).sum(), (xd, wd, bd))
    for got, want in zip(grads, ref):
        assert got.shape == want.shape
        torch.testing.assert_close(got.double(), want, atol=1e-4, rtol=1e-5)


@pytest.mark.parametrize(("backbone", "head"), [("dense", "dense"), ("sparse", "dense"), ("sparse", "sparse_exact"),
                                                ("sparse1_dense23", "dense")])
@pytest.mark.parametrize("workspace", [False, True])
def test_models_give_the_mkl_maps_in_onednn(monkeypatch: pytest.MonkeyPatch, backbone: str, head: str,
                                            workspace: bool) -> None:
    """Whole fp32 models in inference: the head maps with every GEMM in oneDNN equal those with every GEMM in MKL up
    to float rounding (the sparse convs, the exact head's product and the dense neck's levels switch library)."""
    from detector.models import build_model
    from tests.test_models_build import _scene, _tiny_config

    torch.manual_seed(0)
    model = build_model(_tiny_config(backbone=backbone, head=head))
    randomise_norms(model, 2)
    model.float().eval()
    pts = _scene(1)[0]
    maps = {}
    for backend in ("mkl", "auto"):
        monkeypatch.setattr(gemm, "BACKEND", backend)
        model.workspace = Workspace() if workspace else None
        with torch.no_grad():
            for _ in range(2):  # the workspace's second frame reuses its buffers
                maps[backend] = [m.clone() for m in model([pts])]
    for a, b in zip(maps["mkl"], maps["auto"]):
        scale = max(1.0, float(a.abs().max()))
        torch.testing.assert_close(b, a, atol=1e-5 * scale, rtol=1e-5)
        assert float(a.abs().max()) > 0


def test_dense_neck_in_chunks_equals_the_modules(monkeypatch: pytest.MonkeyPatch) -> None:
    """The dense neck's inference path (every level a oneDNN GEMM, a few coarse rows at a time, copied into one
    channels-last map) equals ConvTranspose2d + BatchNorm2d + ReLU and the concatenation; chunks far smaller than a
    level, with a remainder, so the chunk edges are exercised."""
    torch.manual_seed(0)
    neck = SecondFPN(in_channels=(8, 12, 16), out_channels=(5, 6, 7), upsample_strides=(1, 2, 4))
    randomise_norms(neck, 3)
    neck.float().eval()
    feats = [torch.randn(2, c, 24 // s, 20 // s).contiguous(memory_format=torch.channels_last)
             for c, s in ((8, 1), (12, 2), (16, 4))]
    # level 1: 400 bytes per coarse row, chunks of 5 of its 48 rows (a remainder of 3); level 3: one row per chunk
    monkeypatch.setattr("detector.models.neck.CHUNK_BYTES", 2000)
    with torch.no_grad():
        ref = torch.cat([nn.Sequential(*d)(f) for d, f in zip(neck.deblocks, feats)], dim=1)
        got = neck(feats, workspace=Workspace())
    assert got.shape == ref.shape == (2, 18, 24, 20)
    torch.testing.assert_close(got, ref, atol=1e-5, rtol=1e-5)
