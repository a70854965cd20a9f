"""The GPU check's result files: JSON, written atomically, read back leniently (a step that did not run left none)."""

from __future__ import annotations

import json
from pathlib import Path

from mpchair.core.atomic import write_text


def write_json(path: str | Path, obj: object) -> None:
    """``obj`` as indented JSON at ``path`` (temp + rename)."""
    write_text(path, json.dumps(obj, indent=2) + "\n")


def read_json(path: Path) -> dict | None:
    """A result file's JSON, or None when the step did not write it (or wrote something else)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None
