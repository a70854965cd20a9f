"""Reading a user's text file: UTF-8 or a one-line :class:`InputError` naming the file and the line of the bad byte."""

from __future__ import annotations

from pathlib import Path

from mpchair.core.errors import InputError


def decode_utf8(raw: bytes, path: str | Path) -> str:
    """``raw`` as UTF-8 text; bytes that are not are an :class:`InputError` naming the line and byte offset."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise InputError(f"not UTF-8 text (byte {e.start} is 0x{raw[e.start]:02x})", path, line) from None


def read_text(path: str | Path, what: str) -> str:
    """The UTF-8 text of ``path``; a missing file is ``InputError("<what> not found")``, another OS error
    ``InputError("cannot read <what>: ...")`` and non-UTF-8 bytes an error naming their line."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{what} not found", path) from None
    except OSError as e:
        raise InputError(f"cannot read {what}: {e.strerror or e}", path) from None
    return decode_utf8(raw, path)
