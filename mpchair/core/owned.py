"""Output folders a command may replace: only its own. A command never deletes or rewrites what it did not create.

A folder a command fills as a whole (``detector export --out``, a run record, ``eval``'s ``data/``) gets a marker
file, :data:`MARKER`, when it is made: which command made it and every file it holds. Before a later run replaces
such a folder it checks that the marker names the same command and that the folder holds nothing the marker does
not list (a file a user added is never deleted: the command is refused instead, naming the folder and the file).
Anything else that is not missing or empty is refused the same way.

Replacing is a swap: the new folder is filled completely under a hidden name beside the old one, marked, and then
exchanged with it in one ``renameat2(RENAME_EXCHANGE)`` (Linux; a rename aside and back elsewhere), so the output
path always holds a complete folder; the old one, now under the hidden name, is removed. The hidden work folders
carry the marker from their creation, so the next run of the same command removes what a killed run left there
(``.OUT.work*``, ``.OUT.old*``) and nothing else (:func:`clear_leftovers`). Where the file system lacks the exchange,
the old folder is renamed aside to ``.OUT.old<pid>`` and the new one renamed in: a kill between the two leaves no
OUT, and the next run puts the old folder back before anything else.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from mpchair.core.atomic import write_text
from mpchair.core.errors import InputError

#: The marker file in a folder a command owns: ``{"made_by": COMMAND, "files": [relative paths]}``.
MARKER = ".mpchair-output.json"
#: The largest marker read (a marker is a list of file names: a bigger one is not ours).
_MARKER_MAX_BYTES = 4 << 20

#: A check for folders written before markers existed: the folder's files when it is recognisably the command's
#: (e.g. a record's ``record.json`` lists them), else None.
Legacy = Callable[[Path], "set[str] | None"]


def _entries(folder: Path) -> list[str]:
    """Every file, link and special file under ``folder`` (relative paths; folders are not entries). Symlinks are not
    followed."""
    out = []
    for dirpath, dirnames, filenames in os.walk(folder):
        base = Path(dirpath)
        for name in [*filenames, *(d for d in dirnames if (base / d).is_symlink())]:
            out.append(str((base / name).relative_to(folder)))
    return sorted(out)


def read_marker(folder: Path) -> dict | None:
    """The marker of ``folder`` as a dict, or None when there is none or it is not a marker (a link, a special file,
    not JSON, the wrong shape)."""
    path = folder / MARKER
    try:
        if not path.is_file() or path.is_symlink() or path.stat().st_size > _MARKER_MAX_BYTES:
            return None
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None
    if not isinstance(meta, dict) or not isinstance(meta.get("made_by"), str):
        return None
    files = meta.get("files")
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return None
    return meta


def foreign_entry(folder: Path, command: str, *, legacy: Legacy | None = None,
                  nested: tuple[str, ...] = ()) -> str | None:
    """None when ``folder`` is ``command``'s own (its marker names ``command`` and lists every file in it, or
    ``legacy`` recognises it), else the reason it is not, naming a file it holds that ``command`` did not write.
    ``nested``: top-level subfolders (or files) that another command owns inside this one (left out of the
    comparison; see :func:`replace_folder`)."""
    entries = [e for e in _entries(folder) if Path(e).parts[0] not in nested]
    meta = read_marker(folder)
    if meta is not None and meta["made_by"] == command:
        listed = set(meta["files"]) | {MARKER}
    elif meta is not None:
        return f"it was made by {meta['made_by']}, not {command}"
    else:
        listed = legacy(folder) if legacy is not None else None
        if listed is None:
            sample = entries[0] if entries else "a folder"
            return f"it holds files {command} did not write (e.g. {sample})"
    extra = [e for e in entries if e not in listed]
    if extra:
        return f"it holds {extra[0]}, which {command} did not write" + (
            f" (and {len(extra) - 1} more)" if len(extra) > 1 else "")
    return None


def check_replaceable(out: Path, command: str, *, legacy: Legacy | None = None, option: str = "--out",
                      nested: tuple[str, ...] = ()) -> None:
    """Before any work: :class:`InputError` naming ``out`` unless it is missing, an empty folder, or ``command``'s own
    folder (see :func:`foreign_entry`). The current folder and the folders above it are never replaced."""
    if not out.exists() and not out.is_symlink():
        return
    if not out.is_dir():
        raise InputError(f"exists and is not a folder; choose another {option}", out)
    real = Path(os.path.realpath(out))
    try:
        here = Path.cwd().resolve()
    except FileNotFoundError:  # the current folder was removed: it is nothing to protect
        here = None
    if here is not None and (real == here or real in here.parents):
        raise InputError(f"is the current folder or holds it, so {command} will not replace it; choose another "
                         f"{option}", out)
    if not any(real.iterdir()):
        return
    why = foreign_entry(real, command, legacy=legacy, nested=nested)
    if why is not None:
        raise InputError(f"will not replace this folder: {why}; choose another {option} (or empty it yourself)", out)


def write_marker(folder: Path, command: str, *, list_files: bool = True) -> None:
    """Mark ``folder`` as ``command``'s, listing every file it holds now; without ``list_files`` only who made it
    (a hidden work folder, which only :func:`remove_leftovers` checks, or a folder that grows, like a training run)."""
    files = [e for e in _entries(folder) if e != MARKER] if list_files else []
    write_text(folder / MARKER, json.dumps({"made_by": command, "files": files}, indent=1) + "\n")


def made_by(folder: Path, command: str) -> bool:
    """Whether ``folder``'s marker names ``command`` (whatever else the folder holds)."""
    meta = read_marker(folder)
    return meta is not None and meta["made_by"] == command


