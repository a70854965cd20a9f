"""``mpchair generate`` as a library call: houses in, a KITTI-format Matterport-Chair dataset out.

Layout written under ``out``::

    training/{velodyne,label_2,calib,image_2,pose}/NNNNNN.*   one frame each (see mpchair.dataset.frame)
    ImageSets/{train,val,test}.txt                          written when every frame exists
    testing/{velodyne,calib,image_2}/NNNNNN.*               the test split as KITTI lays it out (hard links)
    manifest.json                                           written last (mpchair.dataset.manifest.Manifest)
    .frames/NNNNNN.json                                     per-frame records (mpchair.dataset.manifest.FrameRecord;
                                                            a frame is done iff its record exists)
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
import functools
import math
import os
import re
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from mpchair.core.atomic import temp_glob, write_text
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError
from mpchair.core.lock import folder_lock, held, wait_lock
from mpchair.dataset import job
from mpchair.dataset.frame import (
    FrameSettings,
    HouseContext,
    build_context,
    make_frame,
    record_path,
    resolve_viewpoints,
    viewpoint_sampler,
    warm_up,
    write_frame,
)
from mpchair.dataset.houses import RunHouses, load_run_houses
from mpchair.dataset.manifest import (
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    FrameRecord,
    Manifest,
    ManifestHouse,
    ManifestTotals,
    conventions,
    describe_records,
    read_frame_record,
)
from mpchair.dataset.splits import SPLIT_MODES, TESTING_KINDS, house_splits, split_frames, write_testing_folder
from mpchair.kitti import write_imageset
from mpchair.matterport.house import House
from mpchair.scan.sensors import SensorConfig, load_sensor, scan_directions
from mpchair.scan.viewpoints import ViewpointParams

#: Frame ids are 6 digits (KITTI file names).
MAX_FRAMES = 1_000_000
SETTINGS_FILE = ".generate.json"
GENERATE = job.JobKind(command="generate", folder="dataset", settings_file=SETTINGS_FILE)
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
    #: ``house`` mode: the houses held out for val / test (every other house trains); empty: a seeded choice
    val_houses: tuple[str, ...] = ()
    test_houses: tuple[str, ...] = ()
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


class FrameTask(NamedTuple):
    """One frame to make: its global ``frame`` id (house position * frames + ``index``), its ``house`` id and its
    ``index`` in that house."""

    frame: int
    house: str
    index: int

    @property
    def fid(self) -> str:
        """The 6-digit frame id of the KITTI file names."""
        return f"{self.frame:06d}"


@dataclasses.dataclass(frozen=True)
class _Plan:
    """A checked ``generate`` run, before it touches the folder: the ``req``, its ``houses``, the ``categories``
    (mpcat40 names, sorted) and ``category_ids`` to label, the ``settings`` stored in ``.generate.json`` (and the
    manifest's ``config``) and what every frame shares (``frame_settings``)."""

    req: GenerateRequest
    houses: RunHouses
    categories: tuple[str, ...]
    category_ids: frozenset[int]
    settings: dict
    frame_settings: FrameSettings


def _settings(req: GenerateRequest, sensor: SensorConfig, params: ViewpointParams, cats: tuple[str, ...]) -> dict:
    """The deterministic part of a run (what the output depends on); stored in ``.generate.json``."""
    return {
        "houses": list(req.houses),
        "frames_per_house": req.frames,
        "sensor": to_dict(sensor),
        "viewpoints": to_dict(params),
        "seed": req.seed,
        "categories": list(cats),
        "keep_empty": req.keep_empty,
        "split_mode": req.split_mode,
        # only when chosen, so that the settings (and bytes) of every other run stay as they were
        **({"val_houses": list(req.val_houses), "test_houses": list(req.test_houses)}
           if req.val_houses or req.test_houses else {}),
        "backend": req.backend,
        "max_attempts": req.max_attempts,
    }


@dataclasses.dataclass(frozen=True)
class FrameWorker:
    """What a process that makes frames holds: the run's ``houses``, the frames' ``settings``, the ``categories``
    (mpcat40 indices) to label, the raycasting ``backend``, the dataset folder ``out`` and the sensor's scan
    ``directions`` (sensor frame unit vectors). ``scenes`` caches each house's raycasting scene, built on the first
    frame of that house this process makes (a shard touches few houses; a scene takes seconds for a real mesh)."""

    houses: Mapping[str, House]
    settings: FrameSettings
    categories: frozenset[int]
    backend: str
    out: Path
    directions: np.ndarray
    scenes: dict[str, HouseContext] = dataclasses.field(default_factory=dict)


def make_frame_task(worker: FrameWorker, task: FrameTask) -> FrameRecord:
    """Make and write one frame (in a pool worker or in-process); returns its record."""
    ctx = worker.scenes.get(task.house)
    if ctx is None:
        ctx = build_context(worker.houses[task.house], worker.categories, worker.backend,
                            worker.settings.sensor.filters.box_margin, worker.settings.viewpoint_source)
        worker.scenes[task.house] = ctx
    result = make_frame(ctx, worker.settings, task.index, worker.directions)
    return write_frame(worker.out, task.fid, ctx.house, task.index, result, worker.settings.sensor)


def _frame_folders(out: Path) -> list[Path]:
    """The folders that hold one file per frame (and the frame records)."""
    return [out / "training" / d for d in FRAME_DIRS] + [out / ".frames"]


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


def _is_lock(name: str) -> bool:
    """A shard's lock file (``.generate-i-of-N.lock``)."""
    return bool(_LOCK_NAME.fullmatch(name))


def _is_ours(name: str) -> bool:
    """Files a run of ours may leave in a folder without a settings file: its lock files and a killed settings write."""
    return _is_lock(name) or fnmatch.fnmatchcase(name, temp_glob(SETTINGS_FILE))


def _has_records(out: Path) -> bool:
    d = out / ".frames"
    return d.is_dir() and any(p.suffix == ".json" and not p.name.startswith(".") for p in d.iterdir())


def _undo(out: Path, fids: set[str], existed: bool, shard: tuple[int, int]) -> None:
    """Remove what a run that could not make its frames wrote into a folder that held no frame before it: its frames'
    files, then (when no other shard runs and no frame is left) the settings and the folders it created."""
    for sub in _frame_folders(out):
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
    job.check_houses_and_workers(req.houses, req.workers)
    if len(req.houses) * req.frames > MAX_FRAMES:
        raise InputError(f"{len(req.houses)} houses x --frames {req.frames} exceeds {MAX_FRAMES} frames (6-digit "
                         "KITTI frame ids)")
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
    if req.split_mode == "house" and len(req.houses) < 3 and not (req.val_houses or req.test_houses):
        raise InputError(f"--split-mode house needs at least 3 houses, got {len(req.houses)}")
    if (req.val_houses or req.test_houses) and req.split_mode != "house":
        raise InputError(f"--val-house / --test-house choose whole houses: they need --split-mode house, not "
                         f"{req.split_mode}")
    for flag, chosen in (("--val-house", req.val_houses), ("--test-house", req.test_houses)):
        for h in chosen:
            if h not in req.houses:
                raise InputError(f"{flag} {h}: not one of the --house ids ({', '.join(req.houses)})")
    held_out_positions(req)  # the split itself (a house in both, none left to train) is checked before any frame


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
    plan = _plan(req)
    out = Path(req.out)
    existed = out.exists()
    with folder_lock(_shard_lock(out, req.shard), f"mpchair generate --shard {si}/{sn}"):
        others = _others_running(out, req.shard)
        clash = [o for o in others if o[1] != sn]
        if clash:
            raise InputError(f"another mpchair generate (--shard {clash[0][0]}/{clash[0][1]}) is writing this folder; "
                             f"shards running at the same time must share N (here {sn})", out)
        # a folder without a frame record yet takes new settings, unless another shard is writing it
        job.check_settings(GENERATE, out, plan.settings, alone=not others,
                           replace=not others and not _has_records(out), ours=_is_lock)
        return _run(plan, t0=t0, fresh=not _has_records(out), existed=existed)


def _plan(req: GenerateRequest) -> _Plan:
    """Load the sensor, the classes and the houses of ``req`` (every input check that needs no folder)."""
    sensor = load_sensor(req.sensor)
    params = ViewpointParams(height=req.height, robot_radius=req.robot_radius)
    cat_idx, cats = job.resolve_classes(req.categories)

    def check_viewpoints(house: House) -> None:  # a navmesh without a large enough island fails here, not in a frame
        viewpoint_sampler(house, resolve_viewpoints(house, req.viewpoints))

    houses = load_run_houses(req.root, req.houses, cat_idx, backend=req.backend, navmesh=req.viewpoints != "regions",
                             check=check_viewpoints)
    settings = _settings(req, sensor, params, cats)
    sources = {hid: resolve_viewpoints(h, req.viewpoints) for hid, h in houses.houses.items()}
    if "navmesh" in sources.values():  # only then: regions-only runs keep the settings (and resume) they had
        settings["viewpoint_sources"] = sources
    fs = FrameSettings(sensor=sensor, viewpoints=params, seed=req.seed, keep_empty=req.keep_empty,
                       max_attempts=req.max_attempts, viewpoint_source=req.viewpoints)
    return _Plan(req=req, houses=houses, categories=cats, category_ids=cat_idx, settings=settings, frame_settings=fs)


def _run(plan: _Plan, *, t0: float, fresh: bool, existed: bool) -> GenerateSummary:
    """Make this shard's missing frames, then (when every frame exists) ImageSets and the manifest. ``t0``: when the
    run started (``time.perf_counter``); ``fresh``: the folder held no frame record; ``existed``: nor did it exist."""
    req = plan.req
    out = Path(req.out)
    n_total = len(req.houses) * req.frames
    tasks = [FrameTask(hp * req.frames + i, hid, i) for hp, hid in enumerate(req.houses) for i in range(req.frames)]
    mine = [tasks[g] for g in shard_frames(n_total, req.shard)]
    pending = [t for t in mine if not record_path(out, t.fid).is_file()]
    # Temps of every frame of this shard, done or not: under the shard's lock nothing else writes them (its workers
    # died with the run that forked them), and a temp beside a finished frame would otherwise stay for good. Other
    # shards' frames are left to their own runs.
    shard_fids = {t.fid for t in mine}
    job.remove_temps(_frame_folders(out), owned=lambda name: name[1:7] in shard_fids)
    resumed = len(mine) - len(pending)
    if pending:
        warm_up(plan.frame_settings.sensor)  # before forking: the workers inherit the loaded kernels
    made_seconds = _make_frames(plan, pending, len(mine), fresh=fresh, existed=existed)

    complete = all(record_path(out, f"{g:06d}").is_file() for g in range(n_total))
    splits: dict[str, int] = {}
    if complete:
        try:
            # Shards finishing together take turns (assembly removes temp files a killed assembly left).
            with wait_lock(out / ".generate-assemble.lock") if req.shard[1] > 1 else contextlib.nullcontext():
                manifest = _assemble(plan, n_total)
        except OSError as e:
            raise job.with_hint(e, "the frames are kept: run the same command again to write ImageSets and the "
                                    "manifest") from None
        splits, records = manifest.splits, manifest.frames
    else:  # this shard's frames, made now or by an earlier run
        records = tuple(read_frame_record(record_path(out, t.fid)) for t in mine)
    counts = describe_records(records)
    made = len(pending)
    return GenerateSummary(
        out=str(out), frames=n_total, made=made, resumed=resumed, complete=complete, nothing_to_make=not made,
        scope="dataset" if complete else "shard", kept=counts.kept, kept_by_class=counts.kept_by_class,
        rejected=counts.rejected, points=counts.points, rays=counts.rays, seconds=time.perf_counter() - t0,
        frames_per_second=job.per_second(made, made_seconds), splits=splits,
    )  # fmt: skip


def _make_frames(plan: _Plan, pending: list[FrameTask], shard_frames_total: int, *, fresh: bool,
                 existed: bool) -> float:
    """Make the ``pending`` frames (in worker processes when ``req.workers`` > 1), with a progress bar over the
    shard's ``shard_frames_total`` frames; a frame that cannot be made on a ``fresh`` folder undoes the run. Returns
    the seconds it took."""
    req, out = plan.req, Path(plan.req.out)
    worker = FrameWorker(houses=plan.houses.houses, settings=plan.frame_settings, categories=plan.category_ids,
                         backend=req.backend, out=out, directions=scan_directions(plan.frame_settings.sensor))
    shown = {"kept": 0, "rejected": 0}  # beside the progress bar (the summary counts come from the records)

    def account(rec: FrameRecord) -> dict[str, int]:
        shown["kept"] += len(rec.kept)
        shown["rejected"] += len(rec.rejected)
        return shown

    try:
        return job.make_tasks(functools.partial(make_frame_task, worker), pending, shard_frames_total,
                              workers=req.workers, out=out, kind=GENERATE, progress=req.progress,
                              is_done=lambda t: record_path(out, t.fid).is_file(), account=account)
    except InputError:
        if fresh:  # these settings cannot make the dataset: leave the folder as it was for the corrected command
            _undo(out, {t.fid for t in pending}, existed, req.shard)
        raise
    except OSError as e:
        raise job.with_hint(e, job.RESUME) from None


def shard_frames(n_total: int, shard: tuple[int, int]) -> range:
    """Global frame ids that shard ``(i, N)`` of an ``n_total``-frame dataset makes: the contiguous block
    ``[i * n_total // N, (i + 1) * n_total // N)``. The N blocks partition the frames and differ in size by at most
    one. Contiguous rather than strided because frame ids run house by house: a shard then holds the frames of about
    ``houses / N + 1`` houses and builds only their raycast scenes (seconds each for real meshes), where every strided
    shard would build every house's. Which shard makes a frame never changes its bytes."""
    i, n = shard
    return range(i * n_total // n, (i + 1) * n_total // n)


def _assemble(plan: _Plan, n_total: int) -> Manifest:
    """Write ImageSets and then ``manifest.json`` (last) from the frame records; return the manifest."""
    out = Path(plan.req.out)
    testing = [out / "testing" / kind for kind in TESTING_KINDS]
    job.remove_temps([out, out / "ImageSets", *testing])  # temps a killed assembly left behind
    records = tuple(read_frame_record(record_path(out, f"{g:06d}")) for g in range(n_total))
    req = plan.req
    splits = split_frames(len(req.houses), req.frames, req.split_mode, req.seed, held_out_positions(req))
    for name, ids in splits.items():
        write_imageset(out / "ImageSets" / f"{name}.txt", ids)
    write_testing_folder(out, list(splits.get("test", ())))
    split_houses = None
    if req.split_mode == "house":
        positions = house_splits(len(req.houses), req.seed, held_out_positions(req))
        split_houses = {name: [req.houses[p] for p in ps] for name, ps in positions.items()}
    manifest = _manifest(plan, records, {k: len(v) for k, v in splits.items()}, split_houses)
    write_text(out / MANIFEST_NAME, manifest.to_json() + "\n")
    return manifest


def held_out_positions(req: GenerateRequest) -> dict[str, tuple[int, ...]] | None:
    """The ``--house`` positions of the chosen val / test houses (None: none chosen), checked as a split."""
    if not (req.val_houses or req.test_houses):
        return None
    held = {"val": tuple(req.houses.index(h) for h in req.val_houses),
            "test": tuple(req.houses.index(h) for h in req.test_houses)}
    house_splits(len(req.houses), req.seed, held)
    return held


def _manifest(plan: _Plan, records: tuple[FrameRecord, ...], splits: dict[str, int],
              split_houses: dict[str, list[str]] | None = None) -> Manifest:
    """The manifest of the complete dataset: ``records`` every frame's, ``splits`` the split sizes,
    ``split_houses`` which house went where (house mode)."""
    req, houses, settings = plan.req, plan.houses, plan.settings
    counts = describe_records(records)
    return Manifest(
        format=MANIFEST_FORMAT,
        command=_command(req, settings["sensor"]["name"], plan.categories),
        config=settings,
        versions=houses.versions,
        seed=req.seed,
        houses={hid: ManifestHouse(files_sha256=houses.files_sha256[hid], objects_of_class=houses.objects_of_class[hid],
                                   frames=(p * req.frames, (p + 1) * req.frames - 1))
                for p, hid in enumerate(req.houses)},
        conventions=conventions(settings["sensor"]["filters"]["occlusion_cutoffs"]),
        splits=splits,
        totals=ManifestTotals(frames=len(records), boxes_kept=counts.kept, boxes_rejected=counts.rejected,
                              points=int(sum(r.points for r in records))),
        frames=records,
        split_houses=split_houses,
    )


def _command(req: GenerateRequest, sensor_name: str, cats: tuple[str, ...]) -> tuple[str, ...]:
    """The ``mpchair generate`` command line that makes this dataset (the root by folder name: no absolute path)."""
    return job.command_line(GENERATE, req.root, req.houses, [
        ("--frames", req.frames), ("--sensor", sensor_name), ("--seed", req.seed), ("--height", req.height),
        ("--robot-radius", req.robot_radius), ("--split-mode", req.split_mode), ("--val-house", req.val_houses),
        ("--test-house", req.test_houses), ("--backend", req.backend), ("--max-attempts", req.max_attempts),
        ("--category", cats), ("--keep-empty", bool(req.keep_empty)),
        ("--viewpoints", None if req.viewpoints == "auto" else req.viewpoints)])


def default_workers() -> int:
    """A sensible default worker count: the CPUs this process may use."""
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))

