"""One robot episode: a route (:mod:`mpchair.stream.routes`), its drive (:mod:`mpchair.stream.unicycle`) and the
sensor poses at the capture times.

An episode is a pure function of ``(seed, house id, episode index)`` and the settings: its generator is
``numpy.random.default_rng([seed, crc32(house_id), EPISODE_STREAM, index])``. It draws a route, then the start heading
(uniform in ``[0, 2 pi)``); a drive that leaves free space (the follower cuts a corner too close) is thrown away and
the next route drawn. Poses are sensor → world (Matterport, z up, metres): the robot's x, y, the floor under it plus
the sensor ``height``, its heading as yaw; no pitch or roll.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from collections.abc import Sequence

import numpy as np

from mpchair.geometry import yaw_matrix
from mpchair.stream.freespace import FreeSpace
from mpchair.stream.routes import Route, RouteRules, sample_route, standing_route
from mpchair.stream.unicycle import Limits, Trajectory, drive, frame_times, sample_poses

#: Third seed word of every episode generator (keeps episode draws apart from ``generate``'s per-frame generators).
EPISODE_STREAM = 0x5354
#: Routes drawn per episode before giving up (each needs a drive that stays in free space).
ROUTE_TRIES = 20


@dataclasses.dataclass(frozen=True)
class EpisodeSettings:
    """What every episode of a run shares: sensor ``rate`` (Hz), motion ``limits``, route ``rules``, sensor
    ``height`` (metres above the floor), ``look_around`` at the start, ``duration_us`` cap (``None``: until the goal;
    needed when the robot does not drive) and the ``seed``."""

    rate: float
    limits: Limits
    rules: RouteRules
    height: float
    look_around: bool
    duration_us: int | None
    seed: int


@dataclasses.dataclass(frozen=True, eq=False)
class Episode:
    """A planned episode: its ``route``, ``start_yaw`` (radians), the simulated ``trajectory``, capture ``times_us``
    (N,) int64 microseconds from the episode start, and ``poses`` (N,4,4) sensor → world."""

    house: str
    index: int
    route: Route
    start_yaw: float
    trajectory: Trajectory
    times_us: np.ndarray
    poses: np.ndarray


def episode_rng(seed: int, house_id: str, index: int) -> np.random.Generator:
    """The generator of episode ``index`` of ``house_id`` (see the module docstring)."""
    return np.random.default_rng([seed, zlib.crc32(house_id.encode("utf-8")), EPISODE_STREAM, index])


def plan_episode(spaces: Sequence[FreeSpace], house_id: str, index: int, settings: EpisodeSettings) -> Episode:
    """Plan episode ``index`` of ``house_id`` in its free ``spaces``; ``ValueError`` when no route can be drawn."""
    rng = episode_rng(settings.seed, house_id, index)
    lim = settings.limits
    hold = settings.duration_us or 0
    if lim.speed == 0 and settings.duration_us is None:
        raise ValueError("a robot that does not drive (speed 0) needs a duration")
    for _ in range(ROUTE_TRIES):
        route = (standing_route(rng, spaces, settings.rules) if lim.speed == 0
                 else sample_route(rng, spaces, settings.rules))
        yaw0 = float(rng.random() * 2.0 * math.pi)
        space = next(s for s in spaces if s.level == route.level)
        try:
            traj = drive(route.waypoints, yaw0, lim, settings.look_around, hold_until_us=hold if lim.speed == 0 else 0)
        except RuntimeError:
            continue
        if not space.is_free(traj.xy).all():
            continue
        end = traj.end_us if settings.duration_us is None else min(traj.end_us, settings.duration_us)
        times = frame_times(settings.rate, end)
        xy, yaw = sample_poses(traj, times)
        poses = yaw_matrix(yaw)
        poses[:, :2, 3] = xy
        poses[:, 2, 3] = space.floor_at(xy) + settings.height
        return Episode(house=house_id, index=index, route=route, start_yaw=yaw0, trajectory=traj, times_us=times,
                       poses=poses)
    raise ValueError(f"no route in {ROUTE_TRIES} draws whose drive stays in free space")
