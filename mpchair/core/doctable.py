"""Generated blocks inside hand-written docs: the lines between a named pair of HTML-comment markers (invisible once
rendered) belong to the command that writes them, the rest of the doc to its authors."""

from __future__ import annotations

from pathlib import Path

from mpchair.core.atomic import write_text
from mpchair.core.errors import InputError


def markers(name: str) -> tuple[str, str]:
    """The begin and end markers (HTML comments) of the doc block called ``name``."""
    return f"<!-- {name}:begin -->", f"<!-- {name}:end -->"


def replace_block(text: str, begin: str, end: str, body: str, where: str | Path) -> str:
    """``text`` with the lines between its one ``begin`` line and its one ``end`` line replaced by ``body``; ``where``
    (the doc's path) names the doc in the error when the markers are missing, repeated or out of order."""
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise InputError(f"expected one '{begin}' line followed by one '{end}' line (the generated block's markers)",
                         where)
    return text[: text.index(begin) + len(begin)] + "\n" + body.rstrip("\n") + "\n" + text[text.index(end):]


def write_doc_table(doc: Path, table: str, marker: str) -> None:
    """Put ``table`` between the ``marker`` markers of ``doc`` (atomically); a doc without them is an error."""
    begin, end = markers(marker)
    write_text(doc, replace_block(doc.read_text(encoding="utf-8"), begin, end, table, doc))
