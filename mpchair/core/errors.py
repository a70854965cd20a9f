"""Errors a user can act on. Both CLIs print them as one line and exit with status 2 (no traceback)."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad or missing input, named by file and (when known) line or record.

    ``str(err)`` is the whole one-line message, e.g. ``house.house:12: O record has 22 tokens, expected 23``.
    """

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.path = None if path is None else str(path)
        self.line = line
        self.message = message
        where = ""
        if self.path is not None:
            where = self.path + (f":{line}" if line is not None else "") + ": "
        super().__init__(where + message)



class RunError(Exception):
    """A run stopped for a reason outside its input (e.g. a worker process died); what it wrote is intact and the same
    command resumes. Both CLIs print it as one ``error: ...`` line and exit with status 1."""
