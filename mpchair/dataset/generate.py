"""``mpchair generate`` as a library call: houses in, a KITTI-format Matterport-Chair dataset out.

Layout written under ``out``::

    training/{velodyne,label_2,calib,image_2,pose}/NNNNNN.*   one frame each (see mpchair.dataset.frame)
    ImageSets/{train,val,test}.txt                          written when every frame exists
    manifest.json                                           written last
    .frames/NNNNNN.json                                     per-frame records (a frame is done iff its record exists)
    .generate.json                                          the run's settings; a re-run must match them

Determinism: frame ``g`` (global id = house position * frames + index) depends only on ``(seed, house, index)`` and
the settings, never on ``workers`` or ``shard``; every file is written atomically; the manifest holds no times and no
absolute paths. So an interrupted run (even SIGKILL) re-run with the same arguments resumes and ends byte-identical to
an uninterrupted one, and ``--shard i/N`` jobs (the contiguous block of frames :func:`shard_frames`, so that a job
touches few houses and builds few raycast scenes) can fill one folder in any order: the job that finds every frame
present writes ImageSets and the manifest.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fnmatch
import hashlib
import json
import math
import os
import platform
import re
import shutil
import sys
import time
from collections import Counter
from importlib import metadata
from pathlib import Path

import numpy as np

from mpchair import __version__
from mpchair.core.atomic import temp_glob, write_text
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError, RunError
from mpchair.core.heap import keep_freed_memory
from mpchair.core.lock import folder_lock, held, wait_lock
from mpchair.dataset.frame import (
    FrameSettings,
    build_context,
    frame_rng,  # noqa: F401  (re-exported for callers that reproduce one frame's viewpoint)
    make_frame,
    record_path,
    resolve_viewpoints,
    viewpoint_sampler,
    warm_up,
    write_frame,
)
from mpchair.dataset.splits import split_frames
from mpchair.dataset.workers import WorkerDied, imap_unordered
from mpchair.kitti import write_imageset
from mpchair.matterport.categories import mpcat40_name, resolve_categories
from mpchair.matterport.house import House, objects_of, read_house
from mpchair.matterport.source import SUFFIXES, HouseSource, find_houses
from mpchair.scan.sensors import SensorConfig, load_sensor, scan_directions
from mpchair.scan.viewpoints import ViewpointParams

MANIFEST_FORMAT = "mpchair-kitti/1"
#: Frame ids are 6 digits (KITTI file names).
MAX_FRAMES = 1_000_000
SPLIT_MODES = ("frame", "house", "paper")
SETTINGS_FILE = ".generate.json"
_LOCK_NAME = re.compile(r"\.generate-(\d+)-of-(\d+)\.lock")
FRAME_DIRS = ("velodyne", "label_2", "calib", "image_2", "pose")


@dataclasses.dataclass(frozen=True)
class GenerateRequest:
    """Arguments of one ``generate`` run. ``frames`` is per house; ``shard`` is ``(i, N)``; ``sensor`` a profile name
    or YAML path; ``height`` / ``robot_radius`` metres; ``categories`` mpcat40 names or indices; ``viewpoints``
    where candidates come from (``auto``: a house's navmesh when it has one, else ``regions``; or ``navmesh``)."""

    root: Path
    houses: tuple[str, ...]
    frames: int
    out: Path
    sensor: str = "mp3d-depth90"
    seed: int = 0
    height: float = 1.0
    robot_radius: float = 0.25
    categories: tuple[str, ...] = ("chair",)
    keep_empty: bool = False
    split_mode: str = "frame"
    backend: str = "embree"
    workers: int = 1
    shard: tuple[int, int] = (0, 1)
    max_attempts: int = 400
    progress: bool = True
    viewpoints: str = "auto"


@dataclasses.dataclass(frozen=True)
class GenerateSummary:
    """What a run did and what the folder holds: ``frames`` in the dataset, ``made`` by this run, ``resumed``
    (already present), ``complete`` (manifest written), ``nothing_to_make`` (every frame of this run was already
    there), ``seconds`` wall time and ``frames_per_second`` of the frames made now.

    ``scope`` says what the counts describe: ``"dataset"`` (complete: every frame, as the manifest lists them) or
    ``"shard"`` (other shards pending: this shard's frames, made now or before). Counts: boxes ``kept`` (and
    ``kept_by_class``, mpcat40 name), ``rejected`` by reason, mean ``points`` per frame, ``rays`` cast, ``splits``
    sizes (complete only)."""

    out: str
    frames: int
    made: int
    resumed: int
    complete: bool
    nothing_to_make: bool
    scope: str
    kept: int
    kept_by_class: dict[str, int]
    rejected: dict[str, int]
    points: float
    rays: int
    seconds: float
    frames_per_second: float
    splits: dict[str, int]

    def line(self) -> str:
        """One-line human summary."""
        rej = ", ".join(f"{k} {v}" for k, v in sorted(self.rejected.items())) or "none"
        classes = ", ".join(f"{k} {v}" for k, v in sorted(self.kept_by_class.items()))
        state = "complete" if self.complete else "incomplete: other shards pending"
        if self.nothing_to_make:
            run = f"nothing needed to be made ({self.resumed} frames already there)"
        else:
            run = (f"this run made {self.made} in {self.seconds:.1f} s ({self.frames_per_second:.1f} frames/s), "
                   f"resumed {self.resumed}")
        scope = "" if self.scope == "dataset" else "this shard's frames: "
        splits = ("; splits " + " ".join(f"{k} {v}" for k, v in self.splits.items())) if self.splits else ""
        return (f"{self.out}: {self.frames} frames ({state}); {run}; {scope}boxes kept {self.kept}"
                + (f" ({classes})" if classes else "") + f", rejected: {rej}; {self.points:.0f} points/frame{splits}")


def describe_records(records: list[dict]) -> dict:
    """Counts over frame records (``.frames/*.json``, the manifest's ``frames``): ``kept``, ``kept_by_class``,
    ``rejected`` (by reason, sorted), ``points`` (mean per frame), ``rays`` (sum)."""
    return {
        "kept": sum(len(r["kept"]) for r in records),
        "kept_by_class": dict(sorted(Counter(k["class"] for r in records for k in r["kept"]).items())),
        "rejected": dict(sorted(Counter(k["reason"] for r in records for k in r["rejected"]).items())),
        "points": float(np.mean([r["points"] for r in records])) if records else 0.0,
        "rays": int(sum(r["rays"] for r in records)),
    }


def sha256_of(source: HouseSource, suffix: str) -> str:
    """Hex sha256 of one house file's bytes (``suffix`` like ``.house``)."""
    return hashlib.sha256(source.read_bytes(suffix)).hexdigest()


def _versions(backend: str) -> dict[str, str]:
    out = {"mpchair": __version__, "python": platform.python_version()}
    names = ["numpy", "trimesh", "embreex", "shapely", "pillow"] + (["open3d-cpu", "open3d"] if backend == "open3d"
                                                                    else [])
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def _settings(req: GenerateRequest, sensor: SensorConfig, params: ViewpointParams, cats: list[str]) -> dict:
    """The deterministic part of a run (what the output depends on); stored in ``.generate.json``."""
    return {
        "houses": list(req.houses),
        "frames_per_house": req.frames,
        "sensor": to_dict(sensor),
        "viewpoints": to_dict(params),
        "seed": req.seed,
        "categories": cats,
        "keep_empty": req.keep_empty,
        "split_mode": req.split_mode,
        "backend": req.backend,
        "max_attempts": req.max_attempts,
    }


# Per-process state of pool workers (fork start method: inherited from the parent, never pickled).
_STATE: dict = {}


def _init_state(houses: dict[str, House], settings: FrameSettings, cats: frozenset[int], backend: str,
                out: Path) -> None:
    _STATE.clear()
    _STATE.update(houses=houses, settings=settings, cats=cats, backend=backend, out=out, ctx={},
                  dirs=scan_directions(settings.sensor))


def _init_worker(*args) -> None:
    """Pool initializer: a worker process only makes frames, so it keeps freed memory (``mpchair.core.heap``)."""
    keep_freed_memory()
    _init_state(*args)


def _work(task: tuple[int, str, int]) -> dict:
    """Make and write one frame (runs in a worker or in-process); returns its record."""
    g, house_id, index = task
    ctx = _STATE["ctx"].get(house_id)
    if ctx is None:  # the scene is built once per house and process, then reused for all its frames
        ctx = build_context(_STATE["houses"][house_id], _STATE["cats"], _STATE["backend"],
                            _STATE["settings"].sensor.filters.box_margin, _STATE["settings"].viewpoint_source)
        _STATE["ctx"][house_id] = ctx
    settings: FrameSettings = _STATE["settings"]
    result = make_frame(ctx, settings, index, _STATE["dirs"])
    return write_frame(_STATE["out"], f"{g:06d}", ctx.house, index, result, settings.sensor)


def _remove_stale_temps(out: Path, fids: set[str]) -> None:
    """Delete temp files (``.<name>.*.tmp``) a killed run left for frames this run owns."""
    for sub in [out / "training" / d for d in FRAME_DIRS] + [out / ".frames"]:
        if not sub.is_dir():
            continue
        for p in sub.iterdir():
            if p.name.startswith(".") and p.name.endswith(".tmp") and p.name[1:7] in fids:
                p.unlink(missing_ok=True)


def _shard_lock(out: Path, shard: tuple[int, int]) -> Path:
    return out / f".generate-{shard[0]}-of-{shard[1]}.lock"


def _others_running(out: Path, shard: tuple[int, int]) -> list[tuple[int, int]]:
    """Shards ``(i, N)`` of other live ``generate`` processes on ``out`` (their lock files are held)."""
    files = {}
    for p in out.glob(".generate-*-of-*.lock"):
        m = _LOCK_NAME.fullmatch(p.name)
        if m and (int(m.group(1)), int(m.group(2))) != tuple(shard):
            files[p] = (int(m.group(1)), int(m.group(2)))
    return sorted(files[p] for p in held(list(files)))


def _is_ours(name: str) -> bool:
    """Files a run of ours may leave in a folder without a settings file: its lock files and a killed settings write."""
    return bool(_LOCK_NAME.fullmatch(name)) or fnmatch.fnmatchcase(name, temp_glob(SETTINGS_FILE))


def _has_records(out: Path) -> bool:
    d = out / ".frames"
    return d.is_dir() and any(p.suffix == ".json" and not p.name.startswith(".") for p in d.iterdir())


def _check_settings(out: Path, settings: dict, alone: bool) -> None:
    """Write ``.generate.json`` into a new folder, or check that an existing one holds these settings.

    A folder whose settings differ but that holds no frame record yet (a run stopped before its first frame) takes
    the new settings when no other ``generate`` is running on it. ``alone``: no other shard's process holds a lock.
    """
    path = out / SETTINGS_FILE
    text = json.dumps(settings, sort_keys=True, indent=1) + "\n"
    if alone:  # temp files of a killed settings write (another live shard may be writing its own right now)
        for p in out.glob(temp_glob(SETTINGS_FILE)):
            p.unlink(missing_ok=True)
    if path.is_file():
        old_text = path.read_text(encoding="utf-8")
        if old_text == text:
            return
        if not (alone and not _has_records(out)):
            try:
                old = json.loads(old_text)
                diff = ", ".join(sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k)))
            except (json.JSONDecodeError, AttributeError):
                diff = "the file is not a settings object"
            raise InputError(f"holds a dataset made with other settings ({diff} differ); use a new --out or the same "
                             "arguments to resume", path)
    elif any(not _is_ours(p.name) for p in out.iterdir()):
        raise InputError("exists and is not an mpchair dataset folder (no .generate.json); choose an empty --out",
                         out)
    write_text(path, text)


