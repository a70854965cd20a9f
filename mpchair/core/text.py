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


#: The largest text file read whole by :func:`read_regular` unless told otherwise (a record's or a run's metadata).
MAX_TEXT_BYTES = 256 << 20
#: How deep JSON read by :func:`load_json` may nest (the project's own files nest a few levels).
MAX_JSON_DEPTH = 64


def _kind(mode: int) -> str:
    import stat

    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def read_regular(path: str | Path, what: str, *, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of the regular file ``path`` (a symlink to one included), at most ``max_bytes``: a FIFO, a
    device or a folder in its place is refused before it is opened (reading one would block or never end), as is a
    larger file; every refusal an :class:`InputError` naming ``path`` and ``what`` it should be."""
    import os
    import stat

    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise InputError(f"{what} not found", path) from None
    except OSError as e:
        raise InputError(f"cannot read {what}: {e.strerror or e}", path) from None
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{what} is {_kind(st.st_mode)}, not a regular file", path)
    if st.st_size > max_bytes:
        raise InputError(f"{what} is {st.st_size:,} bytes, more than the {max_bytes:,} it can be", path)
    try:
        with open(path, "rb") as f:
            raw = f.read(max_bytes + 1)
    except OSError as e:
        raise InputError(f"cannot read {what}: {e.strerror or e}", path) from None
    if len(raw) > max_bytes:
        raise InputError(f"{what} grew past the {max_bytes:,} bytes it can be while being read", path)
    return decode_utf8(raw, path)


def parse_json(text: str, path: str | Path, *, max_depth: int = MAX_JSON_DEPTH, line: int | None = None):
    """``text`` parsed as JSON; malformed text or nesting deeper than ``max_depth`` is an :class:`InputError` naming
    ``path`` (and ``line``, or the line of the syntax error)."""
    import json

    try:
        value = json.loads(text)
    except RecursionError:
        raise InputError(f"nested deeper than {max_depth} levels", path, line) from None
    except ValueError as e:
        at = line if line is not None else getattr(e, "lineno", None)
        raise InputError(f"not valid JSON ({getattr(e, 'msg', e)})", path, at) from None
    stack = [(value, 1)]
    while stack:  # the depth of what parsed (below Python's recursion limit, a file can still nest thousands deep)
        node, depth = stack.pop()
        if depth > max_depth:
            raise InputError(f"nested deeper than {max_depth} levels", path, line)
        if isinstance(node, dict):
            stack.extend((v, depth + 1) for v in node.values())
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node)
    return value


def load_json(path: str | Path, what: str, *, max_bytes: int = MAX_TEXT_BYTES, max_depth: int = MAX_JSON_DEPTH):
    """The JSON value of the regular file ``path`` (:func:`read_regular`, :func:`parse_json`)."""
    return parse_json(read_regular(path, what, max_bytes=max_bytes), path, max_depth=max_depth)
