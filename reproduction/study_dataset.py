"""Is a regenerated dataset the accuracy study's dataset? Byte identity, or equivalence shown and recorded.

The study's record holds the sha256 of the dataset it was started on (``dataset_sha256``, :func:`dataset_fingerprint`
over ``training/`` and ``ImageSets/``). The same code, houses and seed give those bytes on one class of CPU, but not
across classes: on an AVX-512 EPYC the regenerated dataset has the recorded manifest (every total: frames, points,
boxes kept and rejected per reason), the recorded splits and the recorded test labels, yet a different fingerprint
(float bits of points / poses that depend on the CPU's instruction set; docs/generate.md, "Determinism"). A training
that continues on such a machine would then be refused for good.

So a session may **accept** a different fingerprint (``tools/accuracy_study.py --accept-dataset``), only when
:func:`equivalence_problems` finds none: the manifest (less its frame list) equal to the record's, every ImageSets file
equal, and every test label file equal to the record's ``test_labels.zip``. The accepted fingerprint is recorded
under ``dataset_equivalents`` with the machine it came from, the evidence, and per-part hashes of its files
(:func:`dataset_parts`: one sha256 per file kind and house, so the next mismatch can be located); later sessions on
that class of machine then match it without the flag.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from mpchair.core.cpu import cpu_flags


def cpu_description() -> str:
    """The CPU in a few words (model name and its widest vector ISA), for the record's notes."""
    from detector.device import cpu_model

    flags = cpu_flags()
    isa = ("AVX512-BF16" if "avx512_bf16" in flags else "AVX-512" if "avx512f" in flags
           else "AVX2 only" if "avx2" in flags else "no AVX2")
    return f"{cpu_model()} ({isa})"


def dataset_parts(dataset: Path) -> dict[str, str]:
    """sha256 (first 16 hex digits) of each file kind per house, ``"<kind>/<house>"`` -> digest: the files of
    ``training/<kind>/`` whose frame ids the manifest gives the house, in frame order (path and bytes)."""
    manifest = json.loads((dataset / "manifest.json").read_text())
    parts = {}
    for kind in sorted(p.name for p in (dataset / "training").iterdir() if p.is_dir()):
        files = {p.stem: p for p in (dataset / "training" / kind).iterdir() if p.is_file()}
        for house, entry in sorted(manifest.get("houses", {}).items()):
            lo, hi = entry["frames"]
            h = hashlib.sha256()
            for g in range(lo, hi + 1):
                p = files.get(f"{g:06d}")
                if p is not None:
                    h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
            parts[f"{kind}/{house}"] = h.hexdigest()[:16]
    return parts


def equivalence_problems(dataset: Path, record: Path, test_labels: dict[str, str]) -> list[str]:
    """Why ``dataset`` is not the recorded one beyond float bits ([] when it is equivalent): the manifest less its
    frame list against the record's, each recorded ImageSets file, each recorded test label (``test_labels``: frame
    id -> text, from the record's ``test_labels.zip``)."""
    problems = []
    mine = json.loads((dataset / "manifest.json").read_text())
    frames = mine.pop("frames", [])
    mine["frames_left_out_of_the_record"] = len(frames)
    theirs = json.loads((record / "dataset" / "manifest.json").read_text())
    for key in sorted(set(mine) | set(theirs)):
        if mine.get(key) != theirs.get(key):
            problems.append(f"manifest.json: {key!r} differs")
    for p in sorted((record / "dataset" / "ImageSets").glob("*.txt")):
        q = dataset / "ImageSets" / p.name
        if not q.is_file() or q.read_bytes() != p.read_bytes():
            problems.append(f"ImageSets/{p.name} differs")
    if not test_labels:
        problems.append("the record has no test labels to compare")
    differ = [i for i, text in sorted(test_labels.items())
              if not (dataset / "training" / "label_2" / f"{i}.txt").is_file()
              or (dataset / "training" / "label_2" / f"{i}.txt").read_text() != text]
    if differ:
        problems.append(f"{len(differ)} of {len(test_labels)} test label files differ (first {differ[0]}.txt)")
    return problems


def accepted(meta: dict, fingerprint: str) -> bool:
    """Whether the study record ``meta`` (record.json) takes a dataset of sha256 ``fingerprint``: its own, or one
    accepted as equivalent by an earlier session."""
    equivalents = meta.get("dataset_equivalents") or {}
    return fingerprint == meta.get("dataset_sha256") or (isinstance(equivalents, dict) and fingerprint in equivalents)