def _undo(out: Path, fids: set[str], existed: bool, shard: tuple[int, int]) -> None:
    """Remove what a run that could not make its frames wrote into a folder that held no frame before it: its frames'
    files, then (when no other shard runs and no frame is left) the settings and the folders it created."""
    for sub in [out / "training" / d for d in FRAME_DIRS] + [out / ".frames"]:
        if sub.is_dir():
            for p in sub.iterdir():
                if p.name.split(".")[0] in fids or (p.name.startswith(".") and p.name[1:7] in fids):
                    p.unlink(missing_ok=True)
    if _has_records(out) or _others_running(out, shard):
        return
    (out / SETTINGS_FILE).unlink(missing_ok=True)
    for d in [out / "training" / d for d in FRAME_DIRS] + [out / "training", out / ".frames"]:
        with contextlib.suppress(OSError):
            d.rmdir()  # only if empty
    if not existed and not any(not _is_ours(p.name) for p in out.iterdir()):
        shutil.rmtree(out, ignore_errors=True)


def _check_numbers(req: GenerateRequest) -> None:
    """Every number of the request finite and in range, before anything is read or written."""
    if req.frames < 1:
        raise InputError(f"--frames must be >= 1, got {req.frames}")
    if not req.houses:
        raise InputError("give at least one --house")
    if len(set(req.houses)) != len(req.houses):
        raise InputError("a --house is repeated")
    if len(req.houses) * req.frames > MAX_FRAMES:
        raise InputError(f"{len(req.houses)} houses x --frames {req.frames} exceeds {MAX_FRAMES} frames (6-digit "
                         "KITTI frame ids)")
    if req.workers < 1:
        raise InputError(f"--workers must be >= 1, got {req.workers}")
    if req.max_attempts < 1:
        raise InputError(f"--max-attempts must be >= 1, got {req.max_attempts}")
    if req.seed < 0:
        raise InputError(f"--seed must be >= 0, got {req.seed}")
    si, sn = req.shard
    if not (sn >= 1 and 0 <= si < sn):
        raise InputError(f"--shard must be i/N with 0 <= i < N, got {si}/{sn}")
    if not (math.isfinite(req.height) and req.height > 0):
        raise InputError(f"--height must be a finite number > 0 (metres), got {req.height}")
    if not (math.isfinite(req.robot_radius) and req.robot_radius >= 0):
        raise InputError(f"--robot-radius must be a finite number >= 0 (metres), got {req.robot_radius}")
    if req.split_mode not in SPLIT_MODES:
        raise InputError(f"--split-mode must be one of {', '.join(SPLIT_MODES)}, got {req.split_mode!r}")
    if req.split_mode == "house" and len(req.houses) < 3:
        raise InputError(f"--split-mode house needs at least 3 houses, got {len(req.houses)}")


