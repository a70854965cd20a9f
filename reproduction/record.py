"""The run record: the small files of a reproduction's work folder from which its report is written, kept in the
checkout (``docs/results-data/`` for the full scale) so that the report can be written again, and steps added to the
same run, in a later session on another machine (this project's machines keep no files between sessions).

What it keeps: every text / JSON / figure the steps wrote (``results/``, ``commands.log``; of ``runs/<model>/`` a
finished training's logs, config and ``done`` marker, so that a restored step counts as done), the
dataset's ``manifest.json`` (less its per-frame list) and ``ImageSets/``, and ``record.json``: the scale as run, the
operator's notes and the dataset's fingerprint. What it leaves out: checkpoints (``*.pt``), exported graphs, the
per-frame detection files (``results/**/data/``), the houses and the dataset's frames — all of them made again by the
steps from the seed (same seed, same bytes), and :func:`check_dataset` tells whether a regenerated dataset is the
recorded one.

    tools/reproduce.py --steps synth,generate,ablations,report,record --from-record docs/results-data

restores the record into the work folder (every recorded step counts as done), regenerates the dataset, refuses to
go on if it is not byte for byte the recorded one, trains the ablations and writes the report of the whole run.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
import shutil
from pathlib import Path

from mpchair.core.atomic import write_bytes, write_text
from mpchair.core.errors import InputError
from mpchair.core.owned import MARKER, check_replaceable, clear_leftovers, replace_folder, work_dir
from mpchair.core.text import load_json
from reproduction.checkout import ROOT
from reproduction.committed import committed_runs
from reproduction.scales import SCALES, Scale

#: The command named in a record folder's ownership marker (:mod:`mpchair.core.owned`).
COMMAND = "tools/reproduce.py --steps record"

RECORD_JSON = "record.json"
SCALE_NAMES = tuple(sorted(SCALES))
#: File kinds a record keeps (text and figures); anything else (checkpoints, ONNX / OpenVINO graphs) is left out.
KEPT_SUFFIXES = (".json", ".jsonl", ".md", ".txt", ".log", ".yaml", ".png", ".csv")
#: Kept files that are text: paths in them are written relative to the checkout (as the report writes them), so a
#: record restored in another clone reads the same.
TEXT_SUFFIXES = (".json", ".jsonl", ".md", ".txt", ".log", ".yaml", ".csv")
#: A kept file larger than this is left out (and named in record.json), so a record stays a few MB in the checkout.
MAX_FILE_BYTES = 4 << 20
#: The dataset's files the report reads; the frames themselves are regenerated.
DATASET_FILES = ("manifest.json", "ImageSets")


class RecordError(InputError):
    """A record that cannot be restored here (a different dataset, a malformed record.json); the message says why.
    An :class:`InputError`, so the command line prints it as one ``error:`` line and exits 2."""


def _kept(out: Path, rel: Path) -> bool:
    """Whether work-folder ``out``'s file ``rel`` (relative path) belongs in the record."""
    parts = rel.parts
    if rel.name == MARKER:  # an output folder's ownership marker: a restored file is not the command's output
        return False
    if parts[0] == "runs":
        # a finished training only (its ``done`` marker kept, so a restored run is not trained again); a training
        # still running or cut belongs to no step yet
        if len(parts) < 3 or not (out / "runs" / parts[1] / "done").exists():
            return False
        if parts[2:] == ("done",):
            return True
    if parts[0] == "houses" or rel.suffix not in KEPT_SUFFIXES:
        return False
    if parts[0] == "dataset":
        return len(parts) > 1 and parts[1] in DATASET_FILES
    return "data" not in parts[1:-1]  # **/data/: one detection file per frame, remade by the eval commands


def dataset_fingerprint(dataset: Path) -> str | None:
    """sha256 over every file of the dataset's ``training/`` and ``ImageSets/`` (path and bytes, sorted by path): equal
    fingerprints mean byte-identical datasets. None when ``dataset`` has no manifest (not generated)."""
    if not (dataset / "manifest.json").exists():
        return None
    h = hashlib.sha256()
    for sub in ("training", "ImageSets"):
        for p in sorted(q for q in (dataset / sub).rglob("*") if q.is_file()):
            h.update(str(p.relative_to(dataset)).encode() + b"\0")
            with open(p, "rb") as f:
                while chunk := f.read(1 << 22):
                    h.update(chunk)
            h.update(b"\0")
    return h.hexdigest()


