"""``mpchair stream`` as a library call: robot episodes through houses → timed, labelled scan sequences.

For every house (in the order given) and episode ``e < episodes``, sequence ``NN = house position * episodes + e``:
plan the episode (:mod:`mpchair.stream.episodes`: free space, route, unicycle drive, capture times at ``rate`` Hz),
then make every frame at its pose with ``generate``'s own raycaster, label filters and scan
(:func:`mpchair.dataset.frame.label_pose`, :func:`~mpchair.dataset.frame.cast_scan`,
:func:`~mpchair.labels.select.apply_scan_points`) and write it (:mod:`mpchair.stream.writer`). ``stream.json`` is
written last, when every frame exists.

Determinism and resuming: a frame depends only on its pose and the settings, never on ``workers``; every file is
written atomically and the stream file holds no times or absolute paths, so a run killed at any point (even SIGKILL)
and re-run with the same arguments ends byte-identical to an uninterrupted one. A folder made with other settings is
refused (``.stream.json``). Every check of the input (houses, sensor, options, routes) runs before the first file is
written.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np

from mpchair.core.atomic import write_text
from mpchair.core.config import to_dict
from mpchair.core.errors import InputError
from mpchair.core.lock import folder_lock
from mpchair.dataset import job
from mpchair.dataset.frame import (
    HouseContext,
    build_context,
    cast_scan,
    floor_areas,
    label_pose,
    resolve_viewpoints,
    warm_up,
)
from mpchair.dataset.houses import RunHouses, load_run_houses
from mpchair.labels.select import apply_scan_points, label_half_fov
from mpchair.matterport.house import House
from mpchair.recording.sources import MAX_RATE_HZ
from mpchair.scan.sensors import SensorConfig, load_sensor, scan_directions
from mpchair.scan.viewpoints import ViewpointParams
from mpchair.stream.episodes import Episode, EpisodeSettings, plan_episode
from mpchair.stream.freespace import free_space, navmesh_areas
from mpchair.stream.routes import RouteRules
from mpchair.stream.unicycle import Limits
from mpchair.stream.writer import (
    FRAME_DIRS,
    StreamFrameRecord,
    read_stream_record,
    record_path,
    sequence_dir,
    write_sequence_files,
    write_stream_frame,
)

STREAM_FORMAT = "mpchair-stream/1"
STREAM = job.JobKind(command="stream", folder="stream", settings_file=".stream.json")
STREAM_LOCK = ".stream.lock"


@dataclasses.dataclass(frozen=True)
class StreamRequest:
    """Arguments of one ``stream`` run: ``episodes`` per house, sensor ``rate`` (Hz), motion limits (``speed`` m/s,
    ``turn_rate`` rad/s, ``accel`` m/s^2), ``duration`` cap per episode (seconds; ``None`` = until the goal),
    route rules (metres), sensor ``height`` and ``robot_radius`` (metres), ``free_space`` source (``auto``: the house's
    navmesh when it has one, else ``regions``: its floor polygons; ``navmesh``)."""

    root: Path
    houses: tuple[str, ...]
    episodes: int
    out: Path
    rate: float = 10.0
    speed: float = 0.5
    turn_rate: float = 1.0
    accel: float = 0.5
    sensor: str = "mp3d-depth90"
    seed: int = 0
    height: float = 1.0
    robot_radius: float = 0.25
    categories: tuple[str, ...] = ("chair",)
    look_around: bool = True
    duration: float | None = None
    min_geodesic: float = 5.0
    max_geodesic: float = 30.0
    min_ratio: float = 1.1
    free_space: str = "auto"
    backend: str = "embree"
    workers: int = 1
    progress: bool = True


@dataclasses.dataclass(frozen=True)
class StreamSummary:
    """What a run did: ``sequences`` and ``frames`` in the stream, frames ``made`` now and ``resumed`` (present),
    ``complete`` (stream.json written), boxes ``kept`` and ``dontcare`` over the whole stream, mean ``points`` per
    frame, ``seconds`` wall time, ``frames_per_second`` of this run's frames."""

    out: str
    sequences: int
    frames: int
    made: int
    resumed: int
    complete: bool
    kept: int
    dontcare: int
    points: float
    seconds: float
    frames_per_second: float

    def line(self) -> str:
        """One-line human summary."""
        return (f"{self.out}: {self.sequences} sequences, {self.frames} frames; this run made {self.made} in "
                f"{self.seconds:.1f} s ({self.frames_per_second:.1f} frames/s), resumed {self.resumed}; chairs "
                f"kept {self.kept}, DontCare {self.dontcare}; {self.points:.0f} points/frame")


