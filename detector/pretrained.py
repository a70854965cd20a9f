"""Trained weights by name: ``--checkpoint pretrained:sparse`` (``:dense``, ``:sparse_exact``) without a training and
without network access.

The weights ship as package data in ``detector/pretrained/``: one checkpoint file per trained model (the model's state
dict in half precision, no optimiser state, with the experiment config it was trained with, read by
:func:`detector.checkpoint.load_checkpoint`, i.e. ``torch.load(weights_only=True)``) and ``index.json``, which maps each
name to its file, the packaged config to use it with and the file's SHA-256::

    {"format": 1, "weights": {"sparse": {"file": "sparse.pt", "config": "mpchair_sparse_cpu", "sha256": "..."},
                              "sparse_exact": {"file": "sparse.pt", "config": "mpchair_sparse_exact_cpu", ...}}}

:func:`detector.checkpoint.pack_pretrained` writes both from a training's ``last.pt`` (``tools/pack_pretrained.py``
is its front-end). A name the index does not list is a one-line :class:`InputError` saying where the files go and how
to make them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

from mpchair.core.atomic import write_text
from mpchair.core.config import package_folder
from mpchair.core.errors import InputError

#: What ``--checkpoint`` starts with to name packaged weights instead of a file.
PREFIX = "pretrained:"
#: The names the paper's models are published under (the index may list fewer until their weights are committed).
NAMES = ("dense", "sparse", "sparse_exact")
#: Folder of the packaged weights and their index (``detector/pretrained``, package data: also in an installed wheel).
PRETRAINED_DIR = package_folder("detector", "pretrained")
INDEX_FILE = "index.json"
INDEX_FORMAT = 1
#: Largest index read (a few names; a bigger file is not an index).
MAX_INDEX_BYTES = 1 << 16


@dataclasses.dataclass(frozen=True)
class PretrainedEntry:
    """One name of ``index.json``: the weights ``file`` (in the index's folder), the packaged ``config`` (name) to use
    them with, and the file's ``sha256`` (hex)."""

    file: str
    config: str
    sha256: str

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: object, source: str, name: str) -> PretrainedEntry:
        keys = [f.name for f in dataclasses.fields(cls)]
        well_formed = isinstance(data, dict) and sorted(data) == sorted(keys)
        if not well_formed or not all(isinstance(v, str) for v in data.values()):
            raise InputError(f"weights.{name}: expected strings {', '.join(keys)}", source)
        if Path(data["file"]).name != data["file"]:
            raise InputError(f"weights.{name}.file: a file name in the index's folder, got {data['file']!r}", source)
        return cls(**data)


def is_pretrained(checkpoint: str | Path | None) -> bool:
    """Whether a ``--checkpoint`` value names packaged weights (``pretrained:NAME``) rather than a file."""
    return checkpoint is not None and str(checkpoint).startswith(PREFIX)


def read_index(folder: Path | None = None) -> dict[str, PretrainedEntry]:
    """The names listed in ``folder/index.json`` (default :data:`PRETRAINED_DIR`; none when the file is absent); a
    malformed index is an :class:`InputError` naming it."""
    path = Path(folder or PRETRAINED_DIR) / INDEX_FILE
    if not path.is_file():
        return {}
    if path.stat().st_size > MAX_INDEX_BYTES:
        raise InputError(f"larger than {MAX_INDEX_BYTES} bytes: not a weights index", path)
    try:
        data = json.loads(path.read_bytes())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"not a JSON weights index ({e})", path) from None
    if not isinstance(data, dict) or data.get("format") != INDEX_FORMAT or not isinstance(data.get("weights"), dict):
        raise InputError(f"not a weights index (expected {{\"format\": {INDEX_FORMAT}, \"weights\": {{...}}}})", path)
    return {name: PretrainedEntry.from_json(entry, str(path), name) for name, entry in data["weights"].items()}


def resolve_checkpoint(checkpoint: str | Path, folder: Path | None = None) -> Path:
    """The file of a ``--checkpoint`` value: ``pretrained:NAME`` → the weights in ``folder`` (default
    :data:`PRETRAINED_DIR`), checked against the index's SHA-256; anything else → that path unchanged."""
    if not is_pretrained(checkpoint):
        return Path(checkpoint)
    folder = Path(folder or PRETRAINED_DIR)
    name = str(checkpoint)[len(PREFIX):]
    index = read_index(folder)
    if name not in index:
        listed = ", ".join(sorted(index)) or "none yet"
        raise InputError(f"no pretrained weights {name!r} in this install (installed: {listed}; published names: "
                         f"{', '.join(NAMES)}): put the packed file and its index.json in {folder} "
                         "(tools/pack_pretrained.py packs a training's last.pt), or train one (detector train "
                         "--config mpchair_sparse_cpu ...) and pass --checkpoint RUN/last.pt")
    path = Path(folder) / index[name].file
    if not path.is_file():
        raise InputError(f"pretrained weights {name!r}: {index[name].file} is listed in {INDEX_FILE} but missing",
                         path)
    if _sha256(path) != index[name].sha256:
        raise InputError(f"pretrained weights {name!r}: the file's SHA-256 differs from {INDEX_FILE}'s (damaged or "
                         "replaced; pack it again)", path)
    return path


def add_to_index(folder: Path, weights: Path, names: dict[str, str]) -> None:
    """List the weights file ``weights`` (in ``folder``) in ``folder/index.json`` under each of ``names`` (name → the
    packaged config to use it with), with its SHA-256; the index's other names are kept."""
    index = read_index(folder)
    digest = _sha256(weights)
    index.update({name: PretrainedEntry(file=weights.name, config=cfg, sha256=digest) for name, cfg in names.items()})
    doc = {"format": INDEX_FORMAT, "weights": {n: index[n].to_json() for n in sorted(index)}}
    write_text(Path(folder) / INDEX_FILE, json.dumps(doc, indent=1) + "\n")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