def _recorded_bytes(out: Path, rel: str) -> bytes:
    """The bytes the record keeps of work-folder file ``rel``: text with checkout paths made relative; the dataset's
    manifest without its per-frame list (13 MB at the full scale; the report reads its houses and command)."""
    data = (out / rel).read_bytes()
    if rel == "dataset/manifest.json":
        manifest = json.loads(data)
        frames = manifest.pop("frames", None)
        if frames is not None:
            manifest["frames_left_out_of_the_record"] = len(frames)
        data = (json.dumps(manifest, indent=1) + "\n").encode()
    if Path(rel).suffix in TEXT_SUFFIXES:
        data = data.replace(str(ROOT).encode() + b"/", b"")
    return data


#: Entries of the run record that another command owns and the record step carries over unchanged: the accuracy
#: study's record and its summary (tools/accuracy_study.py writes docs/results-data/accuracy/ and accuracy.json) and
#: the streaming run's record (tools/reproduce_stream.py's record step writes docs/results-data/stream/).
NESTED = ("accuracy", "accuracy.json", "stream")


def _legacy_record(folder: Path) -> set[str] | None:
    """The files of a record written before ownership markers: its ``record.json`` lists them (None without one)."""
    try:
        meta = read_record(folder)
    except RecordError:
        return None
    return {*(f for f in meta["files"] if isinstance(f, str)), RECORD_JSON}


def check_record_dest(dest: Path) -> None:
    """:class:`RecordError` unless the record step may write ``dest``: missing, empty, or a record it wrote before
    (nothing added to it). A folder holding anything else is never replaced."""
    try:
        check_replaceable(dest, COMMAND, legacy=_legacy_record, option="--record", nested=NESTED)
    except InputError as e:
        raise RecordError(str(e)) from None


def save_record(out: Path, dest: Path, scale: str, sc: Scale, notes: list[str]) -> list[str]:
    """Write work folder ``out``'s record into ``dest`` (paths inside the checkout made relative to it): filled
    under a hidden name beside ``dest`` and swapped in whole, replacing an older record there (only a record: see
    :func:`check_record_dest`). The paths left out for their size."""
    check_record_dest(dest)
    inside = dest.resolve()
    too_big, kept = [], {}
    for p in sorted(q for q in out.rglob("*") if q.is_file() and not q.is_symlink()):
        rel = str(p.relative_to(out))
        if inside in p.resolve().parents or Path(rel).parts[0].startswith(f".{dest.name}.work"):
            continue  # the record itself (out/record by default) and its work folders
        if _kept(out, Path(rel)):
            data = _recorded_bytes(out, rel)
            if len(data) > MAX_FILE_BYTES:
                too_big.append(rel)
            else:
                kept[rel] = data
    clear_leftovers(dest, COMMAND, legacy=_legacy_record)
    stage = work_dir(dest.parent, f".{dest.name}.work", COMMAND)
    try:
        for rel, data in kept.items():
            write_bytes(stage / rel, data)
        meta = {"scale": scale, "scale_sizes": dataclasses.asdict(sc), "notes": list(notes),
                "dataset_sha256": dataset_fingerprint(out / "dataset"), "files": list(kept),
                "left_out_for_size": too_big}
        committed = committed_runs(out)
        if committed:  # which weights every runtime and AP figure of the record is of (runs/<model>/done has it too)
            meta["weights"] = {m: w.to_json() for m, w in committed.items()}
        write_text(stage / RECORD_JSON, json.dumps(meta, indent=1) + "\n")
        try:
            replace_folder(stage, dest, COMMAND, legacy=_legacy_record, nested=NESTED)
        except InputError as e:
            raise RecordError(str(e)) from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return too_big