class StreamTask(NamedTuple):
    """One frame to make: frame ``index`` of sequence ``sequence``."""

    sequence: str
    index: int

    @property
    def fid(self) -> str:
        """The 6-digit frame id of the file names."""
        return f"{self.index:06d}"


#: Bounds that keep planning finite (it runs before any frame, in one process): episodes per house, an episode's
#: --duration (seconds; the drive is simulated at 100 Hz) and the slowest moving robot (m/s; a drive to the goal is
#: simulated for up to 4 x its path at full speed).
MAX_EPISODES = 10_000
MAX_DURATION_S = 3600.0
MIN_SPEED = 0.01


def _check_request(req: StreamRequest) -> None:
    if not 1 <= req.episodes <= MAX_EPISODES:
        raise InputError(f"--episodes must be from 1 to {MAX_EPISODES} per house, got {req.episodes}")
    if not 0 < req.rate <= MAX_RATE_HZ:  # what every stream reader accepts (mpchair.recording.sources); NaN fails
        raise InputError(f"--rate must be a positive sensor rate of at most {MAX_RATE_HZ:g} Hz (what every stream "
                         f"reader accepts), got {req.rate}")
    if not (req.speed == 0 or MIN_SPEED <= req.speed < math.inf):
        raise InputError(f"--speed must be 0 (a robot that stays put) or a finite number >= {MIN_SPEED:g} m/s, got "
                         f"{req.speed}")
    if not 0 <= req.turn_rate < math.inf:
        raise InputError(f"--turn-rate must be a finite number >= 0 rad/s, got {req.turn_rate}")
    if not 0 < req.accel < math.inf:
        raise InputError(f"--accel must be a finite number > 0 m/s^2, got {req.accel}")
    job.check_houses_and_workers(req.houses, req.workers)
    if req.duration is not None and not 0 < req.duration <= MAX_DURATION_S:
        raise InputError(f"--duration must be from 0 to {MAX_DURATION_S:g} seconds per episode, got {req.duration}")
    if req.speed == 0 and req.duration is None:
        raise InputError("--speed 0 (a robot that stays put) needs --duration")
    if req.free_space not in ("auto", "regions", "navmesh"):
        raise InputError(f"--free-space must be auto, regions or navmesh, got {req.free_space!r}")


def _settings(req: StreamRequest, sensor: SensorConfig, es: EpisodeSettings, params: ViewpointParams,
              cats: tuple[str, ...]) -> dict:
    """The deterministic part of a run (what the output depends on); stored in ``.stream.json`` and ``stream.json``."""
    return {
        "houses": list(req.houses),
        "episodes_per_house": req.episodes,
        "rate_hz": req.rate,
        "limits": to_dict(es.limits),
        "route_rules": to_dict(es.rules),
        "look_around": es.look_around,
        "duration_s": req.duration,
        "sensor": to_dict(sensor),
        "viewpoints": to_dict(params),
        "seed": req.seed,
        "categories": list(cats),
        "free_space": req.free_space,
        "backend": req.backend,
    }


