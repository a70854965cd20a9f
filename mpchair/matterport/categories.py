"""The mpcat40 category table (Matterport3D ``metadata/mpcat40.tsv``) and class selection by name or index.

The table is bundled as ``mpchair/data/mpcat40.tsv`` (index, name, display colour): indices 0 (``void``) to 40
(``misc``) plus 41 (``unlabeled``). An object is a chair iff its ``C`` record's mpcat40 index is 3; ``stool`` (19),
``sofa`` (10) and ``seating`` (34) are different classes.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

from mpchair.core.errors import InputError

#: mpcat40 index of ``chair``, the class of the Matterport-Chair dataset.
CHAIR = 3


@dataclass(frozen=True)
class Mpcat40:
    """One mpcat40 class: ``index`` (0..41), ``name`` (``"chair"``, ``"tv_monitor"``), ``color`` (``"#98df8a"``)."""

    index: int
    name: str
    color: str


@lru_cache(maxsize=1)
def mpcat40_table() -> tuple[Mpcat40, ...]:
    """The bundled mpcat40 table, ordered by index (entry ``i`` has index ``i``)."""
    text = resources.files("mpchair").joinpath("data/mpcat40.tsv").read_text(encoding="utf-8")
    rows = []
    for line in text.splitlines()[1:]:
        if line.strip():
            idx, name, color = line.split("\t")
            rows.append(Mpcat40(int(idx), name, color))
    assert [r.index for r in rows] == list(range(len(rows))), "mpcat40.tsv must be dense and ordered"
    return tuple(rows)


def mpcat40_name(index: int) -> str:
    """Name of mpcat40 class ``index``; ``"none"`` for -1 (no category)."""
    if index == -1:
        return "none"
    table = mpcat40_table()
    if not 0 <= index < len(table):
        raise InputError(f"mpcat40 index {index} is outside 0..{len(table) - 1}")
    return table[index].name


def mpcat40_color(index: int) -> tuple[int, int, int]:
    """Display colour of mpcat40 class ``index`` as an (r, g, b) tuple of 0..255; black for -1 or out of range."""
    table = mpcat40_table()
    if not 0 <= index < len(table):
        return (0, 0, 0)
    h = table[index].color.lstrip("#")
    return (int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16))


def resolve_category(name_or_index: str | int) -> int:
    """mpcat40 index of a class given by name (``"chair"``; case-insensitive, spaces as ``_``) or index (3, ``"3"``)."""
    table = mpcat40_table()
    if isinstance(name_or_index, int) or (isinstance(name_or_index, str) and name_or_index.strip().isdigit()):
        idx = int(name_or_index)
        if not 0 <= idx < len(table):
            raise InputError(f"mpcat40 index {idx} is outside 0..{len(table) - 1}")
        return idx
    key = str(name_or_index).strip().lower().replace(" ", "_")
    for row in table:
        if row.name == key:
            return row.index
    raise InputError(f"unknown mpcat40 class {name_or_index!r} (known: {', '.join(r.name for r in table)})")


def resolve_categories(names: Iterable[str | int] | str | int) -> frozenset[int]:
    """The set of mpcat40 indices for one class or several (each by name or index)."""
    if isinstance(names, (str, int)):
        names = [names]
    return frozenset(resolve_category(n) for n in names)
