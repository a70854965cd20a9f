"""Typed readers of what the streaming reproduction's report reads: ``detector stream-eval --json-out`` summaries (and
the measuring run's ``measure.json``, a summary too) and ``mpchair stream``'s ``stream.json``. AP in percent, times
in milliseconds; a file that does not exist reads as None, a key a summary lacks as None."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from detector.device import Machine
from mpchair.core.atomic import write_text
from mpchair.core.errors import InputError
from mpchair.core.text import load_json
from mpchair.dataset.manifest import read_manifest
from reproduction.checkout import ROOT
from reproduction.stream.sweep import HEADLINE, MODELS, MODES, Setting, eval_dir, stream_dir, stream_name

#: (model or ``oracle@<model>``, speed m/s, rate Hz, setting name, mode ``raw`` / ``ego``) of one scored run.
RunKey = tuple[str, float, float, str, str]


@dataclass(frozen=True)
class Stats:
    """Summary statistics of one per-frame quantity (None: not in the summary)."""

    mean: float | None = None
    median: float | None = None
    p95: float | None = None

    @classmethod
    def from_json(cls, d: dict | None) -> Stats:
        d = d or {}
        return cls(mean=d.get("mean"), median=d.get("median"), p95=d.get("p95"))


def _chair_r40(block: dict | None) -> Mapping[str, float] | None:
    """Chair's AP R40 by metric (``3d``, ``bev``) of an AP block of a summary, None when it was not scored."""
    if block is None:
        return None
    return {k: v.get("R40") for k, v in block["Chair"].items() if isinstance(v, dict)}


@dataclass(frozen=True)
class StreamSummary:
    """One ``detector stream-eval --json-out`` summary: streaming AP (``sap``) and offline AP (every frame through the
    model; None when not computed) as Chair's R40 by metric; latency, staleness (ms and frames), the fraction of
    frames processed; the latency repeats and the machine when the latencies were measured here (else None)."""

    sap: Mapping[str, float] | None
    offline_ap: Mapping[str, float] | None
    latency_ms: Stats
    staleness_ms: Stats
    staleness_frames: Stats
    frames_processed: float
    repeats: int | None = None
    machine: Machine | None = None

    @classmethod
    def from_json(cls, d: dict, machine: dict | None = None) -> StreamSummary:
        """``machine``: the measuring run's machine, for a summary scored from its saved outputs (which has none)."""
        found = d.get("machine", machine)
        return cls(sap=_chair_r40(d.get("sAP")), offline_ap=_chair_r40(d.get("offline_AP")),
                   latency_ms=Stats.from_json(d.get("latency_ms")), staleness_ms=Stats.from_json(d.get("staleness_ms")),
                   staleness_frames=Stats.from_json(d.get("staleness_frames")),
                   frames_processed=d.get("frames_processed"), repeats=d.get("repeats"),
                   machine=Machine.from_json(found) if found else None)

    def ap(self, metric: str = "3d", offline: bool = False) -> float | None:
        """sAP (or, ``offline``, the offline AP) of ``metric``, R40; None when not scored."""
        block = self.offline_ap if offline else self.sap
        return None if block is None else block.get(metric)


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def read_summary(path: Path, machine: dict | None = None) -> StreamSummary | None:
    """The stream-eval summary in ``path`` (None when absent); ``machine`` as in :meth:`StreamSummary.from_json`."""
    d = _read_json(path)
    return None if d is None else StreamSummary.from_json(d, machine)


def read_runs(out: Path, points: list[tuple[float, float]], settings: list[Setting]) -> dict[RunKey, StreamSummary]:
    """Every scored run of work folder ``out``: each model on each point's stream under each setting in each mode
    (with the machine its latencies were measured on), then the oracle at each model's latency under each setting on
    the headline stream (``oracle@<model>``)."""
    runs: dict[RunKey, StreamSummary] = {}
    for v, f in points:
        for s in settings:
            for m in MODELS:
                ev = eval_dir(out, v, f, s, m)
                measured = _read_json(ev / "measure.json")
                for mode in MODES:
                    summary = read_summary(ev / f"{mode}.json", (measured or {}).get("machine"))
                    if summary is not None:
                        runs[(m, v, f, s.name, mode)] = summary
    for s in settings:
        for m in MODELS:
            for mode in MODES:
                summary = read_summary(eval_dir(out, *HEADLINE, s, f"oracle-at-{m}") / f"{mode}.json")
                if summary is not None:
                    runs[(f"oracle@{m}", *HEADLINE, s.name, mode)] = summary
    return runs


