"""Find houses on disk and read their ``house_segmentations`` files, extracted or straight from the release zip.

Accepted roots (see :func:`find_houses`): the download root (``<root>/v1/scans/<id>/...``), a ``scans/`` folder, one
scan folder, a ``house_segmentations/`` folder (or any folder holding ``<id>.house``), or a
``house_segmentations.zip`` file. Inside a scan folder the files may be extracted from ``v1/scans``
(``<id>/house_segmentations/<id>.house``), extracted inside the scan folder (``<id>/<id>/house_segmentations/...``) or
still zipped (``<id>/house_segmentations.zip`` whose members are ``<id>/house_segmentations/<id>.*``).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

from mpchair.errors import InputError

#: The side files of one house, by suffix; ``.house`` and ``.ply`` are required.
SUFFIXES = (".house", ".ply", ".fsegs.json", ".semseg.json")


@dataclass(frozen=True)
class HouseSource:
    """Where one house's files live: a folder holding ``<id>.house`` etc. (``zip_path`` None), or a zip file whose
    members are ``<prefix><id>.house`` etc."""

    id: str
    folder: Path | None = None
    zip_path: Path | None = None
    prefix: str = ""

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

    def read_bytes(self, suffix: str) -> bytes:
        """Contents of ``<id><suffix>``; a missing or unreadable file is an :class:`InputError`."""
        where = self.describe(suffix)
        if self.zip_path is not None:
            try:
                with zipfile.ZipFile(self.zip_path) as zf:
                    return zf.read(f"{self.prefix}{self.id}{suffix}")
            except KeyError:
                raise InputError("file not found in the zip archive", where) from None
            except (zipfile.BadZipFile, OSError) as e:
                raise InputError(f"cannot read zip archive: {e}", self.zip_path) from None
        p = Path(self.folder or ".") / f"{self.id}{suffix}"
        try:
            return p.read_bytes()
        except FileNotFoundError:
            raise InputError("file not found", where) from None
        except OSError as e:
            raise InputError(f"cannot read file: {e.strerror}", where) from None


def _houses_in_folder(folder: Path) -> dict[str, HouseSource]:
    """Houses whose ``<id>.house`` sits directly in ``folder``."""
    return {p.name[: -len(".house")]: HouseSource(p.name[: -len(".house")], folder=folder)
            for p in sorted(folder.glob("*.house")) if p.is_file()}  # fmt: skip


def _houses_in_zip(zip_path: Path) -> dict[str, HouseSource]:
    """Houses inside a ``house_segmentations.zip`` (members ``<id>/house_segmentations/<id>.house`` or similar)."""
    try:
        with zipfile.ZipFile(zip_path) as zf:
            names = zf.namelist()
    except (zipfile.BadZipFile, OSError) as e:
        raise InputError(f"cannot read zip archive: {e}", zip_path) from None
    out = {}
    for name in sorted(names):
        if name.endswith(".house") and not name.endswith("/"):
            prefix, _, base = name.rpartition("/")
            hid = base[: -len(".house")]
            out.setdefault(hid, HouseSource(hid, zip_path=zip_path, prefix=prefix + "/" if prefix else ""))
    return out


def _houses_in_scan(scan: Path) -> dict[str, HouseSource]:
    """Houses of one scan folder ``v1/scans/<id>`` in any of its extracted or zipped layouts (extracted first)."""
    for cand in (scan / "house_segmentations", scan / scan.name / "house_segmentations"):
        if cand.is_dir():
            found = _houses_in_folder(cand)
            if found:
                return found
    z = scan / "house_segmentations.zip"
    if z.is_file():
        return _houses_in_zip(z)
    return _houses_in_folder(scan)


def find_houses(root: str | Path) -> dict[str, HouseSource]:
    """All houses under ``root`` as ``{id: HouseSource}``, sorted by id (layouts in the module docstring).

    A root that does not exist, or holds no house, is an :class:`InputError`.
    """
    root = Path(root)
    if not root.exists():
        raise InputError("house root not found", root)
    if root.is_file():
        if zipfile.is_zipfile(root):
            found = _houses_in_zip(root)
        elif root.name.endswith(".house"):
            found = {root.name[:-6]: HouseSource(root.name[:-6], folder=root.parent)}
        else:
            raise InputError("expected a folder, a .house file or a house_segmentations.zip", root)
    else:
        scans = root / "v1" / "scans"
        if not scans.is_dir():
            scans = root
        found = _houses_in_scan(scans) if scans == root else {}
        if not found:
            found = {}
            for child in sorted(p for p in scans.iterdir() if p.is_dir()):
                for hid, src in _houses_in_scan(child).items():
                    found.setdefault(hid, src)
    if not found:
        raise InputError(
            "no house found (expected v1/scans/<id>/house_segmentations[.zip], a scans/ folder or a house folder)",
            root,
        )
    return dict(sorted(found.items()))
