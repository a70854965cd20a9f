"""The run folder's own files besides checkpoints and metrics: the experiment as run (``config.yaml``), the cached
GT-sampling database (``gt_database.npz``), the folder's ownership marker, and the clean-up of temp files a killed run
left.

A run folder is new, empty, or a run's (:mod:`mpchair.core.owned`'s marker, or an older run's ``last.pt``, or its
``config.yaml`` beside ``metrics.jsonl``): ``detector train`` never takes over a folder that holds other files, and
removes only temp files with the names its atomic writes give (``.<name>.<12 hex digits>.tmp``). A new run that meets
bad input before its first checkpoint (a scan only the loader reads) removes the files it wrote and the folders it
made, so a failed start leaves no run behind.

Rank 0 writes them (the caller holds the folder's lock); the other ranks of a torchrun job read the database after a
barrier.
"""

from __future__ import annotations

import contextlib
import json
import re
from pathlib import Path

import yaml

from detector.config import ExperimentConfig
from detector.data import GTDatabase, KittiDataset, build_gt_database
from detector.train.distributed import DistInfo, barrier
from mpchair.core.atomic import write_text
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError
from mpchair.core.owned import MARKER, made_by, write_marker

DATABASE_FILE = "gt_database.npz"
#: The command named in a run folder's ownership marker.
COMMAND = "detector train"
#: The files a run writes before its first checkpoint: all a failed start removes (with its temp files).
_START_FILES = (MARKER, "config.yaml", DATABASE_FILE, "metrics.jsonl")
#: The temp files :mod:`mpchair.core.atomic` names (``.<name>.<12 hex digits>.tmp``): the only ones a run removes.
_TEMP_NAME = re.compile(r"\..+\.[0-9a-f]{12}\.tmp")


def check_run_folder(out: Path) -> None:
    """Before anything is written: :class:`InputError` unless ``out`` is missing, an empty folder, or a training run's
    folder (its marker, or an older run's ``last.pt``, or its ``config.yaml`` beside ``metrics.jsonl``)."""
    if not out.exists():
        return
    if not out.is_dir():
        raise InputError("exists and is not a folder; choose another --out", out)
    if not any(out.iterdir()) or made_by(out, COMMAND):
        return
    if (out / "last.pt").is_file() or ((out / "config.yaml").is_file() and (out / "metrics.jsonl").is_file()):
        return  # a run from before markers (or its checkpoint alone: --resume reads and checks it)
    sample = sorted(p.name for p in out.iterdir())[0]
    raise InputError(f"folder is not empty and is not a training run (it holds {sample}, and no run marker); "
                     "choose another --out (an empty or new folder)", out)


def missing_folders(out: Path) -> list[Path]:
    """``out`` and its parents that do not exist yet, deepest first: the folders a run will make (``[]``: ``out``
    exists; a failed start removes them again if empty)."""
    missing = []
    for p in (out, *out.parents):
        if p.exists() or p.is_symlink():
            break
        missing.append(p)
    return missing


def remove_empty_folders(folders: list[Path]) -> None:
    """Remove each of ``folders`` (deepest first, as :func:`missing_folders` lists them) that is empty: a file anyone
    else put there keeps its folder."""
    for folder in folders:
        with contextlib.suppress(OSError):
            folder.rmdir()


def discard_start(out: Path) -> None:
    """Undo a new run's start (rank 0, under the folder's lock; the caller knows ``out`` was new or empty and holds no
    ``last.pt``): remove the files a run writes before its first checkpoint and its temp files, nothing else."""
    remove_stale_temps(out)
    for name in _START_FILES:
        path = out / name
        if path.is_file() and not path.is_symlink():
            path.unlink()


def load_or_build_database(frames: KittiDataset, path: Path, *, progress: bool) -> tuple[GTDatabase, bool]:
    """The GT database of ``frames`` as cached at ``path``, or built anew when the split, classes or options differ
    (then ``True``: the caller saves it, once the run may write)."""
    meta = {
        "root": str(frames.root.resolve()),
        "split": frames.split,
        "ids": frames.ids,
        "classes": list(frames.classes),
        "name_map": frames.name_map,
        "fov_crop": frames.fov_crop,
    }
    if path.is_file():
        try:
            db = GTDatabase.load(path)
            if db.meta == json.loads(json.dumps(meta)):
                return db, False
        except InputError:
            pass  # a damaged cache is rebuilt
    return build_gt_database(frames, meta=meta, progress=progress), True


def remove_stale_temps(out: Path) -> None:
    """Delete temp files (``.<name>.<12 hex digits>.tmp``) a killed run left in the run folder (the caller holds its
    lock); other files, a user's ``.notes.tmp`` included, are left alone."""
    for p in out.rglob(".*.tmp"):
        if _TEMP_NAME.fullmatch(p.name) and p.is_file() and not p.is_symlink():
            p.unlink(missing_ok=True)


def write_run_files(out: Path, cfg: ExperimentConfig, database: GTDatabase | None, new_database: bool) -> None:
    """Rank 0 at the start of a run: remove stale temp files, write ``config.yaml`` (the experiment as run) and the
    database when it was (re)built."""
    remove_stale_temps(out)
    if not made_by(out, COMMAND):
        write_marker(out, COMMAND, list_files=False)
    write_text(out / "config.yaml", yaml.safe_dump(to_dict(cfg), sort_keys=False))
    if new_database:
        database.save(out / DATABASE_FILE)


def shared_database(out: Path, info: DistInfo, database: GTDatabase | None, *,
                    gt_sampling: bool) -> GTDatabase | None:
    """Every rank's GT database: rank 0's own, the others read the file rank 0 wrote (after a barrier). None without
    GT sampling."""
    if not gt_sampling:
        return database
    barrier()
    return database if info.is_main else GTDatabase.load(out / DATABASE_FILE)
