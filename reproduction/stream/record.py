"""The streaming run's record: the small files of ``make reproduce-stream``'s work folder from which the results block
of docs/streaming.md is written, kept in the checkout (``docs/results-data/stream/`` for the full scale) so that the
block can be written again in a later session on another machine, as ``make reproduce``'s record
(:mod:`reproduction.record`) keeps docs/results.md's inputs.

What it keeps: ``commands.log`` (every command with its wall time), each stream's ``stream.json`` (houses with their
checksums, frames), every stream-eval summary (``measure.json``, ``raw.json``, ``ego.json``), every latency log
(``latency.json``: the measured per-frame latencies, with the machine they were measured on), the episode-bootstrap
gaps (``gap.json``), the held-out check of the streamed houses (``house_check.json``), ``machine.json`` (the machine
the record step ran on: CPU model, its instruction-set flags, threads, torch version, date) and ``record.json`` (the
plan as run: scale and its sizes, grids, threads, speeds, rates, held-out seed, the models' checkpoints, the notes,
the files). What it leaves out: the houses, the streams' frames and the saved per-frame detections (``outputs/``),
all remade from the seeds and the checkpoints.

The record folder is this command's own (:mod:`mpchair.core.owned`: a marker lists every file it wrote); a folder
holding anything else is refused, never replaced, and a symbolic link in a record is never followed on restore.

    tools/reproduce_stream.py --from-record docs/results-data/stream --steps report

writes the results block from the record alone (no models, no streams).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import shutil
from pathlib import Path

from mpchair.core.atomic import write_bytes, write_text
from mpchair.core.errors import InputError
from mpchair.core.owned import MARKER, check_replaceable, clear_leftovers, replace_folder, work_dir
from mpchair.core.text import load_json
from reproduction.checkout import ROOT
from reproduction.stream.sweep import SCALES, Scale

#: The command named in the record folder's ownership marker (:mod:`mpchair.core.owned`).
COMMAND = "tools/reproduce_stream.py --steps record"
RECORD_JSON = "record.json"
MACHINE_JSON = "machine.json"
#: The work folder's files a record keeps, by name (anywhere under ``eval/`` and ``streams/``) or path.
KEPT_NAMES = ("stream.json", "measure.json", "raw.json", "ego.json", "latency.json", "gap.json")
KEPT_PATHS = ("commands.log", "house_check.json")
#: A kept file larger than this is left out (and named in record.json), so the record stays small in the checkout.
MAX_FILE_BYTES = 4 << 20


class StreamRecordError(InputError):
    """A record that cannot be written or restored here; the message says why (one ``error:`` line, exit 2)."""


@dataclasses.dataclass(frozen=True)
class RecordPlan:
    """What the report needs besides the work folder's files: the scale's name and sizes, the grids and thread
    budgets (headline first), the sweep's speeds (m/s) and rates (Hz), the held-out houses' synth seed (None: given
    houses), the models' checkpoints (as the report names them) and the operator's notes."""

    scale: str
    sizes: Scale
    grids: tuple[str, ...]
    threads: tuple[int, ...]
    speeds: tuple[float, ...]
    rates: tuple[float, ...]
    heldout_seed: int | None
    checkpoints: dict[str, str]
    notes: tuple[str, ...] = ()

    def to_json(self) -> dict:
        return {"scale": self.scale, "scale_sizes": dataclasses.asdict(self.sizes), "grids": list(self.grids),
                "threads": list(self.threads), "speeds": list(self.speeds), "rates": list(self.rates),
                "heldout_seed": self.heldout_seed, "checkpoints": dict(self.checkpoints), "notes": list(self.notes)}

    @classmethod
    def from_json(cls, d: dict, where: Path) -> RecordPlan:
        """The plan of :meth:`to_json`'s data; a field a record step never writes is a :class:`StreamRecordError`
        naming ``where``."""
        try:
            if d["scale"] not in SCALES:
                raise ValueError(f"scale {d['scale']!r}")
            sizes = Scale(**d["scale_sizes"])
            plan = cls(scale=d["scale"], sizes=sizes, grids=tuple(str(g) for g in d["grids"]),
                       threads=tuple(int(t) for t in d["threads"]), speeds=tuple(float(v) for v in d["speeds"]),
                       rates=tuple(float(f) for f in d["rates"]),
                       heldout_seed=None if d["heldout_seed"] is None else int(d["heldout_seed"]),
                       checkpoints={str(k): str(v) for k, v in d["checkpoints"].items()},
                       notes=tuple(str(n) for n in d.get("notes", [])))
        except (AttributeError, KeyError, TypeError, ValueError) as e:
            raise StreamRecordError(f"{where}: not a streaming record ({type(e).__name__}: {e})") from None
        if not plan.grids or not plan.threads or min(plan.threads) < 1:
            raise StreamRecordError(f"{where}: not a streaming record (no grid or thread budget)")
        return plan


def machine_record() -> dict:
    """This machine as the record keeps it: :class:`detector.device.Machine` (CPU model, logical CPUs, torch threads
    and version, allocator), the CPU's instruction-set flags that decide the precisions it computes natively and its
    widest vector ISA, and the date (UTC)."""
    import torch

    from detector.deploy.cpu import cpu_flags, precision_flags
    from detector.device import Machine

    flags = cpu_flags()
    isa = ("avx512f" if "avx512f" in flags else "avx2" if "avx2" in flags else "none of avx2 / avx512f")
    return {**Machine.here(torch.device("cpu")).to_json(), "widest_vector_isa": isa,
            "native_precision_flags": precision_flags(flags),
            "isa_flags": sorted(f for f in flags if f.startswith(("avx", "amx", "fma", "sse4"))),
            "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M")}


def kept_files(out: Path) -> list[str]:
    """The work folder's files (relative paths) a record keeps: regular files only, never through a link."""
    kept = [p for p in KEPT_PATHS if (out / p).is_file() and not (out / p).is_symlink()]
    for sub in ("streams", "eval"):
        for dirpath, dirnames, filenames in os.walk(out / sub):  # os.walk follows no link to a folder
            base = Path(dirpath)
            dirnames[:] = [d for d in sorted(dirnames) if d not in ("outputs", "sequences")]
            kept += [str((base / f).relative_to(out)) for f in sorted(filenames)
                     if f in KEPT_NAMES and not (base / f).is_symlink()]
    return kept


