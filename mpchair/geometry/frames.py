"""Angles and rigid transforms between frames (all z-up frames: world, sensor; plus the sensor → camera axis swap).

Transforms are (4,4) float64 homogeneous matrices ``T`` mapping column points ``p_to = T · p_from``; a name like
``T_world_from_sensor`` reads right to left. The sensor frame is x forward, y left, z up (right-handed, metres), the
same axes as the KITTI LiDAR frame; the world frame is Matterport's (z up, metres).
"""

from __future__ import annotations

import math

import numpy as np

#: Rotation sensor/LiDAR axes (x forward, y left, z up) → camera axes (x right, y down, z forward):
#: ``x_cam = -y_sensor``, ``y_cam = -z_sensor``, ``z_cam = x_sensor``.
SENSOR_TO_CAMERA: np.ndarray = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
SENSOR_TO_CAMERA.setflags(write=False)

#: Rotation habitat's run-time frame (y up, -z forward) → the Matterport world frame (z up): habitat rotates every MP3D
#: asset by -90 deg about +x at load time, so ``(x, y, z)_habitat → (x, -z, y)_mp3d`` (its inverse is the transpose,
#: ``(x, y, z)_mp3d → (x, z, -y)_habitat``). Habitat's ``.navmesh`` files, agent states and episodes use that frame.
HABITAT_TO_MP3D: np.ndarray = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
HABITAT_TO_MP3D.setflags(write=False)


def wrap_angle(a: np.ndarray | float, offset: float = 0.5, period: float = 2 * math.pi) -> np.ndarray:
    """Wrap angles (radians) into ``[-offset, 1 - offset) * period``: ``a - floor(a / period + offset) * period``.

    The default gives ``[-pi, pi)``. Returns float64 (a 0-d array for a scalar input).
    """
    a = np.asarray(a, dtype=np.float64)
    out = a - np.floor(a / period + offset) * period
    # Rounding can step just outside the half-open range (a = -1e-17 can give +pi; a = -5e-324 with offset 0 stays
    # negative); fold such results back in, first from below, then from the open upper end.
    lower, upper = -offset * period, (1.0 - offset) * period
    out = np.where(out < lower, out + period, out)
    return np.where(out >= upper, out - period, out)


def canonical_yaw(yaw: np.ndarray | float) -> np.ndarray:
    """The heading of a box without a front (a chair's fitted axes): its long side's direction, in ``[-pi/2, pi/2)``.

    Adding pi turns a front-less box onto itself, so the label is made a function of what the sensor sees, as the
    original Matterport-Chair generator did: ``wrap_angle(yaw, offset=0.5, period=pi)``. Applied to sensor-frame
    label boxes, KITTI ``rotation_y = -yaw - pi/2`` then lies in ``(-pi, 0]``.
    """
    return wrap_angle(yaw, offset=0.5, period=math.pi)


def rigid_from(R: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
    """(4,4) rigid transform from a (3,3) rotation and an optional (3,) translation (metres)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def yaw_matrix(yaw: float | np.ndarray) -> np.ndarray:
    """(4,4) rotation by ``yaw`` radians CCW about +z (no translation); an array of K yaws gives (K,4,4)."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros(yaw.shape + (4, 4))
    T[..., 0, 0] = c
    T[..., 0, 1] = -s
    T[..., 1, 0] = s
    T[..., 1, 1] = c
    T[..., 2, 2] = 1.0
    T[..., 3, 3] = 1.0
    return T


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4,4) rigid transform, exactly ``[R^T | -R^T t]`` (no general matrix inversion)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"invert_rigid expects a (4,4) matrix, got shape {T.shape}")
    R, t = T[:3, :3], T[:3, 3]
    return rigid_from(R.T, -R.T @ t)


def rotate_vectors(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N,3) float64 vectors ``v`` rotated by the (3,3) matrix ``R`` (``v @ R.T``), frame-agnostic.

    Computed column by column instead of with ``@``: a (N,3) x (3,3) product gains nothing from BLAS, and BLAS's own
    threads oversubscribe the cores when several worker processes (``mpchair generate --workers``) or a training job
    run beside it; measured 40x slower than this under such load.
    """
    v = np.asarray(v, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    out = np.empty((len(v), 3))
    for i in range(3):
        out[:, i] = v[:, 0] * R[i, 0] + v[:, 1] * R[i, 1] + v[:, 2] * R[i, 2]
    return out


def transform_points(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Apply the (4,4) transform ``T`` to (N,3) points (metres); returns (N,3) float64 in the target frame."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"transform_points expects (N, 3) points, got shape {p.shape}")
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"transform_points expects a (4,4) transform, got shape {T.shape}")
    return rotate_vectors(p, T[:3, :3]) + T[:3, 3]


def yaw_of(T: np.ndarray, atol: float = 1e-6) -> float:
    """The yaw (radians, CCW about +z) of a rigid (4,4) transform whose rotation is about z only.

    Raises ``ValueError`` when the rotation tilts the z axis or is not a proper rotation (beyond ``atol``).
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"expected a (4,4) transform, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=atol) or np.linalg.det(R) < 0:
        raise ValueError("transform is not rigid (its rotation is not orthonormal with det +1)")
    if abs(R[2, 0]) > atol or abs(R[2, 1]) > atol or abs(R[0, 2]) > atol or abs(R[1, 2]) > atol:
        raise ValueError("transform rotates about an axis other than z; yaw-only boxes cannot follow it")
    return math.atan2(R[1, 0], R[0, 0])


def transform_boxes(boxes: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Move (N,7) boxes ``[x, y, z, l, w, h, yaw]`` by a rigid (4,4) ``T`` whose rotation is about z only.

    Centres are transformed, sizes kept, yaw increased by the transform's yaw and wrapped to ``[-pi, pi)``. Raises
    ``ValueError`` if ``T`` tilts the z axis (a tilted box is no longer a yaw-only box). Returns float64.
    """
    b = np.asarray(boxes, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"transform_boxes expects (N, 7) boxes, got shape {b.shape}")
    dyaw = yaw_of(T)
    out = b.copy()
    out[:, :3] = transform_points(b[:, :3], T)
    out[:, 6] = wrap_angle(b[:, 6] + dyaw)
    return out


def habitat_to_mp3d(points: np.ndarray) -> np.ndarray:
    """(N,3) float64 points in habitat's y-up frame → the Matterport world frame (z up), metres: ``(x, -z, y)``."""
    return np.asarray(points, dtype=np.float64).reshape(-1, 3) @ HABITAT_TO_MP3D.T


def mp3d_to_habitat(points: np.ndarray) -> np.ndarray:
    """(N,3) float64 points in the Matterport world frame (z up) → habitat's y-up frame, metres: ``(x, z, -y)``."""
    return np.asarray(points, dtype=np.float64).reshape(-1, 3) @ HABITAT_TO_MP3D


def make_tr_velo_to_cam(translation: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(3,4) ``Tr_velo_to_cam`` = ``[SENSOR_TO_CAMERA | t]``: a pure axis swap plus ``t`` (camera frame, metres).

    ``t`` is where the sensor origin lands in the camera frame. With ``R0_rect`` = identity this is exactly the case
    where the KITTI box conversions (``rotation_y = -yaw - pi/2``) are exact.
    """
    Tr = np.zeros((3, 4))
    Tr[:, :3] = SENSOR_TO_CAMERA
    Tr[:, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return Tr
