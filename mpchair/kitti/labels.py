"""KITTI ``label_2/%06d.txt``: one object per line, 15 columns (ground truth) or 16 (results, with a score).

Fields are kept in the file's own frame and units: ``dims_hwl`` (height, width, length, metres), ``location`` the
bottom centre in the rectified camera-0 frame (metres), ``rotation_y`` about camera +y (radians), ``bbox`` the image_2
box ``[left, top, right, bottom]`` in 0-based pixels.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from mpchair.core.atomic import atomic_open
from mpchair.core.errors import InputError
from mpchair.core.text import read_text

DONTCARE = "DontCare"

# DontCare rows carry the devkit's "invalid" values, written as integers exactly like the KITTI ground truth:
# truncated -1, occluded -1, alpha -10, (bbox), dims -1 -1 -1, location -1000 -1000 -1000, rotation_y -10.
_DONTCARE_HEAD = ("-1", "-1", "-10")
_DONTCARE_TAIL = ("-1", "-1", "-1", "-1000", "-1000", "-1000", "-10")

_FLOAT_FIELDS = ("truncated", "alpha", "bbox", "dims_hwl", "location", "rotation_y")


@dataclasses.dataclass(frozen=True, eq=False)
class Labels:
    """The objects of one KITTI label file, as parallel arrays of length N (file order kept).

    ``names (N,) str``, ``truncated (N,) float64``, ``occluded (N,) int64``, ``alpha (N,) float64`` radians,
    ``bbox (N,4) float64`` ``[l, t, r, b]`` image_2 pixels, ``dims_hwl (N,3) float64`` metres, ``location (N,3)
    float64`` bottom centre in the rectified camera frame (metres), ``rotation_y (N,) float64`` radians about camera +y,
    ``score (N,) float64`` or ``None`` (ground truth).
    """

    names: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    dims_hwl: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray | None = None

    def __post_init__(self) -> None:
        names = np.asarray(self.names, dtype=str).reshape(-1)
        n = len(names)
        fixed = {
            "names": names,
            "truncated": np.asarray(self.truncated, dtype=np.float64).reshape(n),
            "occluded": np.asarray(self.occluded, dtype=np.int64).reshape(n),
            "alpha": np.asarray(self.alpha, dtype=np.float64).reshape(n),
            "bbox": np.asarray(self.bbox, dtype=np.float64).reshape(n, 4),
            "dims_hwl": np.asarray(self.dims_hwl, dtype=np.float64).reshape(n, 3),
            "location": np.asarray(self.location, dtype=np.float64).reshape(n, 3),
            "rotation_y": np.asarray(self.rotation_y, dtype=np.float64).reshape(n),
            "score": None if self.score is None else np.asarray(self.score, dtype=np.float64).reshape(n),
        }
        for key, value in fixed.items():
            if value is not None:
                value = value.copy()
                value.setflags(write=False)
            object.__setattr__(self, key, value)

    @classmethod
    def empty(cls, with_score: bool = False) -> Labels:
        """Zero objects (with an empty score array when ``with_score``)."""
        z = np.zeros(0)
        return cls(
            np.zeros(0, dtype=str),
            z,
            z,
            z,
            np.zeros((0, 4)),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            z,
            z if with_score else None,
        )

    @classmethod
    def concatenate(cls, parts: list[Labels]) -> Labels:
        """Join label sets in order; all must have a score or none."""
        if not parts:
            return cls.empty()
        has_score = {p.score is not None for p in parts}
        if len(has_score) != 1:
            raise ValueError("cannot concatenate Labels with and without scores")
        cat = {
            f.name: np.concatenate([getattr(p, f.name) for p in parts])
            for f in dataclasses.fields(cls)
            if f.name != "score"
        }
        score = np.concatenate([p.score for p in parts]) if has_score == {True} else None
        return cls(**cat, score=score)

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index: np.ndarray | slice | list[int]) -> Labels:
        """Select objects with a boolean mask, an index array or a slice (a new ``Labels``)."""
        if isinstance(index, (int, np.integer)):
            index = [int(index)]
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return Labels(**{k: None if v is None else v[index] for k, v in values.items()})

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Labels):
            return NotImplemented
        for f in dataclasses.fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
                return False
        return True

    def dontcare_mask(self) -> np.ndarray:
        """(N,) bool: rows whose type is ``DontCare``."""
        return self.names == DONTCARE

    def dontcare(self) -> Labels:
        """Only the ``DontCare`` rows."""
        return self[self.dontcare_mask()]

    def objects(self) -> Labels:
        """Everything but the ``DontCare`` rows."""
        return self[~self.dontcare_mask()]

    def with_names(self, *names: str) -> Labels:
        """Only rows whose type is one of ``names`` (e.g. ``labels.with_names("Car", "Van")``)."""
        return self[np.isin(self.names, list(names))]


def read_labels(path: str | Path) -> Labels:
    """Read a KITTI label file: 15 columns (ground truth) or 16 (with score); an empty file gives zero labels.

    Names are kept exactly as written. Blank lines are skipped. A wrong column count, a file mixing 15- and 16-column
    rows, a non-number, a NaN / infinity or a non-integer ``occluded`` is an :class:`InputError` naming file and line.
    """
    path = Path(path)
    return parse_labels(read_text(path, "label file"), path)


def parse_labels(text: str, path: str | Path) -> Labels:
    """The labels in ``text``, a label file's content (:func:`read_labels`; ``path`` names it in errors: a file, or an
    entry of an archive)."""
    names: list[str] = []
    rows: list[list[float]] = []
    occluded: list[int] = []
    ncols: int | None = None
    first_line = 0
    for lineno, raw in enumerate(text.splitlines(), start=1):
        tokens = raw.split()
        if not tokens:
            continue
        if len(tokens) not in (15, 16):
            raise InputError(f"label line has {len(tokens)} columns, expected 15 (or 16 with a score)", path, lineno)
        if ncols is None:
            ncols, first_line = len(tokens), lineno
        elif len(tokens) != ncols:
            raise InputError(
                f"label line has {len(tokens)} columns but line {first_line} has {ncols} (a file mixes ground truth "
                "and result rows)",
                path,
                lineno,
            )
        names.append(tokens[0])
        values = []
        for col, tok in enumerate(tokens[1:], start=2):
            try:
                v = float(tok)
            except ValueError:
                raise InputError(f"column {col}: {tok!r} is not a number", path, lineno) from None
            if not math.isfinite(v):
                raise InputError(f"column {col}: {tok!r} is not a finite number", path, lineno)
            values.append(v)
        if values[1] != int(values[1]):
            raise InputError(f"column 3 (occluded): {tokens[2]!r} is not an integer", path, lineno)
        occluded.append(int(values[1]))
        rows.append(values)
    if not rows:
        return Labels.empty()
    a = np.array(rows, dtype=np.float64)
    return Labels(
        names=np.array(names, dtype=str),
        truncated=a[:, 0],
        occluded=np.array(occluded, dtype=np.int64),
        alpha=a[:, 2],
        bbox=a[:, 3:7],
        dims_hwl=a[:, 7:10],
        location=a[:, 10:13],
        rotation_y=a[:, 13],
        score=a[:, 14] if ncols == 16 else None,
    )


def _fmt(v: float, precision: int) -> str:
    s = f"{v:.{precision}f}"
    return "0." + "0" * precision if s == "-0." + "0" * precision else s  # no "-0.00" from tiny negatives


def format_labels(labels: Labels, precision: int | None = None) -> str:
    """The text of a label file: object rows in order, then DontCare rows (with the devkit's invalid 3D values).

    ``precision`` is the number of decimals of every float field (default: 2 for ground truth like KITTI, 4 for
    results, i.e. when ``labels.score`` is set, like OpenPCDet). Single spaces, one row per line.
    """
    if precision is None:
        precision = 2 if labels.score is None else 4
    if precision < 0:
        raise ValueError("precision must be >= 0")
    for key in _FLOAT_FIELDS:
        if not np.all(np.isfinite(getattr(labels, key))):
            raise ValueError(f"Labels.{key} holds NaN or infinity; KITTI label files need finite numbers")
    for name in labels.names:
        if not name or any(c.isspace() for c in name):
            raise ValueError(f"label type {name!r} must be a non-empty word without whitespace")
    if labels.score is not None and not np.all(np.isfinite(labels.score)):
        raise ValueError("Labels.score holds NaN or infinity")
    dc = labels.dontcare_mask()
    order = np.concatenate([np.flatnonzero(~dc), np.flatnonzero(dc)])
    lines = []
    for i in order:
        if dc[i]:
            fields = [*_DONTCARE_HEAD, *(_fmt(v, precision) for v in labels.bbox[i]), *_DONTCARE_TAIL]
        else:
            fields = [
                _fmt(labels.truncated[i], precision),
                str(int(labels.occluded[i])),
                _fmt(labels.alpha[i], precision),
            ]
            fields += [_fmt(v, precision) for v in labels.bbox[i]]
            fields += [_fmt(v, precision) for v in labels.dims_hwl[i]]
            fields += [_fmt(v, precision) for v in labels.location[i]]
            fields.append(_fmt(labels.rotation_y[i], precision))
        if labels.score is not None:
            fields.append(_fmt(labels.score[i], precision))
        lines.append(" ".join([str(labels.names[i]), *fields]))
    return "".join(line + "\n" for line in lines)


def write_labels(path: str | Path, labels: Labels, precision: int | None = None) -> None:
    """Atomically write ``labels`` as a KITTI label file (see :func:`format_labels` for layout and precision).

    Writing zero labels gives an empty file (fine for result files; OpenPCDet's GT info builder needs at least one
    row, so a frame without objects should get a DontCare row).
    """
    text = format_labels(labels, precision)
    with atomic_open(path, "w") as f:
        f.write(text)
