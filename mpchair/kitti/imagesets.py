"""KITTI ``ImageSets/{train,val,test}.txt``: one 6-digit frame id per line."""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

from mpchair.core.atomic import atomic_open
from mpchair.core.errors import InputError
from mpchair.core.text import read_text

_ID = re.compile(r"[0-9]{6}")


def read_imageset(path: str | Path) -> list[str]:
    """Read the frame ids of a split file, in file order.

    Blank lines and a missing trailing newline (OpenPCDet's copies) are fine; a line that is not exactly six digits
    (after stripping surrounding whitespace) or a repeated id is an :class:`InputError` naming the file and line.
    """
    path = Path(path)
    text = read_text(path, "image set file")
    ids: list[str] = []
    seen: dict[str, int] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s:
            continue
        if not _ID.fullmatch(s):
            raise InputError(f"frame id {s[:40]!r} is not a 6-digit number", path, lineno)
        if s in seen:
            raise InputError(f"frame id {s} repeated (first on line {seen[s]})", path, lineno)
        seen[s] = lineno
        ids.append(s)
    return ids


def write_imageset(path: str | Path, ids: Iterable[str | int]) -> None:
    """Atomically write frame ids (strings of 6 digits, or ints formatted ``%06d``), one per line, final newline."""
    out = []
    for i in ids:
        s = f"{i:06d}" if isinstance(i, int) else str(i)
        if not _ID.fullmatch(s):
            raise ValueError(f"frame id {i!r} is not a 6-digit number")
        out.append(s)
    if len(set(out)) != len(out):
        raise ValueError("frame ids must be unique")
    with atomic_open(path, "w") as f:
        f.write("".join(s + "\n" for s in out))
