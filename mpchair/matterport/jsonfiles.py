"""The JSON side files of a house: ``<id>.fsegs.json`` (segment id per face) and ``<id>.semseg.json`` (segment groups).

Real ``semseg.json`` files contain invalid escapes such as ``\\o`` (raw labels like ``wall \\other room``); stray
backslashes are escaped before parsing, so such files load and the label keeps its backslash.
"""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass

import numpy as np

from mpchair.core.errors import InputError

# A valid JSON escape (kept as is) or a lone backslash (doubled, so "\o" reads as a literal backslash + "o").
_ESCAPE = re.compile(r'\\(?:["\\/bfnrt]|u[0-9a-fA-F]{4})|\\')
_SEG_INDICES = re.compile(rb'"segIndices"\s*:\s*\[')


def _fix_escapes(text: str) -> str:
    return _ESCAPE.sub(lambda m: m.group(0) if len(m.group(0)) > 1 else "\\\\", text)


def loads_lenient(data: bytes | str, path: str = "<json>"):
    """``json.loads`` that tolerates invalid backslash escapes; other syntax errors are an :class:`InputError`."""
    text = data.decode("utf-8", errors="replace") if isinstance(data, (bytes, bytearray, memoryview)) else data
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        pass
    try:
        return json.loads(_fix_escapes(text))
    except json.JSONDecodeError as e:
        raise InputError(f"invalid JSON: {e.msg} (column {e.colno})", path, e.lineno) from None


def read_fsegs(data: bytes, path: str = "<fsegs.json>") -> np.ndarray:
    """``segIndices`` of an ``.fsegs.json`` file as an (F,) int64 array (one segment id per face, mesh order).

    A fast path parses the integer list with numpy (house files hold millions of faces); anything unusual falls back
    to the lenient JSON parser.
    """
    m = _SEG_INDICES.search(data)
    if m is not None:
        end = data.find(b"]", m.end())
        body = data[m.end() : end].strip() if end >= 0 else b""
        if end >= 0 and not body:
            return np.zeros(0, dtype=np.int64)
        if end >= 0 and not body.translate(None, b"0123456789-, \t\r\n"):
            # np.fromstring's text mode parses in C (30x faster than json); it stops at a bad token (with a
            # DeprecationWarning), so the count is checked and anything odd goes to the JSON parser.
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    values = np.fromstring(body.decode("ascii", errors="replace"), dtype=np.int64, sep=",")
                except ValueError:
                    values = None
            if values is not None and len(values) == body.count(b",") + 1:
                return values
    obj = loads_lenient(data, path)
    if not isinstance(obj, dict) or not isinstance(obj.get("segIndices"), list):
        raise InputError("expected an object with a 'segIndices' list", path)
    seg = obj["segIndices"]
    if not all(type(v) is int for v in seg):
        raise InputError("'segIndices' must hold integers", path)
    return np.asarray(seg, dtype=np.int64).reshape(-1)


@dataclass(frozen=True)
class SegGroup:
    """One ``semseg.json`` segment group: ``id``, ``object_id`` (-1 when absent), raw ``label``, ``segments`` ids."""

    id: int
    object_id: int
    label: str
    segments: tuple[int, ...]


def read_semseg(data: bytes, path: str = "<semseg.json>") -> tuple[SegGroup, ...]:
    """The ``segGroups`` of a ``.semseg.json`` file (invalid ``\\o`` escapes tolerated)."""
    obj = loads_lenient(data, path)
    groups = obj.get("segGroups") if isinstance(obj, dict) else None
    if not isinstance(groups, list):
        raise InputError("expected an object with a 'segGroups' list", path)
    out = []
    for k, g in enumerate(groups):
        if not isinstance(g, dict) or not isinstance(g.get("segments", []), list):
            raise InputError(f"segGroups[{k}] is not an object with a 'segments' list", path)
        try:
            out.append(
                SegGroup(
                    id=int(g.get("id", k)), object_id=int(g.get("objectId", -1)), label=str(g.get("label", "")),
                    segments=tuple(int(s) for s in g.get("segments", [])),
                )  # fmt: skip
            )
        except (TypeError, ValueError):
            raise InputError(f"segGroups[{k}] has a non-integer id, objectId or segment", path) from None
    return tuple(out)


def encode_fsegs(seg_indices: np.ndarray, scene_id: str) -> bytes:
    """Bytes of an ``.fsegs.json`` file: ``{"sceneId": ..., "segIndices": [...]}`` (one id per face)."""
    ids = ",".join(str(int(v)) for v in np.asarray(seg_indices).ravel())
    return f'{{"sceneId": "{scene_id}", "segIndices": [{ids}]}}'.encode()


def encode_semseg(scene_id: str, groups: list[dict], raw_labels: bool = True) -> bytes:
    """Bytes of a ``.semseg.json`` file with ``segGroups``.

    Each group dict has ``id``, ``objectId``, ``label``, ``segments`` and optionally ``obb``. With ``raw_labels``,
    backslashes in labels are written unescaped, as in the real release (which makes ``\\o`` an invalid escape).
    """
    parts = []
    for g in groups:
        label = g["label"]
        label_json = json.dumps(label)
        if raw_labels:
            label_json = label_json.replace("\\\\", "\\")
        items = [f'"id": {int(g["id"])}', f'"objectId": {int(g["objectId"])}', f'"label": {label_json}',
                 f'"segments": [{", ".join(str(int(s)) for s in g["segments"])}]']  # fmt: skip
        if "obb" in g:
            items.append(f'"obb": {json.dumps(g["obb"], sort_keys=True)}')
        parts.append("{" + ", ".join(items) + "}")
    return (f'{{"sceneId": "{scene_id}", "segGroups": [\n' + ",\n".join(parts) + "\n]}\n").encode()
