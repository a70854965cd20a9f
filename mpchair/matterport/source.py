"""Find houses on disk, in either Matterport3D layout, and read their files, extracted or straight from a zip.

Two layouts hold the same houses (``docs/matterport.md``):

- **release** (``download_mp.py``): ``v1/scans/<id>/house_segmentations.zip`` → ``<id>/house_segmentations/`` with
  ``<id>.house``, ``<id>.ply`` (labelled by ``material_id``), ``<id>.fsegs.json``, ``<id>.semseg.json``;
- **habitat** (``download_mp.py --task habitat``): ``mp3d_habitat.zip`` → ``mp3d/<id>/`` with ``<id>.house``,
  ``<id>_semantic.ply`` (labelled by ``object_id``), ``<id>.navmesh`` and ``<id>.glb`` (not read).

:func:`find_houses` walks the root at any depth, so any of these work as a root: the folder holding ``v1``, ``v1``,
``v1/scans``, one scan folder, a ``house_segmentations/`` or ``mp3d/<id>/`` folder, ``mp3d/``, a zip, a ``.house``
file. A folder holding ``<id>.house`` is a house (habitat layout when ``<id>_semantic.ply`` sits beside it and
``<id>.ply`` does not); zips named ``house_segmentations.zip`` or ``*habitat*.zip`` met on the walk (any zip given as
the root) are searched the same way, member by member, without extracting anything. Zip members are read with a
size cap (:meth:`HouseSource.read_bytes`): a member larger than its header can need is refused before it is
decompressed.
"""

from __future__ import annotations

import lzma
import os
import re
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from mpchair.core.errors import InputError
from mpchair.matterport.ply import ply_byte_limit

#: The files of one house by layout, by suffix; the first two are required.
SUFFIXES = {
    "release": (".house", ".ply", ".fsegs.json", ".semseg.json"),
    "habitat": (".house", "_semantic.ply", ".navmesh"),
}
#: Largest zip member read for the files without a size-declaring header (bytes). Real ``.house`` files are a few MB,
#: ``.semseg.json`` and ``.navmesh`` files under 20 MB, ``.fsegs.json`` about 10 bytes per face (30 MB for 3 M
#: faces): anything far larger is a zip bomb or not Matterport3D.
MEMBER_CAPS = {".house": 64 << 20, ".semseg.json": 64 << 20, ".navmesh": 64 << 20, ".fsegs.json": 512 << 20}
#: Largest mesh member whatever its header says: 10x the largest Matterport3D house mesh (~200 MB).
MAX_MESH_BYTES = 4 << 30
#: Folders of a Matterport3D download that hold only images, cameras or other meshes: the walk skips them (a full
#: extracted download has about two million image files).
SKIP_FOLDERS = frozenset({
    "undistorted_color_images", "undistorted_depth_images", "undistorted_normal_images", "matterport_color_images",
    "matterport_depth_images", "matterport_skybox_images", "matterport_hdr_images", "region_segmentations",
    "image_overlap_data", "poisson_meshes", "matterport_mesh", "cameras", "undistorted_camera_parameters",
    "matterport_camera_intrinsics", "matterport_camera_poses", ".git", "__pycache__",
})  # fmt: skip
_CHUNK = 16 << 20

Layout = Literal["release", "habitat"]


