"""The skeleton ``mpchair generate`` and ``mpchair stream`` share: a resumable job that fills one output folder.

Both jobs run the same steps, each in its own module, with the pieces here:

1. check the request's numbers (:func:`check_houses_and_workers`) and plan the run before touching the folder: load
   the sensor, the classes (:func:`resolve_classes`) and the houses, and collect the settings the output depends on;
2. lock the folder and check its settings file (:func:`check_settings`): a new folder takes the settings, a folder
   made with other settings is refused, so that a re-run with the same arguments resumes;
3. remove the temporary files a killed run left (:func:`remove_temps`), keep the tasks whose record is missing;
4. make them, in one process or a fork pool (:func:`make_tasks`: progress bar, dead workers, Ctrl-C);
5. write the folder's summary files last, with the command line that makes it (:func:`command_line`).

A job's module owns its request, plan, worker, task and summary types; :class:`JobKind` names what the messages and
files here need to know of it.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TypeVar

from mpchair.core.atomic import temp_glob, write_text
from mpchair.core.errors import InputError, RunError
from mpchair.core.heap import keep_freed_memory
from mpchair.dataset.workers import WorkerDied, imap_unordered
from mpchair.matterport.categories import mpcat40_name, resolve_categories

T = TypeVar("T")
R = TypeVar("R")

#: What an interrupted job's messages say of its folder.
RESUME = "the frames written so far are kept: run the same command again to resume"


@dataclasses.dataclass(frozen=True)
class JobKind:
    """What the shared steps need to know of a job: its ``command`` (``mpchair <command>``, also the progress bar's
    label), the ``folder`` word of its messages (``"dataset"``) and its ``settings_file`` (``.generate.json``)."""

    command: str
    folder: str
    settings_file: str


def check_houses_and_workers(houses: Sequence[str], workers: int) -> None:
    """The checks every job's request starts with: at least one ``--house``, none repeated, ``--workers`` >= 1."""
    if not houses:
        raise InputError("give at least one --house")
    if len(set(houses)) != len(houses):
        raise InputError("a --house is repeated")
    if workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")


def resolve_classes(categories: Iterable[str]) -> tuple[frozenset[int], tuple[str, ...]]:
    """The ``--category`` values (mpcat40 names or indices) as ``(mpcat40 indices, mpcat40 names sorted)``; an
    unknown class is an :class:`InputError`."""
    ids = resolve_categories(list(categories))
    return ids, tuple(sorted(mpcat40_name(c) for c in ids))


def settings_text(settings: dict) -> str:
    """The settings file's text: the settings as sorted, indented JSON (what a re-run compares byte for byte)."""
    return json.dumps(settings, sort_keys=True, indent=1) + "\n"


def check_settings(kind: JobKind, out: Path, settings: dict, *, alone: bool, replace: bool,
                   ours: Callable[[str], bool]) -> None:
    """Write ``kind``'s settings file into a new folder ``out``, or check that the existing one holds ``settings``.

    ``alone``: no other process of the job writes ``out`` (then temp files of a killed settings write are stale and
    removed). ``replace``: a settings file that differs is replaced instead of refused (the caller knows that no frame
    was made with it). ``ours(name)``: a file a run of the job may leave in a folder before its settings file (its lock
    files); any other file there means ``out`` is not the job's folder. The caller holds the folder's lock.
    """
    path = out / kind.settings_file
    text = settings_text(settings)
    if alone:
        for p in out.glob(temp_glob(kind.settings_file)):
            p.unlink(missing_ok=True)
    if path.is_file():
        old_text = path.read_text(encoding="utf-8")
        if old_text == text:
            return
        if not replace:
            try:
                old = json.loads(old_text)
                diff = ", ".join(sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k)))
            except (json.JSONDecodeError, AttributeError):
                diff = "the file is not a settings object"
            raise InputError(f"holds a {kind.folder} made with other settings ({diff} differ); use a new --out or the "
                             "same arguments to resume", path)
    elif out.exists() and any(not ours(p.name) and not _settings_temp(kind, p.name) for p in out.iterdir()):
        raise InputError(f"exists and is not an mpchair {kind.folder} folder (no {kind.settings_file}); choose an "
                         "empty --out", out)
    write_text(path, text)


def _settings_temp(kind: JobKind, name: str) -> bool:
    """Whether ``name`` is a temp file of a settings write (another live process of the job may be making it)."""
    return fnmatch.fnmatchcase(name, temp_glob(kind.settings_file))


