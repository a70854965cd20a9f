"""The labelled region of a sensor: where a box centre must lie for the box to be labelled (or scored) at all.

Three tests on a box centre ``(x, y, z)`` in the sensor frame (x forward, y left, z up, metres), the first three
filters of the original Matterport-Chair generator: **height** ``|z| <= max_abs_dz``; **distance**
``hypot(x, y) <= max_distance``; **field of view** ``x > 0`` and ``atan2(|y|, x) < half_fov`` (radians; ``None`` = no
field-of-view test, a 360 degree sensor). ``mpchair.labels`` rejects boxes outside it; ``detector stream-eval`` drops
predictions whose centre lies outside the region of the frame they are scored in.
"""

from __future__ import annotations

import math

import numpy as np

#: The tests in the order they are applied (the first failure is a label's reject reason).
REGION_TESTS: tuple[str, ...] = ("height", "distance", "fov")


def region_failures(centres: np.ndarray, max_abs_dz: float, max_distance: float, half_fov: float | None) -> list[str]:
    """Per (N,3+) sensor-frame centre, the first failed test of :data:`REGION_TESTS`, or ``""`` inside the region.

    Scalar ``math`` per centre on purpose: the label filters have always used these exact float operations, and a
    vectorised ``hypot`` / ``arctan2`` may differ in the last bit at the boundary.
    """
    c = np.asarray(centres, dtype=np.float64)
    out = []
    for x, y, z in (c.reshape(-1, c.shape[-1])[:, :3] if c.size else ()):
        if abs(z) > max_abs_dz:
            out.append("height")
        elif math.hypot(x, y) > max_distance:
            out.append("distance")
        elif half_fov is not None and not (x > 0 and math.atan2(abs(y), x) < half_fov):
            out.append("fov")
        else:
            out.append("")
    return out


def in_region(centres: np.ndarray, max_abs_dz: float, max_distance: float, half_fov: float | None) -> np.ndarray:
    """(N,) bool: sensor-frame centres (N,3+) inside the region (see :func:`region_failures`)."""
    return np.array([r == "" for r in region_failures(centres, max_abs_dz, max_distance, half_fov)], dtype=bool)