def _plan_episodes(req: StreamRequest, houses: Mapping[str, House], contexts: Mapping[str, HouseContext],
                   es: EpisodeSettings, params: ViewpointParams) -> list[tuple[str, Episode]]:
    """``(sequence name, episode)`` for every house and episode; bad houses / impossible routes are InputErrors."""
    width = max(2, len(str(len(req.houses) * req.episodes - 1)))
    plan = []
    for hp, hid in enumerate(req.houses):
        ctx = contexts[hid]
        house = houses[hid]
        if req.free_space == "navmesh" and house.navmesh is None:
            raise InputError(f"house {hid} has no <id>.navmesh (habitat layout); use --free-space regions")
        areas = (navmesh_areas(house.navmesh) if resolve_viewpoints(house, req.free_space) == "navmesh"
                 else floor_areas(house))
        spaces = free_space(areas, ctx.raycaster, ctx.floor_ok, ctx.normal_z, params)
        if not spaces:
            raise InputError(f"house {hid}: no free floor cell with {req.robot_radius} m clearance")
        for e in range(req.episodes):
            try:
                ep = plan_episode(spaces, hid, e, es)
            except ValueError as err:
                raise InputError(f"house {hid}, episode {e}: {err}; relax --min-geodesic / --max-geodesic / "
                                 "--min-ratio for a small house") from None
            plan.append((f"{hp * req.episodes + e:0{width}d}", ep))
    return plan


@dataclasses.dataclass(frozen=True)
class StreamWorker:
    """What a process that makes stream frames holds: the ``episodes`` by sequence name, each house's raycasting
    scene (``contexts``), the ``sensor``, its scan ``directions`` (sensor frame unit vectors) and the stream folder
    ``out``."""

    episodes: Mapping[str, Episode]
    contexts: Mapping[str, HouseContext]
    sensor: SensorConfig
    directions: np.ndarray
    out: Path


def make_stream_task(worker: StreamWorker, task: StreamTask) -> StreamFrameRecord:
    """Make and write one frame at its planned pose (in a pool worker or in-process); returns its record."""
    ep = worker.episodes[task.sequence]
    ctx = worker.contexts[ep.house]
    sensor = worker.sensor
    pose = ep.poses[task.index]
    dec = label_pose(ctx, sensor, pose)
    points = cast_scan(sensor, worker.directions, pose, ctx.raycaster)
    dec = apply_scan_points(dec, points, sensor.filters)
    return write_stream_frame(worker.out, task.sequence, task.fid, ctx.house, dec, points, sensor,
                              int(ep.times_us[task.index]), dec.dense_rays + len(worker.directions))


@dataclasses.dataclass(frozen=True)
class _Plan:
    """A checked ``stream`` run, before it touches the folder: the ``req``, the ``settings`` stored in
    ``.stream.json`` (and ``stream.json``'s ``config``), the ``sequences`` (name, episode) in order, each house's
    raycasting scene (``contexts``), the ``sensor``, the run's ``houses`` and the ``categories`` (mpcat40 names,
    sorted) labelled."""

    req: StreamRequest
    settings: dict
    sequences: tuple[tuple[str, Episode], ...]
    contexts: Mapping[str, HouseContext]
    sensor: SensorConfig
    houses: RunHouses
    categories: tuple[str, ...]


def stream(req: StreamRequest) -> StreamSummary:
    """Make (or resume) the stream described by ``req``; see the module docstring. Bad input raises
    :class:`InputError` before any file is written."""
    t0 = time.perf_counter()
    _check_request(req)
    plan = _plan(req)
    with folder_lock(Path(req.out) / STREAM_LOCK, "mpchair stream"):
        return _make(plan, t0)


