"""Generated blocks inside hand-written docs: the lines between a named pair of HTML-comment markers (invisible once
rendered) belong to the command that writes them, the rest of the doc to its authors."""

from __future__ import annotations

from pathlib import Path

from mpchair.core.atomic import write_text
from mpchair.core.errors import InputError


def markers(name: str) -> tuple[str, str]:
    """The begin and end markers (HTML comments) of the doc block called ``name``."""
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def write_doc_table(doc: Path, table: str, marker: str) -> None:
    """Put ``table`` between the ``marker`` markers of ``doc`` (atomically); a doc without them is an error."""
    begin, end = markers(marker)
    text = doc.read_text(encoding="utf-8")
    if begin not in text or end not in text:
        raise InputError(f"no {begin} ... {end} markers", doc)
    head, rest = text.split(begin, 1)
    write_text(doc, head + begin + "\n" + table + end + rest.split(end, 1)[1])
