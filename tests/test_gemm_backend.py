"""The inference GEMM (``detector.ops.gemm``): oneDNN for float32 CPU inference, ``torch.mm`` (MKL) elsewhere; the
same values up to float rounding, for the op and for whole models (the sparse convs, the exact head, the dense neck)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from detector.models.neck import SecondFPN
from detector.ops import gemm
from detector.sparse.workspace import Workspace
from tests.test_sparse_backbone import randomise_norms

pytestmark = pytest.mark.skipif(not gemm.HAVE_ONEDNN, reason="this torch build has no oneDNN")


@pytest.mark.parametrize(("m", "k", "o"), [(0, 8, 4), (1, 5, 3), (37, 64, 17), (300, 576, 64), (64, 256, 512)])
@pytest.mark.parametrize("transposed_weight", [False, True])
@pytest.mark.parametrize("with_bias", [False, True])
def test_linear_equals_the_float64_product(m: int, k: int, o: int, transposed_weight: bool, with_bias: bool) -> None:
    g = torch.Generator().manual_seed(m + k + o)
    x = torch.randn(m, k, generator=g)
    w = torch.randn(o, k, generator=g)
    if transposed_weight:  # an (O, K) view of a (K, O) matrix, as the transposed convs hand it in
        w = w.t().contiguous().t()
    b = torch.randn(o, generator=g) if with_bias else None
    with torch.no_grad():
        assert gemm.uses_onednn(x, w)
        got = gemm.linear(x, w, b)
    ref = x.double() @ w.double().t() + (0 if b is None else b.double())
    assert got.shape == (m, o) and got.dtype == torch.float32
    scale = float(ref.abs().max()) if ref.numel() else 0.0
    torch.testing.assert_close(got.double(), ref, atol=1e-5 * max(1.0, scale), rtol=1e-5)


def test_only_float32_cpu_inference_takes_onednn(monkeypatch: pytest.MonkeyPatch) -> None:
    x, w = torch.randn(4, 3), torch.randn(2, 3)
    assert gemm.uses_onednn(x, w)
    assert not gemm.uses_onednn(x.double(), w.double())  # oneDNN has no float64 GEMM: the exactness tests keep mm
    assert not gemm.uses_onednn(x.bfloat16(), w.bfloat16())  # bf16 mm is oneDNN already
    wg = w.clone().requires_grad_(True)
    assert not gemm.uses_onednn(x, wg)  # autograd records it: mm, whose backward exists
    with torch.no_grad():
        assert gemm.uses_onednn(x, wg)
    y = gemm.linear(x, wg)
    y.sum().backward()
    torch.testing.assert_close(wg.grad, x.sum(0).expand(2, 3))
    with torch.autocast("cpu", dtype=torch.bfloat16), torch.no_grad():
        assert not gemm.uses_onednn(x, w)
    with gemm.gemm_backend("mkl"):
        assert not gemm.uses_onednn(x, w)
        assert gemm.library() == "mkl" and gemm.current_backend() == "mkl"
    assert gemm.current_backend() == "auto" and gemm.library() == "onednn"  # the block's choice ends with it


def test_bucket_rows_rounds_up_to_a_few_sizes_per_octave() -> None:
    """At least m, at most 12.5 % more above 64 rows, and few distinct sizes: the kernels oneDNN compiles repeat."""
    sizes = [gemm.bucket_rows(m) for m in range(1, 8193)]
    assert all(b >= m for m, b in zip(range(1, 8193), sizes))
    assert all(b <= max(64, m * 1.125) for m, b in zip(range(1, 8193), sizes))
    assert sizes[:64] == [64] * 64 and gemm.bucket_rows(65) == 72 and gemm.bucket_rows(1200) == 1280
    assert len(set(sizes)) <= 8 * 8  # 64 .. 8192: 7 octaves of 8 sizes, and 64


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
        with gemm.gemm_backend(backend):
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


@pytest.mark.parametrize("kernel_size", [1, 3, 5])
def test_subm_training_in_onednn_gives_the_mkl_values_and_gradients(monkeypatch: pytest.MonkeyPatch,
                                                                     kernel_size: int) -> None:
    """fp32 training of a SubM conv (``SubMGemm``: forward, mirrored input gradient, weight gradient, all in oneDNN at
    a bucketed row count) equals the MKL path up to float rounding; the padding rows change nothing."""
    from detector.sparse import SparseTensor, SubMConv2d, autograd
    from detector.sparse.synthetic import clustered_sites

    coords = clustered_sites((23, 17), 0.3, batch_size=2, seed=4)
    g = torch.Generator().manual_seed(9)
    feats = torch.randn(coords.shape[0], 6, generator=g)
    r = torch.randn(coords.shape[0], 5, generator=g)
    conv = SubMConv2d(6, 5, kernel_size, algorithm="gemm")
    calls = []
    real = autograd.linear

    def onednn_calls(x, w, b=None):  # count the oneDNN products the training path makes
        calls.append(gemm.uses_onednn(x, w))
        return real(x, w, b)

    monkeypatch.setattr(autograd, "linear", onednn_calls)
    results = {}
    for backend in ("mkl", "auto"):
        with gemm.gemm_backend(backend):
            f = feats.clone().requires_grad_(True)
            out = conv(SparseTensor(f, coords, (23, 17), 2)).features
            grads = torch.autograd.grad((out * r).sum(), (f, conv.weight))
            results[backend] = (out.detach(), *grads)
    assert calls == [True, True, True]  # forward, input gradient, weight gradient: oneDNN (and only under auto)
    assert coords.shape[0] % 64  # the oneDNN path pads its rows
    for a, b in zip(results["mkl"], results["auto"]):
        assert a.shape == b.shape
        torch.testing.assert_close(b, a, atol=1e-5 * max(1.0, float(a.abs().max())), rtol=1e-5)
    assert results["auto"][2].stride() == conv.weight.stride()  # the channels-last weight's own strides (DDP)


def test_sparse_model_training_step_in_onednn_equals_mkl(monkeypatch: pytest.MonkeyPatch) -> None:
    """A whole fp32 training forward + backward of the sparse model: loss and every parameter's gradient equal under
    both libraries up to float rounding."""
    from detector.models import build_model
    from tests.test_models_build import _scene, _tiny_config

    torch.manual_seed(0)
    model = build_model(_tiny_config(backbone="sparse", head="dense")).train()
    pts = _scene(2)[0]
    grads, bucketed = {}, []
    real = gemm._BucketedLinear.apply
    monkeypatch.setattr(gemm._BucketedLinear, "apply", lambda *a: bucketed.append(a[0].shape) or real(*a))
    for backend in ("mkl", "auto"):
        with gemm.gemm_backend(backend):
            model.zero_grad()
            out = model([pts])
            sum((o.float() * (i + 1)).sum() for i, o in enumerate(out)).backward()
            grads[backend] = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    # under auto only: the three blocks' 2x2 down-convs, the three neck levels (transposed, or 1x1 on the same sites)
    # and the head's three products on the neck's rows (the SubM convs count in SubMGemm, tested above)
    assert [tuple(s) for s in bucketed] == [(194, 64), (64, 64), (16, 128), (194, 16), (64, 32), (16, 64),
                                            (194, 96), (194, 96), (194, 96)]
    assert grads["mkl"].keys() == grads["auto"].keys() and len(grads["mkl"]) > 10
    for name, a in grads["mkl"].items():
        b = grads["auto"][name]
        torch.testing.assert_close(b, a, atol=1e-4 * max(1.0, float(a.abs().max())), rtol=1e-4, msg=name)


@pytest.mark.parametrize(("m", "k", "o"), [(0, 8, 4), (1, 5, 3), (100, 64, 17), (300, 576, 64)])
@pytest.mark.parametrize("with_bias", [False, True])
def test_train_linear_gives_the_float64_values_and_gradients(monkeypatch: pytest.MonkeyPatch, m: int, k: int, o: int,
                                                             with_bias: bool) -> None:
    """Training's product in oneDNN (``train_linear``: rows zero-padded to a bucket): output and the gradients of the
    input, weight (a transposed view, as the transposed convs pass it) and bias equal float64 autograd's; it is
    oneDNN's ``_BucketedLinear`` under ``auto`` and plain ``F.linear`` under ``mkl``."""
    g = torch.Generator().manual_seed(m + k + o)
    x0 = torch.randn(m, k, generator=g)
    w0 = torch.randn(k, o, generator=g)  # used as its (O, K) transpose
    b0 = torch.randn(o, generator=g) if with_bias else None
    r = torch.randn(m, o, generator=g)

    def run(dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
        leaves = [t.to(dtype).requires_grad_(True) for t in (x0, w0) + ((b0,) if with_bias else ())]
        x, w = leaves[0], leaves[1]
        out = gemm.train_linear(x, w.t(), leaves[2] if with_bias else None)
        return (out.detach(), *torch.autograd.grad((out * r.to(dtype)).sum(), leaves)), out.grad_fn

    for backend, node in (("auto", "_BucketedLinear"), ("mkl", "")):
        with gemm.gemm_backend(backend):
            assert gemm.trains_in_onednn(x0, w0) == (backend == "auto")
            got, fn = run(torch.float32)
            assert (node in type(fn).__name__) if node else "Bucketed" not in type(fn).__name__
            ref, _ = run(torch.float64)
            for a, b in zip(ref, got):
                assert b.shape == a.shape and b.dtype == torch.float32
                scale = float(a.abs().max()) if a.numel() else 0.0
                torch.testing.assert_close(b.double(), a, atol=1e-5 * max(1.0, scale), rtol=1e-5)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # bf16 autocast keeps its own (oneDNN bf16) matmul
        assert not gemm.trains_in_onednn(x0, w0)