def _recorded_bytes(path: Path) -> bytes:
    """A kept file's bytes with checkout paths made relative (a record restored in another clone reads the same)."""
    return path.read_bytes().replace(str(ROOT).encode() + b"/", b"")


def check_record_dest(dest: Path) -> None:
    """:class:`StreamRecordError` unless the record step may write ``dest``: missing, empty, or a record it wrote."""
    try:
        check_replaceable(dest, COMMAND, option="--record")
    except InputError as e:
        raise StreamRecordError(str(e)) from None


def save_stream_record(out: Path, dest: Path, plan: RecordPlan, machine: dict | None = None) -> list[str]:
    """Write work folder ``out``'s record into ``dest``: filled under a hidden name beside it and swapped in whole,
    replacing an older record there (only this command's: :func:`check_record_dest`). ``machine``: the machine
    record (default: this machine now). The paths left out for their size."""
    check_record_dest(dest)
    kept, too_big = {}, []
    for rel in kept_files(out):
        data = _recorded_bytes(out / rel)
        if len(data) > MAX_FILE_BYTES:
            too_big.append(rel)
        else:
            kept[rel] = data
    clear_leftovers(dest, COMMAND)
    stage = work_dir(dest.parent, f".{dest.name}.work", COMMAND)
    try:
        for rel, data in kept.items():
            write_bytes(stage / rel, data)
        write_text(stage / MACHINE_JSON, json.dumps(machine or machine_record(), indent=1) + "\n")
        meta = {**plan.to_json(), "files": list(kept), "left_out_for_size": too_big}
        write_text(stage / RECORD_JSON, json.dumps(meta, indent=1) + "\n")
        try:
            replace_folder(stage, dest, COMMAND)
        except InputError as e:
            raise StreamRecordError(str(e)) from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return too_big


def read_stream_record(record: Path) -> tuple[RecordPlan, list[str], dict]:
    """The plan, the files and the machine record of a record folder (:class:`StreamRecordError` when it is not
    one)."""
    path = record / RECORD_JSON
    try:
        meta = load_json(path, "streaming record", max_bytes=16 << 20)
        machine = load_json(record / MACHINE_JSON, "streaming record's machine")
    except InputError as e:
        raise StreamRecordError(f"not a streaming record: {e}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("files"), list) or not isinstance(machine, dict):
        raise StreamRecordError(f"{path}: not a streaming record (no 'files')")
    for rel in meta["files"]:
        if not isinstance(rel, str) or not rel or Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise StreamRecordError(f"{path}: file {rel!r} lies outside the record")
    return RecordPlan.from_json(meta, path), list(meta["files"]), machine


def restore_stream_record(record: Path, out: Path) -> list[str]:
    """Copy the record's files into work folder ``out`` where it lacks them (the report then reads them); only
    regular files inside the record, never through a symbolic link. The paths restored."""
    _, files, _ = read_stream_record(record)
    restored = []
    for rel in files:
        src, dst = record / rel, out / rel
        if any(p.is_symlink() for p in (src, *src.parents) if p == src or record in p.parents):
            raise StreamRecordError(f"{src}: a symbolic link; a record is restored only from regular files inside it")
        if not src.is_file():
            raise StreamRecordError(f"{record / RECORD_JSON}: lists {rel}, which the record does not have")
        if not src.resolve().is_relative_to(record.resolve()):
            raise StreamRecordError(f"{src}: lies outside the record")
        if rel == MARKER:
            continue
        if not dst.exists():
            write_bytes(dst, src.read_bytes())
            restored.append(rel)
    return restored