def read_measure(out: Path, setting: Setting, model: str) -> StreamSummary | None:
    """The measuring run's own summary of ``model`` under ``setting`` on the headline stream (its latencies, the
    offline AP where it ran the offline pass), None when absent."""
    return read_summary(eval_dir(out, *HEADLINE, setting, model) / "measure.json")


def stream_frames(out: Path, points: list[tuple[float, float]]) -> dict[str, int]:
    """Frames of each point's stream that exists (its ``stream.json`` totals), by stream folder name."""
    found = {}
    for v, f in points:
        meta = _read_json(stream_dir(out, v, f) / "stream.json")
        if meta is not None:
            found[stream_name(v, f)] = meta["totals"]["frames"]
    return found


# --- which houses the streams drive through, and whether the models were trained on them ------------------------------
@dataclass(frozen=True)
class HouseCheck:
    """The streamed houses (ids, from the headline stream's stream.json) against a training dataset: its houses with a
    train or val frame (``trained``), which streamed houses share an id or every file's checksum with one of them
    (``overlap``), and the dataset folder (None: not found, nothing checked)."""

    streamed: tuple[str, ...]
    trained: tuple[str, ...]
    overlap: tuple[str, ...]
    dataset: Path | None

    def to_json(self) -> dict:
        return {"streamed": list(self.streamed), "trained": list(self.trained), "overlap": list(self.overlap),
                "dataset": None if self.dataset is None else str(self.dataset)}

    @classmethod
    def from_json(cls, d: dict) -> HouseCheck:
        """The check of :meth:`to_json`'s data."""
        return cls(streamed=tuple(d["streamed"]), trained=tuple(d["trained"]), overlap=tuple(d["overlap"]),
                   dataset=None if d.get("dataset") is None else Path(d["dataset"]))


def trained_houses(dataset: Path) -> dict[str, dict[str, str]] | None:
    """{house id: {file: sha256}} of the houses of ``mpchair generate``'s dataset folder that have a frame in its
    train or val split (from manifest.json's per-house frame ranges and ImageSets); None without a manifest."""
    from mpchair.kitti import imageset_path, read_imageset

    manifest = read_manifest(dataset, frames=False)
    if manifest is None:
        return None
    used = {int(i) for split in ("train", "val") if imageset_path(dataset, split).is_file()
            for i in read_imageset(imageset_path(dataset, split))}
    found = {}
    for hid, h in manifest.houses.items():
        first, last = h.frames
        if any(first <= i <= last for i in used):
            found[hid] = dict(h.files_sha256)
    return found


def check_houses(stream: Path, dataset: Path) -> HouseCheck | None:
    """:class:`HouseCheck` of stream folder ``stream`` (None without its stream.json) against training dataset
    ``dataset``."""
    meta = _read_json(stream / "stream.json")
    if meta is None:
        return None
    houses = meta.get("houses") or {}
    streamed = tuple(houses)
    trained = trained_houses(dataset)
    if trained is None:
        return HouseCheck(streamed, (), (), None)
    same_files = {frozenset(files.values()) for files in trained.values()}  # a house is its files' contents
    overlap = tuple(h for h in streamed if h in trained
                    or frozenset((houses[h].get("files_sha256") or {}).values()) in same_files)
    return HouseCheck(streamed, tuple(trained), overlap, dataset)


#: The held-out check as the report made it (kept in the record: a later report has no training dataset to check).
HOUSE_CHECK_JSON = "house_check.json"


def house_check(out: Path, dataset: Path) -> HouseCheck | None:
    """:func:`check_houses` of work folder ``out``'s headline stream against ``dataset`` when both are there (and
    written to ``out/house_check.json`` for the record), else the check a run made before (restored from a record),
    else None."""
    saved = out / HOUSE_CHECK_JSON
    stream = stream_dir(out, *HEADLINE)
    if (stream / "stream.json").is_file() and ((dataset / "manifest.json").is_file() or not saved.is_file()):
        check = check_houses(stream, dataset)
        if check is not None:
            d = check.to_json()
            if check.dataset is not None:
                d["dataset"] = _relative(check.dataset)
            write_text(saved, json.dumps(d, indent=1) + "\n")
        return check
    if saved.is_file():
        try:
            return HouseCheck.from_json(load_json(saved, "held-out house check"))
        except (AttributeError, KeyError, TypeError) as e:
            raise InputError(f"not a held-out house check ({type(e).__name__}: {e})", saved) from None
    return None


def _relative(path: Path) -> str:
    """``path`` relative to the checkout when it lies in it (a record reads the same in every clone)."""
    path = path.resolve()
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)