def _plan(req: StreamRequest) -> _Plan:
    """Load the sensor, the classes and the houses of ``req``, build each house's scene and plan every episode
    (every input check, before the folder is touched)."""
    sensor = load_sensor(req.sensor)
    try:
        params = ViewpointParams(height=req.height, robot_radius=req.robot_radius)
        es = EpisodeSettings(
            rate=float(req.rate), limits=Limits(speed=req.speed, turn_rate=req.turn_rate, accel=req.accel),
            rules=RouteRules(min_geodesic=req.min_geodesic, max_geodesic=req.max_geodesic, min_ratio=req.min_ratio),
            height=req.height, look_around=req.look_around,
            duration_us=None if req.duration is None else int(round(req.duration * 1e6)), seed=req.seed)
    except ValueError as e:
        raise InputError(str(e)) from None
    cat_idx, cats = job.resolve_classes(req.categories)
    contexts: dict[str, HouseContext] = {}

    def build_scene(house: House) -> None:  # right after reading: a house without floor fails before the next is read
        contexts[house.id] = build_context(house, cat_idx, req.backend, sensor.filters.box_margin)

    houses = load_run_houses(req.root, req.houses, cat_idx, backend=req.backend, hashed="layout", check=build_scene)
    sequences = _plan_episodes(req, houses.houses, contexts, es, params)
    return _Plan(req=req, settings=_settings(req, sensor, es, params, cats), sequences=tuple(sequences),
                 contexts=contexts, sensor=sensor, houses=houses, categories=cats)


def _make(plan: _Plan, t0: float) -> StreamSummary:
    """Write the stream's missing frames and its summary files (under the folder's lock; ``t0``: when the run
    started, ``time.perf_counter``)."""
    out = Path(plan.req.out)
    # under the folder's lock: alone; a stream's settings are never replaced (its sequence files come first)
    job.check_settings(STREAM, out, plan.settings, alone=True, replace=False, ours=lambda name: name == STREAM_LOCK)
    seqs = [s for s, _ in plan.sequences]
    job.remove_temps([out, *(sequence_dir(out, s) / d for s in seqs for d in FRAME_DIRS),
                  *(sequence_dir(out, s) for s in seqs), *(out / ".frames" / s for s in seqs)])
    tasks = [StreamTask(seq, i) for seq, ep in plan.sequences for i in range(len(ep.times_us))]
    pending = [t for t in tasks if not record_path(out, t.sequence, t.fid).is_file()]
    resumed = len(tasks) - len(pending)
    try:
        for seq, ep in plan.sequences:
            write_sequence_files(out, seq, ep.times_us, ep.poses)
        if pending:
            warm_up(plan.sensor)  # before forking: the workers inherit the loaded kernels
        worker = StreamWorker(episodes=dict(plan.sequences), contexts=plan.contexts, sensor=plan.sensor,
                              directions=scan_directions(plan.sensor), out=out)
        made_seconds = job.make_tasks(functools.partial(make_stream_task, worker), pending, len(tasks),
                                      workers=plan.req.workers, out=out, kind=STREAM, progress=plan.req.progress,
                                      is_done=lambda t: record_path(out, t.sequence, t.fid).is_file())
        records = [read_stream_record(record_path(out, t.sequence, t.fid)) for t in tasks]
        _write_stream_json(plan, records, label_half_fov(plan.sensor.filters, plan.sensor.camera))
    except OSError as e:
        # a full disk, a lost permission (in any write: the sequence files, a frame, stream.json): what is written is
        # whole (temp + rename), so the same command resumes
        raise job.with_hint(e, "the frames written so far are kept: free the space (or fix the cause) and run the "
                            "same command again to resume") from None
    made = len(pending)
    return StreamSummary(
        out=str(out), sequences=len(plan.sequences), frames=len(tasks), made=made, resumed=resumed, complete=True,
        kept=sum(r.kept for r in records), dontcare=sum(r.dontcare for r in records),
        points=float(np.mean([r.points for r in records])) if records else 0.0,
        seconds=time.perf_counter() - t0,
        frames_per_second=job.per_second(made, made_seconds),
    )  # fmt: skip


def _r(x: float, nd: int = 6) -> float:
    return round(float(x), nd)