@dataclass(frozen=True)
class HouseSource:
    """Where one house's files live: a folder holding ``<id>.house`` etc. (``zip_path`` None), or a zip file whose
    members are ``<prefix><id>.house`` etc.; ``layout`` says which files the house has (module docstring)."""

    id: str
    folder: Path | None = None
    zip_path: Path | None = None
    prefix: str = ""
    layout: Layout = "release"

    @property
    def mesh_suffix(self) -> str:
        """The labelled mesh: ``.ply`` (release) or ``_semantic.ply`` (habitat)."""
        return SUFFIXES[self.layout][1]

    def describe(self, suffix: str) -> str:
        """Display path of one file, used in error messages (``archive.zip:member`` inside zips)."""
        if self.zip_path is not None:
            return f"{self.zip_path}:{self.prefix}{self.id}{suffix}"
        return str(Path(self.folder or ".") / f"{self.id}{suffix}")

    def exists(self, suffix: str) -> bool:
        """Whether the house has the file ``<id><suffix>``."""
        if self.zip_path is not None:
            with zipfile.ZipFile(self.zip_path) as zf:
                return f"{self.prefix}{self.id}{suffix}" in zf.NameToInfo
        return (Path(self.folder or ".") / f"{self.id}{suffix}").is_file()

    def read_bytes(self, suffix: str) -> bytes | bytearray:
        """Contents of ``<id><suffix>``; a missing or unreadable file is an :class:`InputError`.

        A zip member is refused (before it is decompressed) when its declared size exceeds what it can need: for a
        ``.ply``, what its header's element counts × record sizes take plus slack (:func:`ply_byte_limit`), for the
        other files :data:`MEMBER_CAPS`. Reading also stops at that cap if the member turns out longer than declared.
        """
        where = self.describe(suffix)
        if self.zip_path is None:
            p = Path(self.folder or ".") / f"{self.id}{suffix}"
            try:
                return p.read_bytes()
            except FileNotFoundError:
                raise InputError("file not found", where) from None
            except OSError as e:
                raise InputError(f"cannot read file: {e.strerror}", where) from None
        try:
            with zipfile.ZipFile(self.zip_path) as zf:
                try:
                    info = zf.getinfo(f"{self.prefix}{self.id}{suffix}")
                except KeyError:
                    raise InputError("file not found in the zip archive", where) from None
                _check_member(info, where)
                with zf.open(info) as f:
                    return _read_capped(f, info.file_size, suffix, where)
        except (zipfile.BadZipFile, OSError, EOFError, ValueError, RuntimeError, NotImplementedError, zlib.error,
                lzma.LZMAError) as e:  # a corrupt member's deflate / lzma stream raises its codec's own error
            raise InputError(f"cannot read zip archive: {' '.join(str(e).split())[:200]}", self.describe(suffix)) \
                from None


#: Compression methods Python's zipfile decompresses (stored, deflate, bzip2, lzma).
ZIP_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate", zipfile.ZIP_BZIP2: "bzip2",
               zipfile.ZIP_LZMA: "lzma"}
#: A house id as Matterport3D (11 letters and digits) and our synthetic houses write them: a safe file-name stem.
HOUSE_ID = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")


def _check_member(info: zipfile.ZipInfo, where: str) -> None:
    """Refuse, before reading, a zip member that is encrypted or compressed with a method zipfile cannot undo."""
    if info.flag_bits & 0x1:
        raise InputError("zip member is encrypted; refused (Matterport3D zips are not)", where)
    if info.compress_type not in ZIP_METHODS:
        raise InputError(f"zip member uses compression method {info.compress_type}, not one of "
                         f"{', '.join(ZIP_METHODS.values())}; refused", where)


def check_house_id(hid: str, where: str | Path) -> str:
    """``hid`` when it is a valid house id (:data:`HOUSE_ID`), else an :class:`InputError` that shows it escaped."""
    if not HOUSE_ID.fullmatch(hid) or hid in (".", ".."):
        raise InputError(f"{hid!r} is not a house id (letters, digits, '_', '-', '.'; not starting with '-' or '.')",
                         where)
    return hid


def _read_capped(f, declared: int, suffix: str, where: str) -> bytearray:
    """Read one zip member of ``declared`` bytes, refusing it when that exceeds the cap for ``suffix``."""
    if suffix.endswith(".ply"):
        head = f.read(min(declared, 1 << 16))
        cap = min(ply_byte_limit(head, where), MAX_MESH_BYTES)
    else:
        head = b""
        cap = MEMBER_CAPS.get(suffix, 64 << 20)
    if declared > cap:
        raise InputError(f"zip member is {declared} bytes uncompressed but can need at most {cap} (zip bomb?); "
                         "refused", where)  # fmt: skip
    buf = bytearray(declared)
    buf[: len(head)] = head
    view = memoryview(buf)
    at = len(head)
    while at < declared:
        n = f.readinto(view[at : min(declared, at + _CHUNK)])
        if not n:
            raise InputError(f"zip member ends after {at} of its {declared} declared bytes", where)
        at += n
    if f.read(1):
        raise InputError(f"zip member is longer than its declared {declared} bytes; refused", where)
    return buf


def _layout_of(names: set[str], prefix: str, hid: str) -> Layout:
    """habitat when ``<id>_semantic.ply`` is there and the release ``<id>.ply`` is not."""
    if f"{prefix}{hid}_semantic.ply" in names and f"{prefix}{hid}.ply" not in names:
        return "habitat"
    return "release"


