"""The houses of one run (``mpchair generate`` or ``mpchair stream``): found by id under a root, read, checked for
objects of the classes to label, hashed, with the package versions that made the run.

Both commands record the same provenance (``files_sha256`` and ``versions`` in ``manifest.json`` / ``stream.json``)
from :func:`load_run_houses`, so a dataset or stream names exactly the house files it was made from.
"""

from __future__ import annotations

import dataclasses
import hashlib
import platform
from collections.abc import Callable, Mapping
from importlib import metadata
from pathlib import Path
from typing import Literal

from mpchair import __version__
from mpchair.core.errors import InputError
from mpchair.matterport.categories import mpcat40_name
from mpchair.matterport.house import House, objects_of, read_house
from mpchair.matterport.source import SUFFIXES, HouseSource, find_houses


@dataclasses.dataclass(frozen=True)
class RunHouses:
    """The houses a run uses, in the order given: ``houses`` (id → :class:`House`, world frame), ``files_sha256``
    (id → {file name → hex sha256} of every house file read), ``objects_of_class`` (id → objects of the classes to
    label) and ``versions`` (package → version of the packages the output depends on)."""

    houses: Mapping[str, House]
    files_sha256: Mapping[str, dict[str, str]]
    objects_of_class: Mapping[str, int]
    versions: dict[str, str]

    @property
    def ids(self) -> tuple[str, ...]:
        """The house ids, in the run's order."""
        return tuple(self.houses)


def load_run_houses(root: str | Path, ids: tuple[str, ...], categories: frozenset[int], *, backend: str,
                    navmesh: bool = True, hashed: Literal["read", "layout"] = "read",
                    check: Callable[[House], None] | None = None) -> RunHouses:
    """Find the houses ``ids`` under ``root``, read them (``navmesh``: with habitat's ``<id>.navmesh`` when there is
    one) and hash their files: ``hashed="read"`` the files read (``generate``: the navmesh only when it was read,
    whatever the layout), ``"layout"`` the files of the house's layout that exist (``stream``: a release-layout
    house's navmesh is not among them). ``categories`` are the mpcat40 indices to label; ``backend`` the raycasting
    backend (its package joins :func:`package_versions`); ``check`` runs on each house right after it is read, before
    the next one is (so errors come in house order).

    An unknown id (the available ones are listed) or a house without an object of the classes is an
    :class:`InputError`, raised before the next house is read.
    """
    found = find_houses(root)
    unknown = [h for h in ids if h not in found]
    if unknown:
        raise InputError(f"unknown house {unknown[0]!r} (available: {', '.join(sorted(found))})", root)
    houses: dict[str, House] = {}
    hashes: dict[str, dict[str, str]] = {}
    counts: dict[str, int] = {}
    for hid in ids:
        src = found[hid]
        house = read_house(src, navmesh=navmesh)
        counts[hid] = len(objects_of(house, categories))
        if not counts[hid]:
            names = ", ".join(sorted(mpcat40_name(c) for c in categories))
            have = ", ".join(f"{k} {v}" for k, v in house.objects_by_category().items()) or "no objects"
            raise InputError(f"house {hid} has no object of class {names} (it has: {have})", src.describe(".house"))
        if check is not None:
            check(house)
        houses[hid] = house
        hashes[hid] = {f"{hid}{s}": sha256_of(src, s) for s in _hashed_files(src, house, hashed) if src.exists(s)}
    return RunHouses(houses=houses, files_sha256=hashes, objects_of_class=counts, versions=package_versions(backend))


def _hashed_files(src: HouseSource, house: House, hashed: str) -> list[str]:
    """Suffixes of the files of ``src`` to hash (see :func:`load_run_houses`)."""
    if hashed == "layout":
        return list(SUFFIXES[src.layout])
    return [s for s in SUFFIXES[src.layout] if s != ".navmesh"] + [".navmesh"] * (house.navmesh is not None)


def sha256_of(source: HouseSource, suffix: str) -> str:
    """Hex sha256 of one house file's bytes (``suffix`` like ``.house``)."""
    return hashlib.sha256(source.read_bytes(suffix)).hexdigest()


def package_versions(backend: str) -> dict[str, str]:
    """Versions of mpchair, Python and the installed packages a run's output depends on (the raycasting
    ``backend``'s included); packages that are not installed are left out."""
    out = {"mpchair": __version__, "python": platform.python_version()}
    names = ["numpy", "trimesh", "embreex", "shapely", "pillow"] + (["open3d-cpu", "open3d"] if backend == "open3d"
                                                                    else [])
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out
