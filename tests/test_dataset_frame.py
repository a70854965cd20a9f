"""A frame's scan: the compiled point filter keeps exactly the hits within the profile's range and z crop."""

from __future__ import annotations

import numpy as np
import pytest

from mpchair.dataset.frame import REFLECTANCE, _scan_points


@pytest.mark.parametrize("planar", [True, False])
def test_scan_points_keep_hits_in_range_and_crop(planar):
    rng = np.random.default_rng(5)
    d = rng.normal(size=(5000, 3))
    if planar:
        d /= np.abs(d[:, :1])  # x = +-1: planar depth is t * d_x
    t = rng.uniform(0, 30, 5000)
    face = np.where(rng.random(5000) < 0.2, -1, 7)
    out = _scan_points(t, face, d, planar, 0.5, 25.0, -2.0, 2.0, REFLECTANCE)
    rng_ = t * d[:, 0] if planar else t * np.linalg.norm(d, axis=1)
    pts = t[:, None] * d
    keep = (face >= 0) & (rng_ >= 0.5) & (rng_ <= 25.0) & (pts[:, 2] > -2.0) & (pts[:, 2] < 2.0)
    assert out.dtype == np.float32 and out.shape == (int(keep.sum()), 4)
    np.testing.assert_array_equal(out[:, :3], pts[keep].astype(np.float32))
    assert (out[:, 3] == REFLECTANCE).all()
    none = _scan_points(t, face, d, planar, 0.5, 25.0, -np.inf, np.inf, REFLECTANCE)
    assert len(none) == int(((face >= 0) & (rng_ >= 0.5) & (rng_ <= 25.0)).sum())  # no crop