def work_dir(parent: Path, prefix: str, command: str) -> Path:
    """A new hidden folder ``parent/<prefix><random>`` marked as ``command``'s work folder (so that the next run
    removes it if this one is killed)."""
    parent.mkdir(parents=True, exist_ok=True)
    path = Path(tempfile.mkdtemp(dir=parent, prefix=prefix))
    try:
        write_marker(path, command, list_files=False)
    except BaseException:  # a full disk: an unmarked folder would stay forever (remove_leftovers proves ownership)
        with contextlib.suppress(OSError):
            path.rmdir()
        raise
    return path


def _ours(folder: Path, command: str, legacy: Legacy | None) -> bool:
    """Whether the real folder ``folder`` (no link) is ``command``'s: its marker names it, or, unmarked, ``legacy``
    recognises every file in it."""
    if folder.is_symlink() or not folder.is_dir():
        return False
    meta = read_marker(folder)
    if meta is not None:
        return meta["made_by"] == command
    return legacy is not None and foreign_entry(folder, command, legacy=legacy) is None


def remove_leftovers(parent: Path, prefixes: tuple[str, ...], command: str, *,
                     legacy: Legacy | None = None) -> list[Path]:
    """Remove the folders ``parent/<prefix>*`` that ``command``'s marker (or ``legacy``) proves are its own, left by a
    killed run (the caller holds the output's lock, so none is in use). The paths removed."""
    removed = []
    if not parent.is_dir():
        return removed
    for p in sorted(parent.iterdir()):
        if p.name.startswith(prefixes) and _ours(p, command, legacy):
            shutil.rmtree(p)
            removed.append(p)
    return removed


def clear_leftovers(out: Path, command: str, *, legacy: Legacy | None = None,
                    extra: tuple[str, ...] = ()) -> list[Path]:
    """Before a run of ``command`` replaces ``out`` (under its lock): undo what a killed :func:`replace_folder` left.
    A swap killed between its two renames (file systems without ``RENAME_EXCHANGE``) left no ``out`` and the old
    folder at ``.OUT.old<pid>``: it is put back first, so the previous output is never lost to a kill. Then the
    command's own ``.OUT.work*`` / ``.OUT.old*`` folders (and ``extra`` prefixes) are removed. The paths removed."""
    if not out.exists() and not out.is_symlink() and out.parent.is_dir():
        swapped = [p for p in out.parent.iterdir()
                   if p.name.startswith(f".{out.name}.old") and p.name[len(out.name) + 5:].isdigit()
                   and _ours(p, command, legacy)]
        if swapped:  # one at most: the lock lets a single run swap at a time
            max(swapped, key=lambda p: p.stat().st_mtime).rename(out)
    return remove_leftovers(out.parent, (f".{out.name}.work", f".{out.name}.old", *extra), command, legacy=legacy)


_RENAME_EXCHANGE = 2  # <linux/fs.h>


def _exchange(a: Path, b: Path) -> bool:
    """Swap the paths ``a`` and ``b`` atomically (Linux ``renameat2``); False where that is not available."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd = -100
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):  # a file system without it
        return False
    raise OSError(err, os.strerror(err), str(b))


def replace_folder(stage: Path, out: Path, command: str, *, legacy: Legacy | None = None,
                   nested: tuple[str, ...] = ()) -> None:
    """Mark the complete folder ``stage`` (beside ``out``, same file system) as ``command``'s and put it at ``out``;
    an ``out`` already there must be ``command``'s own (checked again here: :class:`InputError` otherwise) and is
    removed once swapped out. A symlink ``out`` keeps pointing at the new folder (the folder it names is replaced).
    ``nested`` top-level subfolders and files of the old ``out`` belong to another command (e.g. the accuracy
    study's record and its summary inside the run record): they are copied into the new folder unchanged, never
    judged or dropped."""
    if out.is_symlink():
        out = Path(os.path.realpath(out))
    for name in nested:
        src = out / name
        if src.is_symlink() or (stage / name).exists():
            continue
        if src.is_dir():
            shutil.copytree(src, stage / name, symlinks=True)
        elif src.is_file():
            shutil.copy2(src, stage / name)
    write_marker(stage, command)
    if not out.exists():
        stage.rename(out)
        return
    check_replaceable(out, command, legacy=legacy, nested=nested)
    if _exchange(stage, out):
        shutil.rmtree(stage)  # now the old folder, checked above to be ours
        return
    old = out.parent / f".{out.name}.old{os.getpid()}"
    out.rename(old)
    try:
        stage.rename(out)
    except BaseException:
        with contextlib.suppress(OSError):
            old.rename(out)
        raise
    shutil.rmtree(old)
