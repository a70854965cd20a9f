"""``mpchair stream``: robot episodes through houses → timed, labelled scan sequences (parse, call, print)."""

from __future__ import annotations

from pathlib import Path

import click

from mpchair.commands import echo_summary, sensor_help
from mpchair.core import limits


@click.command(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.option("--root", required=True, type=click.Path(path_type=Path),
              help="Matterport3D root (v1/scans/<id>/..., zips or folders) or a folder of houses.")
@click.option("--house", "houses", multiple=True, required=True, help="House id; repeat for several houses.")
@click.option("--episodes", required=True, type=int, help="Episodes (sequences) per house.")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path), help="Stream folder.")
@click.option("--rate", default=10.0, show_default=True, type=float, help="Sensor rate, Hz.")
@click.option("--speed", default=0.5, show_default=True, type=float,
              help="Top speed v_max, m/s (0: the robot stays put; needs --duration).")
@click.option("--turn-rate", default=1.0, show_default=True, type=float, help="Top turn rate omega_max, rad/s.")
@click.option("--accel", default=0.5, show_default=True, type=float, help="Acceleration limit a_max, m/s^2.")
@click.option("--duration", type=float, default=None,
              help="Cut each episode after this many seconds [default: drive to the goal].")
@click.option("--look-around/--no-look-around", default=True, show_default=True,
              help="Start each episode with a 360-degree turn in place.")
@click.option("--min-geodesic", default=5.0, show_default=True, type=float, help="Shortest start-goal path, m.")
@click.option("--max-geodesic", default=30.0, show_default=True, type=float, help="Longest start-goal path, m.")
@click.option("--min-ratio", default=1.1, show_default=True, type=float,
              help="Least geodesic / straight-line distance of a start-goal pair.")
@click.option("--free-space", type=click.Choice(["auto", "regions", "navmesh"]), default="auto", show_default=True,
              help="Where the robot may drive: the house's floor polygons (regions) or its habitat navmesh; auto: the "
                   "navmesh when the house has one.")
@click.option("--sensor", default="mp3d-depth90", show_default=True,
              help=sensor_help())
@click.option("--seed", default=0, show_default=True, type=limits.SEED, help="Seed: same seed, same bytes.")
@click.option("--height", default=1.0, show_default=True, type=float, help="Sensor height above the floor, m.")
@click.option("--robot-radius", default=0.25, show_default=True, type=float, help="Clearance radius, m.")
@click.option("--category", "categories", multiple=True, default=("chair",), show_default=True,
              help="mpcat40 class to label; repeat for several.")
@click.option("--backend", type=click.Choice(["embree", "open3d"]), default="embree", show_default=True,
              help="Raycasting backend.")
@click.option("--workers", default=1, show_default=True, type=limits.parallel_range(),
              help="Worker processes (at most 4 per core).")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def stream(root: Path, houses: tuple[str, ...], episodes: int, out: Path, rate: float, speed: float,
           turn_rate: float, accel: float, duration: float | None, look_around: bool, min_geodesic: float,
           max_geodesic: float, min_ratio: float, free_space: str, sensor: str, seed: int, height: float,
           robot_radius: float, categories: tuple[str, ...], backend: str, workers: int, as_json: bool,
           quiet: bool) -> None:
    """Drive a robot through houses and record what its sensor sees: KITTI-odometry-style sequences for streaming
    evaluation (detector stream-eval).

    Each episode: a start and a goal on one floor, a collision-free path with clearance, a unicycle drive under the
    speed / turn / acceleration limits (after a look-around), and a labelled frame every 1/--rate seconds, made with
    the same raycaster, labels and filters as `mpchair generate` (chairs rejected inside the sensor's labelled region
    become DontCare). Writes OUT/sequences/NN/{velodyne,label_2,label_dontcare,calib}/NNNNNN.*, times.txt,
    poses.txt and OUT/stream.json. Re-running the same command resumes; the output is byte-identical for a seed.

    \b
    Examples:
      mpchair stream --root houses/ --house X --house Y --episodes 5 --rate 10 --speed 0.5 --out stream/
      mpchair stream --root houses/ --house X --episodes 1 --speed 0 --duration 5 --out still/   # a still robot
    """
    from mpchair.core.atomic import check_writable
    from mpchair.core.heap import keep_freed_memory
    from mpchair.stream import StreamRequest
    from mpchair.stream import stream as run

    keep_freed_memory()  # this process makes frames itself when --workers 1 (see mpchair/core/heap.py)
    check_writable(out, folder=True)
    req = StreamRequest(
        root=root, houses=tuple(houses), episodes=episodes, out=out, rate=rate, speed=speed, turn_rate=turn_rate,
        accel=accel, sensor=sensor, seed=seed, height=height, robot_radius=robot_radius, categories=tuple(categories),
        look_around=look_around, duration=duration, min_geodesic=min_geodesic, max_geodesic=max_geodesic,
        min_ratio=min_ratio, free_space=free_space, backend=backend, workers=workers, progress=not quiet,
    )  # fmt: skip
    echo_summary(run(req), as_json)