def read_record(record: Path) -> dict:
    """``record.json`` of a record folder (:class:`RecordError` when it is missing or not a record's)."""
    path = record / RECORD_JSON
    try:
        meta = load_json(path, "run record", max_bytes=16 << 20)
    except InputError as e:
        raise RecordError(f"not a run record: {e}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("files"), list) or "scale_sizes" not in meta:
        raise RecordError(f"{path}: not a run record (no 'files' / 'scale_sizes')")
    _check_fields(meta, path)
    return meta


def _check_fields(meta: dict, path: Path) -> None:
    """:class:`RecordError` for a field of ``record.json`` that a record step never writes (checked like a config:
    types, ranges, known keys), naming the field."""
    def bad(field: str, why: str) -> RecordError:
        return RecordError(f"{path}: {field}: {why}")

    for rel in meta["files"]:
        if not isinstance(rel, str) or not rel or rel.strip() != rel:
            raise bad("files", f"expected relative paths, got {rel!r}")
        if ".." in Path(rel).parts or Path(rel).is_absolute():
            raise RecordError(f"{path}: file {rel!r} lies outside the record")
    if not isinstance(meta.get("notes", []), list) or not all(isinstance(n, str) for n in meta.get("notes", [])):
        raise bad("notes", f"expected a list of sentences, got {meta.get('notes')!r}")
    if not isinstance(meta.get("scale"), str) or meta["scale"] not in SCALE_NAMES:
        raise bad("scale", f"expected one of {', '.join(SCALE_NAMES)}, got {meta.get('scale')!r}")
    sha = meta.get("dataset_sha256")
    if sha is None and any(isinstance(f, str) and f.startswith("dataset/") for f in meta["files"]):
        raise bad("dataset_sha256", "missing, but the record holds a dataset: a regenerated one could not be checked")
    if sha is not None and not (isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha)):
        raise bad("dataset_sha256", f"expected 64 hex digits, got {sha!r}")
    sizes = meta["scale_sizes"]
    if not isinstance(sizes, dict):
        raise bad("scale_sizes", f"expected a mapping, got {type(sizes).__name__}")
    fields = {f.name: f for f in dataclasses.fields(Scale)}
    unknown = sorted(set(sizes) - set(fields))
    if unknown:
        raise bad("scale_sizes", f"unknown key {unknown[0]!r} (known: {', '.join(fields)})")
    missing = [k for k, f in fields.items() if k not in sizes and f.default is dataclasses.MISSING]
    if missing:
        raise bad("scale_sizes", f"missing key {missing[0]!r}")
    for key, value in sizes.items():
        if key == "precision":
            ok = value is None or value in ("fp32", "bf16", "auto")
        elif key == "curve_densities":
            ok = value is None or (isinstance(value, list) and all(_number(v) and 0 < v <= 1 for v in value))
        elif key == "split_mode":
            ok = value in ("frame", "house", "paper")
        elif key == "budget_seconds":
            ok = _number(value) and 0 < value <= 1e6
        else:  # counts: houses, frames, epochs, trials
            ok = (value is None and key == "epochs") or (
                isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 1_000_000)
        if not ok:
            raise bad(f"scale_sizes.{key}", f"{value!r} is not a value a run can have")


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def record_scale(meta: dict) -> Scale:
    """The scale the recorded run ran at (its command line's overrides included)."""
    sizes = dict(meta["scale_sizes"])
    if sizes.get("curve_densities") is not None:
        sizes["curve_densities"] = tuple(sizes["curve_densities"])
    return Scale(**sizes)


def restorable_files(record: Path, *, with_dataset: bool) -> list[str]:
    """The files :func:`restore_record` copies, every one checked (regular, inside the record) before any is: a
    :class:`RecordError` for the first that is not."""
    meta = read_record(record)
    chosen = []
    for rel in meta["files"]:
        parts = Path(rel).parts
        if ".." in parts or Path(rel).is_absolute():
            raise RecordError(f"{record / RECORD_JSON}: file {rel!r} lies outside the record")
        if parts[0] == "dataset" and not with_dataset:
            continue
        src = record / rel
        if not src.is_file():
            raise RecordError(f"{record / RECORD_JSON}: lists {rel}, which the record does not have")
        if any(p.is_symlink() for p in (src, *src.parents) if record in p.parents or p == src):
            raise RecordError(f"{src}: a symbolic link; a record is restored only from regular files inside it")
        if not src.resolve().is_relative_to(record.resolve()):
            raise RecordError(f"{src}: lies outside the record")
        if src.suffix == ".json":
            # parsed here (size and depth capped, UTF-8) so that a malformed one refuses the record before any file is
            # copied, not in the step that reads it after the work folder was filled
            load_json(src, "run record file", max_bytes=max(MAX_FILE_BYTES, 16 << 20))
        chosen.append(rel)
    return chosen


def restore_record(record: Path, out: Path, *, with_dataset: bool) -> list[str]:
    """Copy the record's files into work folder ``out`` where ``out`` lacks them (the recorded steps then count as
    done); the dataset's manifest and ImageSets only ``with_dataset`` (a run that regenerates the dataset must not find
    a manifest that marks it generated). The paths restored; a refused record restores nothing."""
    restored = []
    for rel in restorable_files(record, with_dataset=with_dataset):
        src, dst = record / rel, out / rel
        if not dst.exists():
            write_bytes(dst, src.read_bytes())
            restored.append(rel)
    return restored


def check_dataset(record: Path, dataset: Path) -> None:
    """Raise :class:`RecordError` unless ``dataset`` is byte for byte the dataset the record was made from."""
    want = read_record(record).get("dataset_sha256")
    got = dataset_fingerprint(dataset)
    if want and got and want != got:
        raise RecordError(f"{dataset} is not the dataset of the record {record} (sha256 {got[:12]} vs the record's "
                          f"{want[:12]}): the code or the seed that made it differs, so steps run on it would not "
                          "belong to the recorded run; run the whole reproduction instead")
