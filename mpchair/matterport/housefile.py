"""Read and write the Matterport3D ``.house`` annotation file (``ASCII 1.1`` and ``ASCII 1.0``).

Every record kind is parsed by token index (never by counting zeros): ``H L R P S V P I C O E``. Portals and
panoramas share the letter ``P`` and are told apart by the ``H`` counts (the first ``#portals`` ``P`` lines are
portals); files re-saved by GAPS write portals with the letter ``R``, which the ``H`` counts also resolve (the first
``#regions`` ``R`` lines are regions). ``#`` in category names stands for a space. A line may be short only in its
trailing zero fields. All positions are in the raw Matterport world frame (metres, z up).

Any malformed line raises :class:`mpchair.core.errors.InputError` naming the file and line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mpchair.core.errors import InputError

# Record layouts: letter → (meaningful tokens, full tokens). A line may omit trailing zero fields down to the
# meaningful count (hand-made fixtures do), but never a meaningful field.
_LAYOUT_11 = {
    "H": (24, 29),
    "L": (13, 18),
    "R": (16, 20),
    "Pp": (11, 15),  # portal
    "S": (17, 22),
    "V": (10, 13),
    "Pn": (8, 13),  # panorama
    "I": (36, 41),
    "C": (6, 11),
    "O": (16, 24),
    "E": (14, 19),
}
_LAYOUT_10 = dict(_LAYOUT_11, H=(15, 23))
_KIND_NAMES = {"Pp": "portal P", "Pn": "panorama P"}


@dataclass(frozen=True)
class HouseHeader:
    """The ``H`` record: name, label, record counts and the house AABB ``(6,)`` [xlo ylo zlo xhi yhi zhi] (world)."""

    name: str
    label: str
    n_images: int
    n_panoramas: int
    n_vertices: int
    n_surfaces: int
    n_segments: int
    n_objects: int
    n_categories: int
    n_regions: int
    n_portals: int
    n_levels: int
    bbox: np.ndarray


@dataclass(frozen=True)
class LevelRecord:
    """``L``: level ``index``, its region count, label, position (3,) and AABB (6,) (world, metres)."""

    index: int
    n_regions: int
    label: str
    position: np.ndarray
    bbox: np.ndarray


@dataclass(frozen=True)
class RegionRecord:
    """``R``: region ``index``, ``level`` (-1 = none), one-character ``label``, position (3,), AABB (6,), ``height``.

    ``height`` is the file value (token 15); 0 or less means "not given" (ASCII 1.0), see :func:`region_height`.
    """

    index: int
    level: int
    label: str
    position: np.ndarray
    bbox: np.ndarray
    height: float


@dataclass(frozen=True)
class PortalRecord:
    """Portal (``P`` among the first ``#portals``, or ``R`` past ``#regions``): the opening between two regions.

    ``bbox`` (6,) is the documented span xlo ylo zlo xhi yhi zhi (world, metres).
    """

    index: int
    region0: int
    region1: int
    label: str
    bbox: np.ndarray


@dataclass(frozen=True)
class SurfaceRecord:
    """``S``: surface ``index`` of ``region``; ``label`` ``F`` = floor; position, normal (3,), AABB (6,).

    ``n_vertices`` is token 3 (documented as 0; real files hold the vertex count there).
    """

    index: int
    region: int
    n_vertices: int
    label: str
    position: np.ndarray
    normal: np.ndarray
    bbox: np.ndarray


@dataclass(frozen=True)
class VertexRecord:
    """``V``: polygon vertex ``index`` of ``surface``; label, position (3,), normal (3,) (world, metres)."""

    index: int
    surface: int
    label: str
    position: np.ndarray
    normal: np.ndarray


@dataclass(frozen=True)
class PanoramaRecord:
    """Panorama ``P``: ``name`` (uuid), ``index``, ``region``, camera centre ``position`` (3,) (world, metres)."""

    name: str
    index: int
    region: int
    position: np.ndarray


@dataclass(frozen=True)
class ImageRecord:
    """``I``: image of a panorama; extrinsics (4,4) and intrinsics (3,3) as stored (row-major), size, position."""

    index: int
    panorama: int
    name: str
    camera_index: int
    yaw_index: int
    extrinsics: np.ndarray
    intrinsics: np.ndarray
    width: int
    height: int
    position: np.ndarray


@dataclass(frozen=True)
class CategoryRecord:
    """``C``: house-local ``index``; ``mapping_index``/``mapping_name`` (``category_mapping.tsv`` index and raw name,
    ``#`` already replaced by spaces); ``mpcat40_index``/``mpcat40_name``."""

    index: int
    mapping_index: int
    mapping_name: str
    mpcat40_index: int
    mpcat40_name: str


@dataclass(frozen=True)
class ObjectRecord:
    """``O``: object ``index``, ``region`` and ``category`` (index into the ``C`` records; -1 = none) and its oriented
    box as stored: ``center`` (3,), ``axis0``/``axis1`` (3,) (not re-orthonormalised), ``radii`` (3,) half-lengths."""

    index: int
    region: int
    category: int
    center: np.ndarray
    axis0: np.ndarray
    axis1: np.ndarray
    radii: np.ndarray


@dataclass(frozen=True)
class SegmentRecord:
    """``E``: segment ``index``, ``object`` (O index, -1 = none), ``id`` (the value faces carry as ``material_id``),
    ``area`` (m²), position (3,), AABB (6,)."""

    index: int
    object: int
    id: int
    area: float
    position: np.ndarray
    bbox: np.ndarray


@dataclass(frozen=True)
class HouseFile:
    """A parsed ``.house`` file. ``version`` is ``"1.1"`` or ``"1.0"``; record tuples keep file order."""

    version: str
    header: HouseHeader
    levels: tuple[LevelRecord, ...] = ()
    regions: tuple[RegionRecord, ...] = ()
    portals: tuple[PortalRecord, ...] = ()
    surfaces: tuple[SurfaceRecord, ...] = ()
    vertices: tuple[VertexRecord, ...] = ()
    panoramas: tuple[PanoramaRecord, ...] = ()
    images: tuple[ImageRecord, ...] = ()
    categories: tuple[CategoryRecord, ...] = ()
    objects: tuple[ObjectRecord, ...] = ()
    segments: tuple[SegmentRecord, ...] = ()
    warnings: tuple[str, ...] = field(default=())


def region_height(region: RegionRecord) -> float:
    """Region height (metres): the file value when positive, else the GAPS fallback AABB zmax - position z."""
    if region.height > 0:
        return float(region.height)
    return float(region.bbox[5] - region.position[2])


# ----------------------------------------------------------------------------------------------------- parsing


class _Line:
    """Token access for one record line with one-line errors naming the file, line number and field."""

    __slots__ = ("tokens", "path", "lineno", "kind")

    def __init__(self, tokens: list[str], path: str, lineno: int, kind: str):
        self.tokens, self.path, self.lineno, self.kind = tokens, path, lineno, kind

    def fail(self, msg: str) -> InputError:
        return InputError(f"{_KIND_NAMES.get(self.kind, self.kind)} record: {msg}", self.path, self.lineno)

    def tok(self, i: int) -> str:
        # Trailing zero fields may be missing; everything before the meaningful count was checked already.
        return self.tokens[i] if i < len(self.tokens) else "0"

    def int(self, i: int) -> int:
        t = self.tok(i)
        try:
            return int(t)
        except ValueError:
            try:
                v = float(t)
            except ValueError:
                raise self.fail(f"token {i} is {t!r}, expected an integer") from None
            if not math.isfinite(v) or not v.is_integer():
                raise self.fail(f"token {i} is {t!r}, expected an integer") from None
            return int(v)

    def float(self, i: int) -> float:
        t = self.tok(i)
        try:
            v = float(t)
        except ValueError:
            raise self.fail(f"token {i} is {t!r}, expected a number") from None
        if not math.isfinite(v):
            raise self.fail(f"token {i} is {t!r}, expected a finite number")
        return v

    def vec(self, i: int, n: int) -> np.ndarray:
        return np.array([self.float(i + k) for k in range(n)], dtype=np.float64)

    def name(self, i: int) -> str:
        # "-" is an empty name; "#" stands for a space (in every occurrence, not only the first).
        t = self.tok(i)
        return "" if t == "-" else t.replace("#", " ")

    def zeros(self, start: int) -> None:
        # Trailing fields are documented as zeros; real data holds only zeros there, so anything else is a sign of a
        # misaligned record (wrong version or wrong layout) and is reported rather than silently ignored.
        for i in range(start, len(self.tokens)):
            self.float(i)


def _is_int(t: str) -> bool:
    try:
        int(t)
    except ValueError:
        return False
    return True


def _check_len(ln: _Line, layout: dict[str, tuple[int, int]]) -> None:
    lo, hi = layout[ln.kind]
    n = len(ln.tokens)
    if n < lo:
        raise ln.fail(f"has {n} tokens, expected {hi} (at least {lo} before the trailing zeros)")
    if n > hi:
        raise ln.fail(f"has {n} tokens, expected {hi}")


def parse_house_text(text: str, path: str = "<house>") -> HouseFile:
    """Parse the text of a ``.house`` file (see module docstring); ``path`` is used in error messages only."""
    lines = text.splitlines()
    content = [(i + 1, ln.split()) for i, ln in enumerate(lines) if ln.strip()]
    if not content:
        raise InputError("empty .house file", path, 1)
    first_no, first = content[0]
    if len(first) != 2 or first[0] != "ASCII" or first[1] not in ("1.0", "1.1"):
        raise InputError(f"first line must be 'ASCII 1.1' or 'ASCII 1.0', got {' '.join(first)!r}", path, first_no)
    version = first[1]
    layout = _LAYOUT_11 if version == "1.1" else _LAYOUT_10
    if len(content) < 2 or content[1][1][0] != "H":
        raise InputError("second line must be the H record", path, content[1][0] if len(content) > 1 else first_no)

    hno, htoks = content[1]
    h = _Line(htoks, path, hno, "H")
    _check_len(h, layout)
    if version == "1.1":
        header = HouseHeader(
            name=h.name(1), label=h.name(2), n_images=h.int(3), n_panoramas=h.int(4), n_vertices=h.int(5),
            n_surfaces=h.int(6), n_segments=h.int(7), n_objects=h.int(8), n_categories=h.int(9),
            n_regions=h.int(10), n_portals=h.int(11), n_levels=h.int(12), bbox=h.vec(18, 6),
        )  # fmt: skip
        for i in (*range(13, 18), *range(24, len(htoks))):
            h.float(i)
    else:
        header = HouseHeader(
            name=h.name(1), label=h.name(2), n_images=h.int(3), n_panoramas=h.int(4), n_vertices=h.int(5),
            n_surfaces=h.int(6), n_segments=0, n_objects=0, n_categories=0, n_regions=h.int(7), n_portals=0,
            n_levels=h.int(8), bbox=h.vec(9, 6),
        )  # fmt: skip
        h.zeros(15)
    counts = [header.n_images, header.n_panoramas, header.n_vertices, header.n_surfaces, header.n_segments,
              header.n_objects, header.n_categories, header.n_regions, header.n_portals, header.n_levels]  # fmt: skip
    if min(counts) < 0:
        raise h.fail("negative record count")

    out: dict[str, list] = {k: [] for k in ("L", "R", "Pp", "S", "V", "Pn", "I", "C", "O", "E")}
    n_r = 0
    for lineno, toks in content[2:]:
        letter = toks[0]
        kind = letter
        if letter == "P":
            # Count-based dispatch: the first #portals P lines are portals, the rest panoramas (the token count,
            # 15 against 13, and the uuid in token 1 are only used to word the error).
            kind = "Pp" if len(out["Pp"]) < header.n_portals and not out["Pn"] else "Pn"
            if kind == "Pp" and len(toks) > 1 and not _is_int(toks[1]):
                raise InputError(
                    f"H record says {header.n_portals} portals but only {len(out['Pp'])} precede this panorama line",
                    path, lineno,
                )  # fmt: skip
        elif letter == "R":
            # GAPS re-saves portals as R lines after the #regions region lines.
            kind = "R" if n_r < header.n_regions else "Pp"
            n_r += 1
        elif letter not in ("L", "S", "V", "I", "C", "O", "E"):
            raise InputError(f"unknown record letter {letter!r}", path, lineno)
        ln = _Line(toks, path, lineno, kind)
        _check_len(ln, layout)
        out[kind].append(_PARSERS[kind](ln))

    expected = {
        "L": ("levels", header.n_levels), "R": ("regions", header.n_regions), "Pp": ("portals", header.n_portals),
        "S": ("surfaces", header.n_surfaces), "V": ("vertices", header.n_vertices),
        "Pn": ("panoramas", header.n_panoramas), "I": ("images", header.n_images),
        "C": ("categories", header.n_categories), "O": ("objects", header.n_objects),
        "E": ("segments", header.n_segments),
    }  # fmt: skip
    last = content[-1][0]
    for kind, (what, n) in expected.items():
        if len(out[kind]) != n:
            problem = "truncated file? " if len(out[kind]) < n else ""
            raise InputError(f"{problem}H record says {n} {what}, found {len(out[kind])}", path, last)
    if not text.endswith("\n"):
        # Matterport's writer ends every record with a newline, and a record may legally omit its trailing zeros,
        # so a missing final newline is the one sign left that the file was cut inside its last record.
        raise InputError("the file ends inside its last line (truncated?): a .house file ends with a newline", path,
                         len(lines))

    hf = HouseFile(
        version=version, header=header, levels=tuple(out["L"]), regions=tuple(out["R"]), portals=tuple(out["Pp"]),
        surfaces=tuple(out["S"]), vertices=tuple(out["V"]), panoramas=tuple(out["Pn"]), images=tuple(out["I"]),
        categories=tuple(out["C"]), objects=tuple(out["O"]), segments=tuple(out["E"]),
    )  # fmt: skip
    _check_references(hf, path, content)
    return hf


def _check_references(hf: HouseFile, path: str, content: list[tuple[int, list[str]]]) -> None:
    """Cross-record references must point at existing records (O → C, E → O); errors name the offending line."""
    linenos: dict[str, list[int]] = {}
    for lineno, toks in content[2:]:
        linenos.setdefault(toks[0], []).append(lineno)
    ncat = len(hf.categories)
    obj_ids = {o.index for o in hf.objects}
    if len(obj_ids) != len(hf.objects):
        raise InputError("duplicate O object index", path, linenos["O"][0])
    for k, o in enumerate(hf.objects):
        if not -1 <= o.category < ncat:
            raise InputError(f"O record: category index {o.category} is outside -1..{ncat - 1}", path,
                             linenos["O"][k])  # fmt: skip
        if np.any(o.radii < 0):
            raise InputError("O record: negative radius", path, linenos["O"][k])
    for k, e in enumerate(hf.segments):
        if e.object != -1 and e.object not in obj_ids:
            raise InputError(f"E record: object index {e.object} has no O record", path, linenos["E"][k])


def _p_level(ln: _Line) -> LevelRecord:
    ln.zeros(13)
    return LevelRecord(ln.int(1), ln.int(2), ln.name(3), ln.vec(4, 3), ln.vec(7, 6))


def _p_region(ln: _Line) -> RegionRecord:
    ln.float(3)
    ln.float(4)
    ln.zeros(16)
    return RegionRecord(ln.int(1), ln.int(2), ln.name(5) or "-", ln.vec(6, 3), ln.vec(9, 6), ln.float(15))


def _p_portal(ln: _Line) -> PortalRecord:
    # GAPS writes a portal as "R index region0 region1 label span..." with the same field positions as P.
    ln.zeros(11)
    return PortalRecord(ln.int(1), ln.int(2), ln.int(3), ln.name(4), ln.vec(5, 6))


def _p_surface(ln: _Line) -> SurfaceRecord:
    ln.zeros(17)
    return SurfaceRecord(ln.int(1), ln.int(2), ln.int(3), ln.name(4), ln.vec(5, 3), ln.vec(8, 3), ln.vec(11, 6))


def _p_vertex(ln: _Line) -> VertexRecord:
    ln.zeros(10)
    return VertexRecord(ln.int(1), ln.int(2), ln.name(3), ln.vec(4, 3), ln.vec(7, 3))


def _p_panorama(ln: _Line) -> PanoramaRecord:
    ln.float(4)
    ln.zeros(8)
    return PanoramaRecord(ln.name(1), ln.int(2), ln.int(3), ln.vec(5, 3))


def _p_image(ln: _Line) -> ImageRecord:
    ln.zeros(36)
    return ImageRecord(
        ln.int(1), ln.int(2), ln.name(3), ln.int(4), ln.int(5), ln.vec(6, 16).reshape(4, 4),
        ln.vec(22, 9).reshape(3, 3), ln.int(31), ln.int(32), ln.vec(33, 3),
    )  # fmt: skip


def _p_category(ln: _Line) -> CategoryRecord:
    ln.zeros(6)
    return CategoryRecord(ln.int(1), ln.int(2), ln.name(3), ln.int(4), ln.name(5))


def _p_object(ln: _Line) -> ObjectRecord:
    ln.zeros(16)
    return ObjectRecord(ln.int(1), ln.int(2), ln.int(3), ln.vec(4, 3), ln.vec(7, 3), ln.vec(10, 3), ln.vec(13, 3))


def _p_segment(ln: _Line) -> SegmentRecord:
    ln.zeros(14)
    return SegmentRecord(ln.int(1), ln.int(2), ln.int(3), ln.float(4), ln.vec(5, 3), ln.vec(8, 6))


_PARSERS = {
    "L": _p_level, "R": _p_region, "Pp": _p_portal, "S": _p_surface, "V": _p_vertex, "Pn": _p_panorama,
    "I": _p_image, "C": _p_category, "O": _p_object, "E": _p_segment,
}  # fmt: skip


# ----------------------------------------------------------------------------------------------------- writing


def _g(v: float) -> str:
    # Real files use %g (6 significant digits); 10 keeps synthetic round trips exact to ~1e-9 relative.
    s = f"{float(v):.10g}"
    return "0" if s == "-0" else s


def _gs(values) -> str:
    return " ".join(_g(v) for v in np.asarray(values, dtype=np.float64).ravel())


def _nm(s: str) -> str:
    return "-" if not s else s.replace(" ", "#")


def format_house(hf: HouseFile) -> str:
    """The ``ASCII 1.1`` text of ``hf`` in release record order and layout (double spaces between field groups)."""
    if hf.version != "1.1":
        raise ValueError("format_house writes ASCII 1.1 only")
    h = hf.header
    z5, z4, z8 = "0 0 0 0 0", "0 0 0 0", "0 0 0 0 0 0 0 0"
    out = ["ASCII 1.1"]
    out.append(
        f"H  {_nm(h.name)}  {_nm(h.label)}  {len(hf.images)} {len(hf.panoramas)} {len(hf.vertices)} "
        f"{len(hf.surfaces)} {len(hf.segments)} {len(hf.objects)} {len(hf.categories)} {len(hf.regions)} "
        f"{len(hf.portals)} {len(hf.levels)}  {z5}  {_gs(h.bbox)}  {z5}"
    )
    out += [f"L  {r.index}  {r.n_regions}  {_nm(r.label)}  {_gs(r.position)}  {_gs(r.bbox)}  {z5}" for r in hf.levels]
    out += [
        f"R  {r.index} {r.level}  0 0  {_nm(r.label)}  {_gs(r.position)}  {_gs(r.bbox)}  {_g(r.height)}  {z4}"
        for r in hf.regions
    ]
    out += [f"P  {p.index}  {p.region0} {p.region1}  {_nm(p.label)}  {_gs(p.bbox)}  {z4}" for p in hf.portals]
    out += [
        f"S  {s.index} {s.region}  {s.n_vertices}  {_nm(s.label)}  {_gs(s.position)}  {_gs(s.normal)}  "
        f"{_gs(s.bbox)}  {z5}"
        for s in hf.surfaces
    ]
    out += [
        f"V  {v.index} {v.surface}  {_nm(v.label)}  {_gs(v.position)}  {_gs(v.normal)}  0 0 0" for v in hf.vertices
    ]
    out += [f"P  {p.name}  {p.index} {p.region}  0  {_gs(p.position)}  {z5}" for p in hf.panoramas]
    out += [
        f"I  {i.index} {i.panorama}  {_nm(i.name)}  {i.camera_index} {i.yaw_index}  {_gs(i.extrinsics)}  "
        f"{_gs(i.intrinsics)}  {i.width} {i.height}  {_gs(i.position)}  {z5}"
        for i in hf.images
    ]
    out += [
        f"C  {c.index}  {c.mapping_index} {_nm(c.mapping_name)}  {c.mpcat40_index} {_nm(c.mpcat40_name)}  {z5}"
        for c in hf.categories
    ]
    out += [
        f"O  {o.index} {o.region} {o.category}  {_gs(o.center)}  {_gs(o.axis0)}  {_gs(o.axis1)}  {_gs(o.radii)}  {z8}"
        for o in hf.objects
    ]
    out += [
        f"E  {e.index} {e.object} {e.id}  {_g(e.area)}  {_gs(e.position)}  {_gs(e.bbox)}  {z5}" for e in hf.segments
    ]
    return "\n".join(out) + "\n"
