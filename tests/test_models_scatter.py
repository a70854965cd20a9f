"""The dense scatter (detector.models.scatter): one in-place canvas, bit for bit the earlier three-canvas scatter."""

from __future__ import annotations

import torch

from detector.models.scatter import scatter_to_canvas


def _three_canvas_scatter(features: torch.Tensor, coords: torch.Tensor, batch_size: int, shape) -> torch.Tensor:
    """The scatter as it was before issue 15: index_copy into a fresh canvas, then a contiguous NCHW copy."""
    ny, nx = shape
    flat = (coords[:, 0] * ny + coords[:, 1]) * nx + coords[:, 2]
    canvas = features.new_zeros((batch_size * ny * nx, features.shape[1])).index_copy(0, flat, features)
    return canvas.view(batch_size, ny, nx, -1).permute(0, 3, 1, 2).contiguous()


def _pillars(seed: int, batch_size: int = 3, shape=(40, 24), n: int = 150, c: int = 16):
    g = torch.Generator().manual_seed(seed)
    ny, nx = shape
    keys = torch.randperm(batch_size * ny * nx, generator=g)[:n]  # unique sites, random order
    coords = torch.stack([keys // (ny * nx), keys // nx % ny, keys % nx], dim=1)
    return torch.randn(n, c, generator=g), coords


def test_in_place_scatter_equals_the_three_canvas_scatter_bit_for_bit() -> None:
    for seed in range(3):
        feats, coords = _pillars(seed)
        old = _three_canvas_scatter(feats, coords, 3, (40, 24))
        for channels_last in (False, True):
            new = scatter_to_canvas(feats, coords, 3, (40, 24), channels_last=channels_last)
            assert new.shape == old.shape == (3, 16, 40, 24) and new.dtype == old.dtype
            assert torch.equal(new, old)
            fmt = torch.channels_last if channels_last else torch.contiguous_format
            assert new.is_contiguous(memory_format=fmt)
        # an empty batch item stays an all-zero plane
        keep = coords[:, 0] != 1
        new = scatter_to_canvas(feats[keep], coords[keep], 3, (40, 24), channels_last=True)
        assert torch.equal(new, _three_canvas_scatter(feats[keep], coords[keep], 3, (40, 24)))
        assert not bool(new[1].any())


def test_scatter_gradient_equals_the_three_canvas_scatter() -> None:
    feats, coords = _pillars(7)
    weight = torch.randn(3, 16, 40, 24)
    grads = []
    for fn in (_three_canvas_scatter, lambda *a: scatter_to_canvas(*a, channels_last=False),
               lambda *a: scatter_to_canvas(*a, channels_last=True)):
        f = feats.clone().requires_grad_(True)
        (fn(f, coords, 3, (40, 24)) * weight).sum().backward()
        grads.append(f.grad)
    assert torch.equal(grads[0], grads[1]) and torch.equal(grads[0], grads[2])
    # the gradient of a pillar is the weight at its cell
    b, y, x = coords[0].tolist()
    assert torch.equal(grads[0][0], weight[b, :, y, x])