def generate(req: GenerateRequest) -> GenerateSummary:
    """Generate (or resume) the dataset described by ``req``; see the module docstring.

    Bad input (a number out of range; unknown house: the available ones are listed; house without objects of the
    class; unknown sensor; an ``out`` made with other settings or holding other files) raises :class:`InputError`
    before anything is written. Frames that cannot be made with these settings (no valid viewpoint: the cause is
    named) raise :class:`InputError` when the first failing frame is reached; a run that started on a folder without
    frames then removes what it wrote, so the corrected command starts afresh. Another process on the same shard
    of ``out`` is an :class:`InputError`; a dead worker process (or another error inside one) a :class:`RunError`; an
    ``OSError`` (full disk) propagates with a hint to resume. After any of the last three, and after SIGKILL, the same
    request resumes.
    """
    t0 = time.perf_counter()
    _check_numbers(req)
    si, sn = req.shard
    sensor = load_sensor(req.sensor)
    params = ViewpointParams(height=req.height, robot_radius=req.robot_radius)
    cat_idx = resolve_categories(list(req.categories))
    cats = sorted(mpcat40_name(c) for c in cat_idx)

    found = find_houses(req.root)
    unknown = [h for h in req.houses if h not in found]
    if unknown:
        raise InputError(f"unknown house {unknown[0]!r} (available: {', '.join(sorted(found))})", req.root)
    houses: dict[str, House] = {}
    hashes: dict[str, dict[str, str]] = {}
    sources: dict[str, str] = {}
    for hid in req.houses:
        house = read_house(found[hid], navmesh=req.viewpoints != "regions")
        if not objects_of(house, cat_idx):
            have = ", ".join(f"{k} {v}" for k, v in house.objects_by_category().items()) or "no objects"
            raise InputError(f"house {hid} has no object of class {', '.join(cats)} (it has: {have})",
                             found[hid].describe(".house"))
        sources[hid] = resolve_viewpoints(house, req.viewpoints)
        viewpoint_sampler(house, sources[hid])  # a navmesh without a large enough island fails here, not in a frame
        houses[hid] = house
        src = found[hid]
        used = [s for s in SUFFIXES[src.layout] if s != ".navmesh"] + [".navmesh"] * (sources[hid] == "navmesh")
        hashes[hid] = {f"{hid}{s}": sha256_of(src, s) for s in used if src.exists(s)}

    out = Path(req.out)
    settings = _settings(req, sensor, params, cats)
    if "navmesh" in sources.values():  # only then: regions-only runs keep the settings (and resume) they had
        settings["viewpoint_sources"] = sources
    fs = FrameSettings(sensor=sensor, viewpoints=params, seed=req.seed, keep_empty=req.keep_empty,
                       max_attempts=req.max_attempts, viewpoint_source=req.viewpoints)
    existed = out.exists()
    with folder_lock(_shard_lock(out, req.shard), f"mpchair generate --shard {si}/{sn}"):
        others = _others_running(out, req.shard)
        clash = [o for o in others if o[1] != sn]
        if clash:
            raise InputError(f"another mpchair generate (--shard {clash[0][0]}/{clash[0][1]}) is writing this folder; "
                             f"shards running at the same time must share N (here {sn})", out)
        _check_settings(out, settings, alone=not others)
        fresh = not _has_records(out)
        summary = _run(req, out, houses, hashes, fs, settings, cats, cat_idx, t0, fresh, existed)
    return summary