def _write_stream_json(plan: _Plan, records: list[StreamFrameRecord], half_fov: float | None) -> None:
    """``stream.json`` (last): settings, versions, house checksums, the labelled region (``half_fov`` radians or
    ``None``), one entry per sequence, totals, conventions."""
    req, settings, filters = plan.req, plan.settings, plan.settings["sensor"]["filters"]
    by_seq: dict[str, list[StreamFrameRecord]] = {}
    for r in records:
        by_seq.setdefault(r.sequence, []).append(r)
    rejected: Counter[str] = Counter()
    for r in records:
        rejected.update(r.rejected)
    doc = {
        "format": STREAM_FORMAT,
        "command": _command(req, settings["sensor"]["name"], plan.categories),
        "config": settings,
        "versions": plan.houses.versions,
        "seed": req.seed,
        "rate_hz": req.rate,
        # the labelled region in numbers (mpchair.geometry.region), so that a reader need not re-derive it
        "region": {"max_abs_dz": filters["max_abs_dz"], "max_distance": filters["max_distance"], "half_fov": half_fov},
        "image_size": [settings["sensor"]["camera"]["width"], settings["sensor"]["camera"]["height"]],
        "houses": {hid: {"files_sha256": plan.houses.files_sha256[hid],
                         "objects_of_class": plan.houses.objects_of_class[hid],
                         "sequences": [s for s, ep in plan.sequences if ep.house == hid]} for hid in req.houses},
        "sequences": {seq: _sequence_entry(ep, by_seq[seq]) for seq, ep in plan.sequences},
        "totals": {"sequences": len(plan.sequences), "frames": len(records), "boxes_kept": sum(r.kept for r in records),
                   "dontcare": sum(r.dontcare for r in records), "boxes_rejected": dict(sorted(rejected.items())),
                   "points": int(sum(r.points for r in records))},
        "conventions": {
            "frame": "sensor: x forward, y left, z up, metres (right-handed)",
            "velodyne": "float32 x, y, z, 1.0 (constant 4th channel)",
            "poses": "poses.txt: 3x4 row-major sensor -> world (Matterport z-up metres) per frame",
            "times": "times.txt: capture time in seconds from the sequence start, exact integer microseconds",
            "label_2": "kept boxes, then DontCare rows (2D box) for boxes rejected inside the labelled region",
            "label_dontcare": "the DontCare boxes with their 3D box (KITTI 15 columns)",
            "region": "box centre |z| <= max_abs_dz, hypot(x, y) <= max_distance, inside the camera's hfov if fov",
        },
    }
    write_text(Path(req.out) / "stream.json", json.dumps(doc, sort_keys=True, indent=1) + "\n")


def _sequence_entry(ep: Episode, records: list[StreamFrameRecord]) -> dict:
    """``stream.json``'s entry of one sequence: its house, episode, route (world frame, metres / radians, 6
    decimals) and box counts over its ``records``."""
    return {"house": ep.house, "episode": ep.index, "level": ep.route.level, "frames": len(ep.times_us),
            "duration_s": _r(ep.times_us[-1] / 1e6), "start_xy": [_r(v) for v in ep.route.waypoints[0]],
            "goal_xy": [_r(v) for v in ep.route.waypoints[-1]], "start_yaw": _r(ep.start_yaw),
            "path_m": _r(ep.route.length), "geodesic_m": _r(ep.route.geodesic),
            "euclidean_m": _r(ep.route.euclidean), "kept": sum(r.kept for r in records),
            "dontcare": sum(r.dontcare for r in records)}  # fmt: skip


def _command(req: StreamRequest, sensor_name: str, cats: tuple[str, ...]) -> tuple[str, ...]:
    """The ``mpchair stream`` command line that makes this stream (the root by folder name: no absolute path)."""
    return job.command_line(STREAM, req.root, req.houses, [
        ("--episodes", req.episodes), ("--rate", req.rate), ("--speed", req.speed), ("--turn-rate", req.turn_rate),
        ("--accel", req.accel), ("--sensor", sensor_name), ("--seed", req.seed), ("--height", req.height),
        ("--robot-radius", req.robot_radius), ("--min-geodesic", req.min_geodesic),
        ("--max-geodesic", req.max_geodesic), ("--min-ratio", req.min_ratio), ("--free-space", req.free_space),
        ("--backend", req.backend), ("--duration", req.duration), ("--no-look-around", not req.look_around),
        ("--category", cats)])
