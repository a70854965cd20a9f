"""Train / val / test membership of the frames of a dataset (``ImageSets/{train,val,test}.txt``).

* ``paper``: the paper's layout. Per house, the first half of its frames go to the training pool and the second half
  to ``test``; the pool (houses in command-line order) is split at 2/3: indices below go to ``train``, the last third
  to ``val`` (the original: training index < 5000 of 7500). As in the paper, train and test share houses.
* ``frame`` (default): a seeded random permutation of all frames, cut 60 / 20 / 20 % into train / val / test.
* ``house``: houses (not frames) are assigned whole, so no house is shared between splits: the ones the user names
  for ``val`` / ``test`` (``--val-house`` / ``--test-house``, every other house trains), or else a seeded shuffle
  cut 60 / 20 / 20 % of the houses (at least one each; needs 3 houses; 12 houses give 8 / 2 / 2). The manifest
  records which house went where (``split_houses``).

Frame ids are global 6-digit indices, ``house position * frames_per_house + frame index``.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from mpchair.core.atomic import link_or_copy
from mpchair.core.errors import InputError
from mpchair.kitti import frame_paths

SPLIT_MODES = ("frame", "house", "paper")
FRACTIONS = (0.6, 0.2, 0.2)


def house_splits(n_houses: int, seed: int, held_out: dict[str, tuple[int, ...]] | None = None) -> dict[str, list[int]]:
    """``{"train": [...], "val": [...], "test": [...]}`` of house positions (``--house`` order, each list sorted) for
    ``house`` mode: ``held_out`` names the val / test positions (the rest train), else a seeded 60 / 20 / 20 cut."""
    if held_out:
        val, test = sorted(held_out.get("val", ())), sorted(held_out.get("test", ()))
        if not val or not test:
            raise InputError("--val-house and --test-house: name at least one house for each")
        if set(val) & set(test):
            raise InputError("--val-house and --test-house: a house cannot be in both splits")
        train = [p for p in range(n_houses) if p not in set(val) | set(test)]
        if not train:
            raise InputError("--val-house / --test-house leave no house to train on")
        return {"train": train, "val": val, "test": test}
    if n_houses < 3:
        raise InputError(f"--split-mode house needs at least 3 houses, got {n_houses}")
    rng = np.random.default_rng([seed, zlib.crc32(b"split"), zlib.crc32(b"house")])
    perm = rng.permutation(n_houses)
    n_val = max(1, int(round(FRACTIONS[1] * n_houses)))
    n_test = max(1, int(round(FRACTIONS[2] * n_houses)))
    n_train = n_houses - n_val - n_test
    parts = np.split(perm, [n_train, n_train + n_val])
    return {name: sorted(int(p) for p in part) for name, part in zip(("train", "val", "test"), parts, strict=True)}


def split_frames(n_houses: int, frames_per_house: int, mode: str, seed: int,
                 held_out: dict[str, tuple[int, ...]] | None = None) -> dict[str, list[int]]:
    """``{"train": [...], "val": [...], "test": [...]}`` of global frame indices (each list sorted); ``held_out``:
    :func:`house_splits`' chosen val / test house positions (``house`` mode only)."""
    n = n_houses * frames_per_house
    ids = np.arange(n)
    rng = np.random.default_rng([seed, zlib.crc32(b"split"), zlib.crc32(mode.encode())])
    if mode == "paper":
        local = ids % frames_per_house
        half = frames_per_house // 2
        pool = ids[local < half]
        test = ids[local >= half]
        cut = (2 * len(pool)) // 3
        train, val = pool[:cut], pool[cut:]
    elif mode == "frame":
        perm = rng.permutation(n)
        a = int(round(FRACTIONS[0] * n))
        b = a + int(round(FRACTIONS[1] * n))
        train, val, test = perm[:a], perm[a:b], perm[b:]
    elif mode == "house":
        parts = house_splits(n_houses, seed, held_out)
        house_of = ids // frames_per_house
        train, val, test = (ids[np.isin(house_of, parts[k])] for k in ("train", "val", "test"))
    else:
        raise InputError(f"unknown split mode {mode!r} (choose from {', '.join(SPLIT_MODES)})")
    return {"train": sorted(int(i) for i in train), "val": sorted(int(i) for i in val),
            "test": sorted(int(i) for i in test)}


#: What a reader of the ``testing/`` folder needs of a frame (OpenPCDet's KITTI info creation: the scan, the
#: calibration, the image for its size; no labels, as KITTI's test split has none).
TESTING_KINDS = ("velodyne", "calib", "image_2")


def write_testing_folder(out: Path, test_ids: list[str]) -> None:
    """``out/testing/{velodyne,calib,image_2}/`` of the ``test`` split, as KITTI lays it out (OpenPCDet's
    ``create_kitti_infos`` reads the test split from ``testing/``): hard links to the frames' ``training/`` files,
    so no byte is stored twice and ``training/`` keeps every frame (Open3D-ML and our own readers take the splits
    from ``ImageSets/``)."""
    for fid in test_ids:
        src, dst = frame_paths(out, fid), frame_paths(out, fid, "testing")
        for kind in TESTING_KINDS:
            link_or_copy(getattr(src, kind), getattr(dst, kind))