def _run(req: GenerateRequest, out: Path, houses: dict[str, House], hashes: dict, fs: FrameSettings, settings: dict,
         cats: list[str], cat_idx: frozenset[int], t0: float, fresh: bool, existed: bool) -> GenerateSummary:
    """Make this shard's missing frames, then (when every frame exists) ImageSets and the manifest."""
    sn = req.shard[1]
    n_total = len(req.houses) * req.frames
    tasks = [(hp * req.frames + i, hid, i) for hp, hid in enumerate(req.houses) for i in range(req.frames)]
    mine = [tasks[g] for g in shard_frames(n_total, req.shard)]
    pending = [t for t in mine if not record_path(out, f"{t[0]:06d}").is_file()]
    _remove_stale_temps(out, {f"{t[0]:06d}" for t in pending})
    resumed = len(mine) - len(pending)

    kept = rejected = 0  # shown on the progress bar (the summary counts come from the records afterwards)
    if pending:
        warm_up(fs.sensor)  # before forking: the workers inherit the loaded kernels
    t_frames = time.perf_counter()
    from tqdm import tqdm

    bar = tqdm(total=len(mine), initial=resumed, unit="frame", disable=not req.progress, file=sys.stderr,
               dynamic_ncols=True, desc="generate")

    def account(rec: dict) -> None:
        nonlocal kept, rejected
        kept += len(rec["kept"])
        rejected += len(rec["rejected"])
        bar.update(1)
        bar.set_postfix(kept=kept, rejected=rejected, refresh=False)

    resume = "the frames written so far are kept: run the same command again to resume"
    try:
        if req.workers == 1 or len(pending) <= 1:
            _init_state(houses, fs, cat_idx, req.backend, out)
            for task in pending:
                account(_work(task))
        else:
            # Forked workers inherit the parsed houses instead of re-reading them; chunks of 4 frames: one pipe round
            # trip per frame cost the parent ~1 ms of CPU per frame.
            for rec in imap_unordered(_work, pending, min(req.workers, len(pending)), initializer=_init_worker,
                                      initargs=(houses, fs, cat_idx, req.backend, out), chunksize=4):
                account(rec)
    except InputError:
        if fresh:  # these settings cannot make the dataset: leave the folder as it was for the corrected command
            _undo(out, {f"{t[0]:06d}" for t in pending}, existed, req.shard)
        raise
    except WorkerDied as e:
        raise RunError(f"{out}: {e}; stopped the other workers; {resume}") from None
    except OSError as e:
        raise _with_hint(e, resume) from None
    except Exception as e:
        if req.workers > 1 and len(pending) > 1:  # a worker's unexpected error: its traceback stayed in the worker
            raise RunError(f"{out}: a worker process failed: {type(e).__name__}: {e}; stopped the other workers; "
                           f"{resume}") from e
        raise
    finally:
        bar.close()
    made_seconds = time.perf_counter() - t_frames

    complete = all(record_path(out, f"{g:06d}").is_file() for g in range(n_total))
    splits_count: dict[str, int] = {}
    if complete:
        try:
            # Shards finishing together take turns (assembly removes temp files a killed assembly left).
            with wait_lock(out / ".generate-assemble.lock") if sn > 1 else contextlib.nullcontext():
                splits_count, records = _assemble(out, req, settings, hashes, houses, cats, n_total)
        except OSError as e:
            raise _with_hint(e, "the frames are kept: run the same command again to write ImageSets and the "
                                "manifest") from None
    else:  # this shard's frames, made now or by an earlier run
        records = [json.loads(record_path(out, f"{t[0]:06d}").read_text(encoding="utf-8")) for t in mine]
    seconds = time.perf_counter() - t0
    made = len(pending)
    return GenerateSummary(
        out=str(out), frames=n_total, made=made, resumed=resumed, complete=complete, nothing_to_make=not made,
        scope="dataset" if complete else "shard", **describe_records(records), seconds=seconds,
        frames_per_second=made / made_seconds if made and made_seconds > 0 else 0.0, splits=splits_count,
    )  # fmt: skip


