"""Object boxes of a ``.house`` ``O`` record: the stored oriented box and its vertically aligned (yaw-only) box.

The ``O`` record stores a centre, two axes and three radii (half-lengths); GAPS normalises a0, makes a1 orthogonal,
sets a2 = a0 × a1 and sorts the axes by radius, largest first. The vertical axis can therefore be any of the three.

The aligned box (world frame, metres) is ``[x, y, z_center, l, w, h, yaw]``: up axis k = argmax_i |a_i · z|,
h = 2 r_k, l / w = the larger / smaller full extent of the two other axes, yaw = atan2 of the long axis's XY
direction, wrapped to [-pi/2, pi/2) (a box's long axis has no direction).
"""

from __future__ import annotations

import math

import numpy as np

from mpchair.geometry.frames import wrap_angle

#: Boxes whose up axis deviates from world z by more than this are reported as tilted.
TILT_WARN_DEG = 10.0


def orthonormal_axes(axis0: np.ndarray, axis1: np.ndarray) -> np.ndarray:
    """(3,3) rows a0, a1, a2: a0 normalised, a1 Gram-Schmidt against a0 and normalised, a2 = a0 × a1.

    Degenerate input (zero or parallel axes) falls back to the world axes so that a bad record yields a box, not NaN.
    """
    a0 = np.asarray(axis0, dtype=np.float64)
    a1 = np.asarray(axis1, dtype=np.float64)
    n0 = np.linalg.norm(a0)
    a0 = a0 / n0 if n0 > 1e-12 else np.array([1.0, 0.0, 0.0])
    a1 = a1 - np.dot(a1, a0) * a0
    n1 = np.linalg.norm(a1)
    if n1 > 1e-12:
        a1 = a1 / n1
    else:
        # Pick any unit vector orthogonal to a0.
        helper = np.array([0.0, 0.0, 1.0]) if abs(a0[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        a1 = np.cross(helper, a0)
        a1 /= np.linalg.norm(a1)
    return np.stack([a0, a1, np.cross(a0, a1)])


def aligned_box(center: np.ndarray, axes: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, float]:
    """Vertically aligned box ``(7,)`` [x, y, z, l, w, h, yaw] (world frame) of an oriented box, and its tilt (deg).

    ``axes`` (3,3) rows are orthonormal box axes, ``radii`` (3,) half-lengths, ``center`` (3,) world metres. The tilt
    is the angle between the chosen up axis and world z; callers warn above :data:`TILT_WARN_DEG`.
    """
    axes = np.asarray(axes, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    up_dot = np.abs(axes[:, 2])
    k = int(np.argmax(up_dot))
    tilt = math.degrees(math.acos(min(1.0, float(up_dot[k]))))
    i, j = (a for a in range(3) if a != k)
    if radii[j] > radii[i]:
        i, j = j, i  # i is the long horizontal axis; ties keep the lower index
    yaw = float(wrap_angle(math.atan2(axes[i, 1], axes[i, 0]), offset=0.5, period=math.pi))
    c = np.asarray(center, dtype=np.float64)
    box = np.array([c[0], c[1], c[2], 2 * radii[i], 2 * radii[j], 2 * radii[k], yaw], dtype=np.float64)
    return box, tilt


def obb_from_aligned(box: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``O`` record form of a yaw-only box ``[x, y, z, l, w, h, yaw]`` (world frame): ``center (3,)``,
    ``axes (3,3)`` rows a0, a1, a2 = a0 × a1 sorted by radius (largest first) as GAPS writes them, ``radii (3,)``."""
    x, y, z, l, w, h, yaw = (float(v) for v in box)
    c, s = math.cos(yaw), math.sin(yaw)
    cand = [(l / 2, np.array([c, s, 0.0])), (w / 2, np.array([-s, c, 0.0])), (h / 2, np.array([0.0, 0.0, 1.0]))]
    order = sorted(range(3), key=lambda k: -cand[k][0])  # stable: equal radii keep l, w, h order
    a0, a1 = cand[order[0]][1], cand[order[1]][1]
    axes = np.stack([a0, a1, np.cross(a0, a1)])
    radii = np.array([cand[k][0] for k in order])
    return np.array([x, y, z]), axes, radii