def _houses_in_zip(zip_path: Path) -> list[HouseSource]:
    """Houses inside a zip (members ``.../<id>.house`` at any depth)."""
    try:
        with zipfile.ZipFile(zip_path) as zf:
            listed = zf.namelist()
    except (zipfile.BadZipFile, OSError, RuntimeError, NotImplementedError, ValueError) as e:
        raise InputError(f"cannot read zip archive: {e}", zip_path) from None
    names = set(listed)
    if len(names) != len(listed):
        twice = sorted(n for n in names if listed.count(n) > 1)[0]
        raise InputError(f"the archive holds member {twice!r} more than once (which one is meant?); refused", zip_path)
    out = []
    for name in sorted(names):
        if name.endswith(".house") and not name.endswith("/"):
            prefix, _, base = name.rpartition("/")
            prefix = prefix + "/" if prefix else ""
            hid = check_house_id(base[: -len(".house")], f"{zip_path}:{name!r}")
            out.append(HouseSource(hid, zip_path=zip_path, prefix=prefix, layout=_layout_of(names, prefix, hid)))
    return out


def _wanted_zip(name: str) -> bool:
    return name == "house_segmentations.zip" or (name.endswith(".zip") and "habitat" in name)


def _walk(root: Path) -> list[tuple[tuple, HouseSource]]:
    """Every house below folder ``root`` with its precedence key (see :func:`find_houses`)."""
    found: list[tuple[tuple, HouseSource]] = []
    seen: set[tuple[int, int]] = set()
    stack = [(root, 0)]
    while stack:
        folder, depth = stack.pop()
        try:
            st = folder.stat()
            entries = sorted(os.scandir(folder), key=lambda e: e.name)
        except OSError:
            continue  # unreadable folders below the root are skipped, as `find` would
        if (st.st_dev, st.st_ino) in seen:  # symlink loops
            continue
        seen.add((st.st_dev, st.st_ino))
        files = {e.name for e in entries if e.is_file()}
        for e in entries:
            if e.is_file() and e.name.endswith(".house"):
                hid = check_house_id(e.name[: -len(".house")], folder / repr(e.name))
                src = HouseSource(hid, folder=folder, layout=_layout_of(files, "", hid))
                found.append(((src.layout != "release", 0, depth, str(folder)), src))
            elif e.is_file() and _wanted_zip(e.name):
                for src in _houses_in_zip(Path(e.path)):
                    found.append(((src.layout != "release", 1, depth, e.path), src))
            elif e.is_dir() and e.name not in SKIP_FOLDERS:
                stack.append((Path(e.path), depth + 1))
    return found


def find_houses(root: str | Path) -> dict[str, HouseSource]:
    """All houses under ``root`` as ``{id: HouseSource}``, sorted by id (layouts and roots in the module docstring).

    When one id is found more than once, the release layout wins over habitat, an extracted folder over a zip, a
    shallower place over a deeper one, then the path that sorts first. A root that does not exist, or holds no house,
    is an :class:`InputError`.
    """
    root = Path(root)
    if not root.exists():
        raise InputError("house root not found", root)
    if root.is_file():
        if zipfile.is_zipfile(root):
            found = [((src.layout != "release",), src) for src in _houses_in_zip(root)]
        elif root.name.endswith(".house"):
            hid = check_house_id(root.name[: -len(".house")], root)
            files = {p.name for p in root.parent.iterdir()}
            found = [((), HouseSource(hid, folder=root.parent, layout=_layout_of(files, "", hid)))]
        else:
            raise InputError("expected a folder, a .house file or a zip (house_segmentations.zip, mp3d_habitat.zip)",
                             root)  # fmt: skip
    else:
        found = _walk(root)
    if not found:
        raise InputError(
            "no house found (expected <id>.house with <id>.ply or <id>_semantic.ply at any depth, extracted or in "
            "house_segmentations.zip / mp3d_habitat.zip)",
            root,
        )
    best: dict[str, tuple[tuple, HouseSource]] = {}
    for key, src in found:
        if src.id not in best or key < best[src.id][0]:
            best[src.id] = (key, src)
    return {hid: best[hid][1] for hid in sorted(best)}