def shard_frames(n_total: int, shard: tuple[int, int]) -> range:
    """Global frame ids that shard ``(i, N)`` of an ``n_total``-frame dataset makes: the contiguous block
    ``[i * n_total // N, (i + 1) * n_total // N)``. The N blocks partition the frames and differ in size by at most
    one. Contiguous rather than strided because frame ids run house by house: a shard then holds the frames of about
    ``houses / N + 1`` houses and builds only their raycast scenes (seconds each for real meshes), where every strided
    shard would build every house's. Which shard makes a frame never changes its bytes."""
    i, n = shard
    return range(i * n_total // n, (i + 1) * n_total // n)


def _with_hint(e: OSError, hint: str) -> OSError:
    """The same OS error (errno, file) with ``hint`` after its reason."""
    return type(e)(e.errno, f"{e.strerror or e}; {hint}", e.filename)


#: Placeholder of the manifest's frame list while the rest is encoded (see :func:`_assemble`).
_FRAMES_SLOT = "@@frame records@@"


def _assemble(out: Path, req: GenerateRequest, settings: dict, hashes: dict, houses: dict[str, House],
              cats: list[str], n_total: int) -> tuple[dict[str, int], list[dict]]:
    """Write ImageSets and then ``manifest.json`` (last) from the frame records; return the split sizes and the
    manifest's frame records."""
    for p in [out, out / "ImageSets"]:  # temps a killed assembly left behind
        if p.is_dir():
            for q in p.iterdir():
                if q.name.startswith(".") and q.name.endswith(".tmp"):
                    q.unlink(missing_ok=True)
    texts = [record_path(out, f"{g:06d}").read_text(encoding="utf-8").strip() for g in range(n_total)]
    records = [json.loads(t) for t in texts]
    splits = split_frames(len(req.houses), req.frames, req.split_mode, req.seed)
    for name, ids in splits.items():
        write_imageset(out / "ImageSets" / f"{name}.txt", ids)
    counts = describe_records(records)
    command = ["mpchair", "generate", "--root", Path(req.root).name]
    for h in req.houses:
        command += ["--house", h]
    command += ["--frames", str(req.frames), "--sensor", settings["sensor"]["name"], "--seed", str(req.seed),
                "--height", repr(req.height), "--robot-radius", repr(req.robot_radius), "--split-mode", req.split_mode,
                "--backend", req.backend, "--max-attempts", str(req.max_attempts)]
    for c in cats:
        command += ["--category", c]
    if req.keep_empty:
        command.append("--keep-empty")
    if req.viewpoints != "auto":
        command += ["--viewpoints", req.viewpoints]
    manifest = {
        "format": MANIFEST_FORMAT,
        "command": command,
        "config": settings,
        "versions": _versions(req.backend),
        "seed": req.seed,
        "houses": {
            hid: {"files_sha256": hashes[hid], "objects_of_class": len(objects_of(houses[hid], cats)),
                  "frames": [p * req.frames, (p + 1) * req.frames - 1]}
            for p, hid in enumerate(req.houses)
        },
        "conventions": {
            "frame": "sensor: x forward, y left, z up, metres (right-handed; the original was mirrored)",
            "velodyne": "float32 x, y, z, 1.0 (constant 4th channel: the sensor has no intensity)",
            "pose": "3x4 row-major sensor -> world (Matterport z-up metres)",
            "bbox_2d": "projection of the 3D box through P2, clipped to the image; truncation = fraction outside",
            "occluded": "0 if visible fraction >= {:.2f}, 1 if >= {:.2f}, else 2 (dense grid)".format(
                *settings["sensor"]["filters"]["occlusion_cutoffs"]),
            "image_2": "8-bit scan depth: 0 none, else 1 + round(254 * (1 - depth / max_range))",
            "misses": "rays without a hit (or outside the range limits) are dropped",
        },
        "splits": {k: len(v) for k, v in splits.items()},
        "totals": {"frames": n_total, "boxes_kept": counts["kept"], "boxes_rejected": counts["rejected"],
                   "points": int(sum(r["points"] for r in records))},
        "frames": _FRAMES_SLOT,
    }
    # One frame record per line, spliced in as written (sorted keys, compact): json's indenting encoder is pure
    # Python (~0.5 ms per frame, serially after the last frame); the file parses to the same data either way.
    text = json.dumps(manifest, sort_keys=True, indent=1)
    slot = json.dumps(_FRAMES_SLOT)
    if text.count(slot) == 1:
        text = text.replace(slot, "[\n  " + ",\n  ".join(texts) + "\n ]" if texts else "[]")
    else:  # the placeholder also occurs in a user-given value: encode the slow way
        text = json.dumps({**manifest, "frames": records}, sort_keys=True, indent=1)
    write_text(out / "manifest.json", text + "\n")
    return manifest["splits"], records


def default_workers() -> int:
    """A sensible default worker count: the CPUs this process may use."""
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))