def remove_temps(folders: Iterable[Path], owned: Callable[[str], bool] = lambda name: True) -> None:
    """Delete the temp files (``.<name>.*.tmp``, see :mod:`mpchair.core.atomic`) a killed run left in ``folders``
    (those that exist), only those whose name ``owned`` accepts (a shard removes only its own frames' temps)."""
    for d in folders:
        if d.is_dir():
            for p in d.iterdir():
                if p.name.startswith(".") and p.name.endswith(".tmp") and owned(p.name):
                    p.unlink(missing_ok=True)


def make_tasks(make: Callable[[T], R], pending: Sequence[T], total: int, *, workers: int, out: Path, kind: JobKind,
               progress: bool, is_done: Callable[[T], bool], account: Callable[[R], dict] | None = None) -> float:
    """Run ``make`` on every ``pending`` task (each makes and writes one frame), in worker processes when ``workers``
    > 1, with a progress bar over the job's ``total`` frames; returns the seconds it took.

    ``make`` is called in forked workers, which inherit it (never pickled): bind what it needs with
    ``functools.partial``. ``account(result)``: numbers shown beside the bar. ``is_done(task)``: whether the task's
    frame is on disk (counted for the Ctrl-C message). Bad input and OS errors propagate as they are (the caller
    knows what to undo or hint); a dead worker, or another error in one, is a :class:`RunError`; Ctrl-C a
    ``KeyboardInterrupt`` that says how many frames are kept.
    """
    from tqdm import tqdm

    bar = tqdm(total=total, initial=total - len(pending), unit="frame", disable=not progress, file=sys.stderr,
               dynamic_ncols=True, desc=kind.command)
    pooled = workers > 1 and len(pending) > 1
    t0 = time.perf_counter()
    try:
        if pooled:
            # Forked workers inherit what ``make`` holds (houses, scenes) instead of re-reading it; chunks of 4
            # frames: one pipe round trip per frame cost the parent ~1 ms of CPU per frame. A worker that dies (the
            # OOM killer) or raises stops the others at once (mpchair.dataset.workers).
            results = imap_unordered(make, pending, min(workers, len(pending)), initializer=keep_freed_memory,
                                     chunksize=4)
        else:
            results = map(make, pending)
        for result in results:
            bar.update(1)
            if account is not None:
                bar.set_postfix(account(result), refresh=False)
    except (InputError, OSError):
        raise
    except KeyboardInterrupt:
        bar.close()  # the message below starts on a line of its own
        done = sum(is_done(t) for t in pending) + total - len(pending)
        raise KeyboardInterrupt(f"{done} of {total} frames are kept in {out}: run the same command again to resume") \
            from None
    except WorkerDied as e:
        raise RunError(f"{out}: {e}; stopped the other workers; {RESUME}") from None
    except Exception as e:
        if pooled:  # a worker's unexpected error: its traceback stayed in the worker
            raise RunError(f"{out}: a worker process failed: {type(e).__name__}: {e}; stopped the other workers; "
                           f"{RESUME}") from e
        raise
    finally:
        bar.close()
    return time.perf_counter() - t0


def per_second(made: int, seconds: float) -> float:
    """Frames per second of ``made`` frames in ``seconds`` (0 when nothing was made)."""
    return made / seconds if made and seconds > 0 else 0.0


def with_hint(e: OSError, hint: str) -> OSError:
    """The same OS error (errno, file) with ``hint`` after its reason."""
    return type(e)(e.errno, f"{e.strerror or e}; {hint}", e.filename)


#: One flag of a recorded command line: ``(name, value)``, see :func:`command_line`.
Flag = tuple[str, "str | int | float | bool | None | Sequence[str]"]


def command_line(kind: JobKind, root: Path, houses: Sequence[str], flags: Sequence[Flag]) -> tuple[str, ...]:
    """The command line that makes a job's folder, as its summary file records it: ``mpchair <command> --root
    <root's folder name> --house ...`` (no absolute path), then ``flags`` in order: a tuple or list repeats its flag
    per item, ``True`` writes the flag alone (pass switches as ``bool``), ``False`` and ``None`` leave it out, a
    float is written by ``repr`` (it reads back to the same number), anything else by ``str``."""
    command = ["mpchair", kind.command, "--root", Path(root).name]
    for h in houses:
        command += ["--house", h]
    for flag, value in flags:
        if value is None or value is False:
            continue
        if value is True:
            command.append(flag)
        elif isinstance(value, (tuple, list)):
            command += [w for v in value for w in (flag, str(v))]
        else:
            command += [flag, repr(value) if isinstance(value, float) else str(value)]
    return tuple(command)
