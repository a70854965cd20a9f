"""KITTI ``calib/%06d.txt``: the seven matrices of one frame, read by key and written in the standard order."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from mpchair.core.atomic import atomic_open
from mpchair.core.errors import InputError
from mpchair.core.text import read_text

#: Keys in the order OpenPCDet expects them (it reads calib files by line index), with their shapes.
CALIB_KEYS: tuple[tuple[str, tuple[int, int]], ...] = (
    ("P0", (3, 4)),
    ("P1", (3, 4)),
    ("P2", (3, 4)),
    ("P3", (3, 4)),
    ("R0_rect", (3, 3)),
    ("Tr_velo_to_cam", (3, 4)),
    ("Tr_imu_to_velo", (3, 4)),
)


def to_4x4(m: np.ndarray) -> np.ndarray:
    """Extend a (3,3) rotation or (3,4) ``[R|t]`` to a homogeneous (4,4) float64 matrix (1 at bottom right)."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape not in ((3, 3), (3, 4), (4, 4)):
        raise ValueError(f"to_4x4 expects a (3,3), (3,4) or (4,4) matrix, got shape {m.shape}")
    out = np.eye(4)
    out[: m.shape[0], : m.shape[1]] = m
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class Calib:
    """The calibration of one KITTI frame (float64 arrays, metres / pixels).

    ``P0..P3`` (3,4) project the *rectified camera-0 frame* into images 0-3 (``P2`` = ``image_2``); ``R0_rect`` (3,3)
    rectifies camera 0; ``Tr_velo_to_cam`` (3,4) maps LiDAR / sensor points into the (unrectified) camera-0 frame;
    ``Tr_imu_to_velo`` (3,4) maps IMU points into the LiDAR frame.
    """

    P0: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    P3: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray
    Tr_imu_to_velo: np.ndarray

    def __post_init__(self) -> None:
        for key, shape in CALIB_KEYS:
            value = np.array(getattr(self, key), dtype=np.float64)  # a private copy, frozen below
            if value.shape != shape:
                raise ValueError(f"Calib.{key} must have shape {shape}, got {value.shape}")
            value.setflags(write=False)
            object.__setattr__(self, key, value)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calib):
            return NotImplemented
        return all(np.array_equal(getattr(self, k), getattr(other, k)) for k, _ in CALIB_KEYS)

    def velo_to_rect(self) -> np.ndarray:
        """(4,4) transform LiDAR/sensor frame → rectified camera-0 frame: ``R0_rect(4x4) · Tr_velo_to_cam(4x4)``."""
        return to_4x4(self.R0_rect) @ to_4x4(self.Tr_velo_to_cam)

    def rect_to_velo(self) -> np.ndarray:
        """(4,4) transform rectified camera-0 frame → LiDAR/sensor frame (the inverse of :meth:`velo_to_rect`)."""
        return np.linalg.inv(self.velo_to_rect())

    def velo_to_image(self) -> np.ndarray:
        """(3,4) projection LiDAR/sensor frame → homogeneous image_2 pixels: ``P2 · R0_rect · Tr_velo_to_cam``."""
        return self.P2 @ self.velo_to_rect()

    def rect_to_image(self, pts: np.ndarray) -> np.ndarray:
        """Project (N,3) rectified-camera points (metres) to (N,2) image_2 pixels ``(u, v)`` through ``P2``.

        Points must be in front of the camera (positive projective depth); no clipping is done here.
        """
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        uvw = pts @ self.P2[:, :3].T + self.P2[:, 3]
        return uvw[:, :2] / uvw[:, 2:3]

    @classmethod
    def from_dict(cls, values: dict[str, np.ndarray]) -> Calib:
        """Build from a ``{key: array}`` mapping holding all seven keys (arrays reshaped to their standard shapes)."""
        return cls(**{k: np.asarray(values[k], dtype=np.float64).reshape(shape) for k, shape in CALIB_KEYS})


def read_calib(path: str | Path) -> Calib:
    """Read a KITTI object calib file: ``KEY: v v v ...`` lines, parsed by key (any order, blank lines skipped).

    Unknown extra keys are ignored; a missing key, a wrong value count, a duplicated key or a non-finite /
    non-numeric value is an :class:`InputError` naming the file and line.
    """
    path = Path(path)
    text = read_text(path, "calib file")
    shapes = dict(CALIB_KEYS)
    values: dict[str, np.ndarray] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        key, sep, rest = line.partition(":")
        key = key.strip()
        if not sep or not key or " " in key:
            raise InputError(f"expected 'KEY: values', got {line[:40]!r}", path, lineno)
        if key not in shapes:
            continue  # e.g. extra keys some tools add; the seven standard ones are all we need
        if key in values:
            raise InputError(f"duplicate key {key!r}", path, lineno)
        tokens = rest.split()
        shape = shapes[key]
        if len(tokens) != shape[0] * shape[1]:
            raise InputError(f"{key} has {len(tokens)} values, expected {shape[0] * shape[1]}", path, lineno)
        numbers = []
        for tok in tokens:
            try:
                v = float(tok)
            except ValueError:
                raise InputError(f"{key}: {tok!r} is not a number", path, lineno) from None
            if not math.isfinite(v):
                raise InputError(f"{key}: {tok!r} is not a finite number", path, lineno)
            numbers.append(v)
        values[key] = np.array(numbers, dtype=np.float64).reshape(shape)
    missing = [k for k, _ in CALIB_KEYS if k not in values]
    if missing:
        raise InputError(f"missing calib key(s): {', '.join(missing)}", path)
    return Calib.from_dict(values)


def _format_value(v: float) -> str:
    for digits in range(12, 17):
        s = f"{v:.{digits}e}"
        if float(s) == v:
            return s
    return f"{v:.16e}"  # 17 significant digits always round-trip a float64


def format_calib(calib: Calib) -> str:
    """The text of a calib file: the seven keys in the standard order, single spaces, ``%.12e`` values.

    A value that ``%.12e`` would round is written with as many more digits (up to 17 significant) as it needs to read
    back exactly, so any float64 calib round-trips bit for bit.

    Like the official files it ends with an empty line, so a KITTI calib file read and re-written is byte-identical.
    """
    lines = []
    for key, _ in CALIB_KEYS:
        values = getattr(calib, key).reshape(-1)
        lines.append(key + ": " + " ".join(_format_value(float(v)) for v in values))
    return "\n".join(lines) + "\n\n"


def write_calib(path: str | Path, calib: Calib) -> None:
    """Atomically write ``calib`` as a KITTI calib file (keys in the order OpenPCDet's line-index reader expects)."""
    with atomic_open(path, "w") as f:
        f.write(format_calib(calib))
