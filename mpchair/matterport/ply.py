"""Read and write the labelled whole-house ``.ply`` mesh of a Matterport3D release (triangles with per-face fields).

The body is read with numpy structured dtypes built from the header, in file order: vertices and faces are never
merged or reordered, so the per-face ``material_id`` / ``segment_id`` / ``category_id`` stay attached to their faces.
Binary little- and big-endian and ASCII bodies are supported; faces must be triangles. Coordinates are the raw
Matterport world frame (metres, z up).

The release layout (``house_segmentations/<id>.ply``) is::

    vertex: float x y z nx ny nz tx ty; uchar red green blue                      (35 bytes packed)
    face:   list uchar int vertex_indices; int material_id segment_id category_id  (25 bytes packed)

habitat's ``<id>_semantic.ply`` (:func:`read_semantic_ply`, :func:`encode_semantic_ply`) is the same mesh with fewer
fields, one ``object_id`` (the ``.house`` O index) per face::

    vertex: float x y z; uchar red green blue                                      (15 bytes packed)
    face:   list uchar int vertex_indices; int object_id                           (17 bytes packed)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mpchair.core.errors import InputError

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip

#: The face fields of the release mesh, in header order after ``vertex_indices``.
FACE_FIELDS = ("material_id", "segment_id", "category_id")
#: numpy types a semantic mesh's ``object_id`` may have: MP3D writes int; Gibson/Replica-style files use ushort.
OBJECT_ID_TYPES = ("i4", "u4", "i2", "u2")
#: Bytes a zip member may hold beyond what its PLY header declares (trailing newline, padding) before it is refused.
BODY_SLACK = 1 << 16
#: Bytes one ASCII PLY value may take at most (``%.17g`` of a double plus a separator is 25): sizes ASCII members.
ASCII_VALUE_BYTES = 48


@dataclass(frozen=True)
class PlyMesh:
    """A triangle mesh as stored: ``vertices (V,3) float64``, ``faces (F,3) int64`` and, when present, the per-face
    fields ``material_id``, ``segment_id``, ``category_id`` ``(F,) int64`` (``None`` when the header lacks them).
    ``normals (V,3)``/``colors (V,3) uint8`` when present."""

    vertices: np.ndarray
    faces: np.ndarray
    material_id: np.ndarray | None
    segment_id: np.ndarray | None
    category_id: np.ndarray | None
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    object_id: np.ndarray | None = None


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    props: tuple[tuple[str, str, str | None], ...]  # (name, numpy type, list count type or None)
    lineno: int


def _parse_header(data: bytes | memoryview, path: str) -> tuple[str, list[_Element], int]:
    head = bytes(data[: min(len(data), 1 << 16)])
    if not head.startswith(b"ply"):
        raise InputError("not a PLY file (missing 'ply' magic)", path, 1)
    end = head.find(b"end_header")
    if end < 0:
        raise InputError("PLY header has no 'end_header' line (truncated?)", path)
    nl = head.find(b"\n", end)
    if nl < 0:
        raise InputError("PLY header has no newline after 'end_header'", path)
    body_start = nl + 1
    try:
        lines = head[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError("PLY header is not ASCII", path) from None
    fmt = None
    elements: list[_Element] = []
    cur: list | None = None
    for lineno, raw in enumerate(lines, start=1):
        t = raw.split()
        if not t or t[0] in ("ply", "comment", "obj_info"):
            continue
        if t[0] == "format":
            if len(t) != 3 or t[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise InputError(f"unsupported PLY format line {raw.strip()!r}", path, lineno)
            fmt = t[1]
        elif t[0] == "element":
            if len(t) != 3 or not t[2].isdigit():
                raise InputError(f"bad element line {raw.strip()!r}", path, lineno)
            cur = [t[1], int(t[2]), [], lineno]
            elements.append(cur)  # type: ignore[arg-type]
        elif t[0] == "property":
            if cur is None:
                raise InputError("property before any element", path, lineno)
            if len(t) in (3, 5) and any(prop[0] == t[-1] for prop in cur[2]):
                raise InputError(f"property {t[-1]!r} appears twice in element {cur[0]!r}", path, lineno)
            if len(t) == 5 and t[1] == "list" and t[2] in _TYPES and t[3] in _TYPES:
                cur[2].append((t[4], _TYPES[t[3]], _TYPES[t[2]]))
            elif len(t) == 3 and t[1] in _TYPES:
                cur[2].append((t[2], _TYPES[t[1]], None))
            else:
                raise InputError(f"bad property line {raw.strip()!r}", path, lineno)
        else:
            raise InputError(f"unknown PLY header line {raw.strip()!r}", path, lineno)
    if fmt is None:
        raise InputError("PLY header has no format line", path)
    els = [_Element(e[0], e[1], tuple(e[2]), e[3]) for e in elements]  # type: ignore[index]
    return fmt, els, body_start


def _values_per_record(el: _Element) -> int:
    """Numbers one record of ``el`` holds in an ASCII body (a list is its count plus 3 entries: triangles only)."""
    return sum(4 if c is not None else 1 for _, _, c in el.props)


def _dtype(el: _Element, endian: str) -> np.dtype:
    fields = []
    for name, typ, count_type in el.props:
        if count_type is None:
            fields.append((name, endian + typ))
        else:
            # Only fixed-length lists (triangles) can be read as one structured dtype; counts are checked after.
            fields.append(("__count_" + name, endian + count_type))
            fields.append((name, endian + typ, (3,)))
    return np.dtype(fields)


def read_ply(data: bytes | memoryview, path: str = "<ply>") -> PlyMesh:
    """Parse a PLY file's bytes into a :class:`PlyMesh` (file order kept). ``path`` names the file in errors.

    Raises :class:`InputError` for a body shorter than the header declares, non-triangle faces, out-of-range vertex
    indices or non-finite coordinates.
    """
    fmt, elements, arrays, _ = _read_body(data, path)
    return _to_mesh(arrays, elements, path)


def read_semantic_ply(data: bytes | memoryview, path: str = "<ply>") -> PlyMesh:
    """Parse habitat's ``<id>_semantic.ply`` (the house mesh with one ``object_id`` per face; Matterport world frame,
    z up, as stored). The header drives the numpy dtypes, so any property order is read; ``object_id`` must be a
    face property of type int, uint, short or ushort.

    Raises :class:`InputError` for everything :func:`read_ply` does, for a missing or non-integer ``object_id`` and for
    a binary body longer than its header declares (the file is not what the header says).
    """
    fmt, elements, arrays, end = _read_body(data, path)
    face = next((e for e in elements if e.name == "face"), None)
    if face is not None:
        prop = next((p for p in face.props if p[0] == "object_id"), None)
        if prop is None:
            raise InputError("semantic mesh lacks the per-face 'object_id' property", path, face.lineno)
        if prop[2] is not None or prop[1] not in OBJECT_ID_TYPES:
            raise InputError("face property 'object_id' must be int, uint, short or ushort", path, face.lineno)
    if fmt != "ascii" and end < len(data):
        raise InputError(f"PLY body is longer than its header says: {len(data) - end} bytes after the last element "
                         f"(at offset {end})", path)  # fmt: skip
    return _to_mesh(arrays, elements, path)


def ply_byte_limit(head: bytes, path: str = "<ply>") -> int:
    """The most bytes a PLY file whose first bytes are ``head`` (its header, at least) may sensibly hold: the header,
    plus each element's count × record size (binary; ASCII: × :data:`ASCII_VALUE_BYTES` per value), plus
    :data:`BODY_SLACK`. Used to refuse zip members (zip bombs) before decompressing them; a bad header raises the
    same :class:`InputError` as :func:`read_ply`."""
    fmt, elements, body_start = _parse_header(head, path)
    need = 0
    for el in elements:
        if fmt == "ascii":
            need += el.count * ASCII_VALUE_BYTES * _values_per_record(el)
        else:
            need += el.count * _dtype(el, "<").itemsize
    return body_start + need + BODY_SLACK


def _read_body(data: bytes | memoryview, path: str) -> tuple[str, list[_Element], dict[str, np.ndarray], int]:
    """Header and element arrays of a PLY file; also the byte offset where the declared body ends (binary)."""
    fmt, elements, pos = _parse_header(data, path)
    names = [e.name for e in elements]
    if "vertex" not in names or "face" not in names:
        raise InputError("PLY file needs 'vertex' and 'face' elements", path)
    arrays: dict[str, np.ndarray] = {}
    if fmt == "ascii":
        return fmt, elements, _read_ascii_body(data, pos, elements, path), len(data)
    endian = "<" if fmt == "binary_little_endian" else ">"
    for el in elements:
        dt = _dtype(el, endian)
        nbytes = dt.itemsize * el.count
        if pos + nbytes > len(data):
            raise InputError(
                f"PLY body is shorter than its header says: element '{el.name}' needs {nbytes} bytes at offset "
                f"{pos}, file has {len(data) - pos} left",
                path, el.lineno,
            )  # fmt: skip
        arrays[el.name] = np.frombuffer(data, dtype=dt, count=el.count, offset=pos)
        pos += nbytes
    return fmt, elements, arrays, pos


def _read_ascii_body(data: bytes | memoryview, pos: int, elements: list[_Element], path: str) -> dict:
    tokens = bytes(data[pos:]).split()
    arrays = {}
    at = 0
    for el in elements:
        dt = _dtype(el, "<")
        width = _values_per_record(el)
        need = width * el.count
        if at + need > len(tokens):
            raise InputError(
                f"PLY body is shorter than its header says: element '{el.name}' needs {need} values, "
                f"{len(tokens) - at} left",
                path, el.lineno,
            )  # fmt: skip
        try:
            block = np.array(tokens[at : at + need], dtype=np.float64).reshape(el.count, width)
        except ValueError:
            raise InputError(f"non-numeric value in element '{el.name}'", path, el.lineno) from None
        rec = np.zeros(el.count, dtype=dt)
        col = 0
        for name, _typ, count_type in el.props:
            if count_type is None:
                rec[name] = block[:, col]
                col += 1
            else:
                rec["__count_" + name] = block[:, col]
                rec[name] = block[:, col + 1 : col + 4]
                col += 4
        arrays[el.name] = rec
        at += need
    if at < len(tokens):
        raise InputError(f"PLY body is longer than its header says: {len(tokens) - at} values after the last element "
                         f"(first: {tokens[at][:20].decode('ascii', 'replace')!r})", path)
    return arrays


def _to_mesh(arrays: dict, elements: list[_Element], path: str) -> PlyMesh:
    by_name = {e.name: e for e in elements}
    v, f = arrays["vertex"], arrays["face"]
    vnames = v.dtype.names or ()
    if not {"x", "y", "z"} <= set(vnames):
        raise InputError("PLY vertex element lacks x, y, z", path, by_name["vertex"].lineno)
    vertices = np.empty((len(v), 3), dtype=np.float64)
    with np.errstate(invalid="ignore"):  # a NaN or out-of-range value is reported just below, in words
        vertices[:, 0], vertices[:, 1], vertices[:, 2] = v["x"], v["y"], v["z"]
    if not np.isfinite(vertices).all():
        bad = int(np.flatnonzero(~np.isfinite(vertices).all(axis=1))[0])
        raise InputError(f"vertex {bad} has a non-finite coordinate", path, by_name["vertex"].lineno)
    normals = colors = None
    if {"nx", "ny", "nz"} <= set(vnames):
        normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1).astype(np.float64)
    if {"red", "green", "blue"} <= set(vnames):
        colors = np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8)

    list_props = [name for name, _, c in by_name["face"].props if c is not None]
    idx_name = next((n for n in ("vertex_indices", "vertex_index") if n in list_props), None)
    if idx_name is None:
        raise InputError("PLY face element lacks a 'vertex_indices' list", path, by_name["face"].lineno)
    counts = f["__count_" + idx_name]
    if len(counts) and (counts != 3).any():
        bad = int(np.flatnonzero(counts != 3)[0])
        raise InputError(f"face {bad} has {int(counts[bad])} vertices; only triangles are supported", path,
                         by_name["face"].lineno)  # fmt: skip
    faces = f[idx_name].astype(np.int64)
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        bad = int(np.flatnonzero(((faces < 0) | (faces >= len(vertices))).any(axis=1))[0])
        raise InputError(f"face {bad} references a vertex outside 0..{len(vertices) - 1}", path,
                         by_name["face"].lineno)  # fmt: skip
    fnames = f.dtype.names or ()
    fields = {k: (f[k].astype(np.int64) if k in fnames else None) for k in (*FACE_FIELDS, "object_id")}
    return PlyMesh(vertices, faces, normals=normals, colors=colors, **fields)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V,3) of a triangle mesh (zero for vertices of no face)."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def encode_ply(
    vertices: np.ndarray,
    faces: np.ndarray,
    material_id: np.ndarray,
    segment_id: np.ndarray,
    category_id: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    ascii: bool = False,
) -> bytes:
    """Bytes of a house ``.ply`` in the release layout (binary little-endian by default, or ASCII).

    ``vertices`` (V,3) metres (stored as float32), ``faces`` (F,3) indices, per-face ``material_id`` (segment id),
    ``segment_id`` (object index) and ``category_id`` (category_mapping index, -1 = unlabelled). ``normals``
    default to area-weighted vertex normals, ``colors`` (V,3) uint8 to grey. Texture coordinates are zero.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    nv, nf = len(vertices), len(faces)
    if normals is None:
        normals = vertex_normals(vertices, faces)
    if colors is None:
        colors = np.full((nv, 3), 128, dtype=np.uint8)
    header = (
        "ply\n"
        f"format {'ascii' if ascii else 'binary_little_endian'} 1.0\n"
        f"element vertex {nv}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property float tx\nproperty float ty\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {nf}\n"
        "property list uchar int vertex_indices\n"
        "property int material_id\nproperty int segment_id\nproperty int category_id\n"
        "end_header\n"
    ).encode("ascii")
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                    ("tx", "<f4"), ("ty", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])  # fmt: skip
    fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("material_id", "<i4"), ("segment_id", "<i4"),
                    ("category_id", "<i4")])  # fmt: skip
    v = np.zeros(nv, dtype=vdt)
    v["x"], v["y"], v["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    v["nx"], v["ny"], v["nz"] = normals[:, 0], normals[:, 1], normals[:, 2]
    v["red"], v["green"], v["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    f = np.zeros(nf, dtype=fdt)
    f["n"] = 3
    f["v"] = faces
    f["material_id"], f["segment_id"], f["category_id"] = material_id, segment_id, category_id
    if not ascii:
        return header + v.tobytes() + f.tobytes()
    vx = v[["x", "y", "z", "nx", "ny", "nz", "tx", "ty"]]
    lines = [
        " ".join(f"{float(c):.9g}" for c in row) + f" {r} {g} {b}"
        for row, r, g, b in zip(vx.tolist(), v["red"], v["green"], v["blue"])
    ]
    lines += [
        f"3 {a} {b} {c} {m} {s} {k}"
        for (a, b, c), m, s, k in zip(faces.tolist(), f["material_id"].tolist(), f["segment_id"].tolist(),
                                      f["category_id"].tolist())  # fmt: skip
    ]
    return header + ("\n".join(lines) + "\n").encode("ascii")


def encode_semantic_ply(vertices: np.ndarray, faces: np.ndarray, object_id: np.ndarray,
                        colors: np.ndarray | None = None, *, id_type: str = "int") -> bytes:
    """Bytes of habitat's ``<id>_semantic.ply`` as its Datatool wrote them (binary little-endian; ``float x y z``,
    ``uchar red green blue``; ``list uchar int vertex_indices``, ``<id_type> object_id``).

    ``vertices`` (V,3) metres, Matterport world frame (stored as float32, as in the release ``.ply``), ``faces`` (F,3)
    indices, ``object_id`` (F,) the ``.house`` O index (-1 unlabelled), ``colors`` (V,3) uint8 (grey by default).
    ``id_type`` ``int`` (MP3D) or ``ushort`` (other habitat datasets).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    nv, nf = len(vertices), len(faces)
    if colors is None:
        colors = np.full((nv, 3), 128, dtype=np.uint8)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {nv}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {nf}\n"
        "property list uchar int vertex_indices\n"
        f"property {id_type} object_id\n"
        "end_header\n"
    ).encode("ascii")
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("object_id", "<" + _TYPES[id_type])])
    v = np.zeros(nv, dtype=vdt)
    v["x"], v["y"], v["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    v["red"], v["green"], v["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    f = np.zeros(nf, dtype=fdt)
    f["n"] = 3
    f["v"] = faces
    f["object_id"] = object_id
    return header + v.tobytes() + f.tobytes()
