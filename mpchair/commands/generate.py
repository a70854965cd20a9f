"""``mpchair generate``: raycast houses into a KITTI-format Matterport-Chair dataset (parse, call, print)."""

from __future__ import annotations

import re
from pathlib import Path

import click

from mpchair.commands import echo_summary, sensor_help
from mpchair.core import limits
from mpchair.core.errors import InputError


def _parse_shard(value: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", value)
    if not m:
        raise InputError(f"--shard must look like i/N (e.g. 0/4), got {value!r}")
    return int(m.group(1)), int(m.group(2))


@click.command(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.option("--root", required=True, type=click.Path(path_type=Path),
              help="Where the houses are, searched at any depth: the folder holding v1, v1, v1/scans, one scan folder, "
                   "a house_segmentations.zip, mp3d_habitat.zip or its extracted mp3d/ folder (release or habitat "
                   "layout; see mpchair houses).")
@click.option("--house", "houses", multiple=True, required=True, help="House id; repeat for several houses.")
@click.option("--frames", required=True, type=int, help="Frames per house.")
@click.option("--out", required=True, type=click.Path(file_okay=False, path_type=Path), help="Dataset folder.")
@click.option("--sensor", default="mp3d-depth90", show_default=True,
              help=sensor_help())
@click.option("--seed", default=0, show_default=True, type=limits.SEED, help="Seed: same seed, same bytes.")
@click.option("--height", default=1.0, show_default=True, type=float,
              help="Sensor height above the floor, metres (1.0 = paper, 1.25 = original code).")
@click.option("--robot-radius", default=0.25, show_default=True, type=float, help="Clearance radius, metres.")
@click.option("--category", "categories", multiple=True, default=("chair",), show_default=True,
              help="mpcat40 class to label; repeat for several.")
@click.option("--keep-empty", is_flag=True, help="Keep frames without a kept box (they get one DontCare row).")
@click.option("--split-mode", type=click.Choice(["frame", "house", "paper"]), default="frame", show_default=True,
              help="frame: seeded 60/20/20 over frames; house: whole houses per split (no house shared; seeded "
                   "60/20/20 of the houses, or --val-house / --test-house); paper: the paper's layout.")
@click.option("--val-house", "val_houses", multiple=True,
              help="House (one of --house) held out for the val split; repeat for several. Implies --split-mode "
                   "house; every house not named for val or test trains.")
@click.option("--test-house", "test_houses", multiple=True,
              help="House (one of --house) held out for the test split; repeat for several (implies --split-mode "
                   "house).")
@click.option("--backend", type=click.Choice(["embree", "open3d"]), default="embree", show_default=True,
              help="Raycasting backend.")
@click.option("--workers", default=1, show_default=True, type=limits.parallel_range(),
              help="Worker processes (at most 4 per core).")
@click.option("--shard", default="0/1", show_default=True,
              help="Make only block i of N contiguous blocks of frames (cluster array jobs, one process per shard, "
                   "all into one --out); the shard that finds every frame made writes ImageSets and the manifest.")
@click.option("--viewpoints", type=click.Choice(["auto", "regions", "navmesh"]), default="auto", show_default=True,
              help="Where robot positions are drawn: regions = inside the .house region floor polygons; navmesh = on "
                   "habitat's <id>.navmesh islands of radius >= 1.5 m (as habitat's PointNav episodes); auto = navmesh "
                   "when the house has one, else regions. The same validity checks apply to both.")
@click.option("--max-attempts", default=400, show_default=True, type=click.IntRange(1),
              help="Viewpoint candidates per frame before giving up.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def generate(root: Path, houses: tuple[str, ...], frames: int, out: Path, sensor: str, seed: int, height: float,
             robot_radius: float, categories: tuple[str, ...], keep_empty: bool, split_mode: str,
             val_houses: tuple[str, ...], test_houses: tuple[str, ...], backend: str,
             workers: int, shard: str, viewpoints: str, max_attempts: int, as_json: bool, quiet: bool) -> None:
    """Generate a Matterport-Chair dataset in KITTI layout by raycasting the labelled house meshes (Embree).

    Writes OUT/training/{velodyne,label_2,calib,image_2,pose}/NNNNNN.*, OUT/ImageSets/{train,val,test}.txt and
    OUT/manifest.json. Re-running the same command resumes an interrupted run; the result is byte-identical for a
    given seed whatever --workers is, and whichever layout (release or habitat) the house was read from (only the
    manifest differs: it names and hashes the files read).

    \b
    Examples:
      mpchair generate --root houses/ --house X --frames 200 --out dataset/
      mpchair generate --root mp3d_habitat.zip --house X --frames 200 --viewpoints navmesh --out dataset/
      mpchair generate --root mp3d/ --house A --house B --frames 3750 --height 1.25 --split-mode paper --out mpc/
      mpchair generate --root mp3d/ --house A --house B --house C --house D --frames 500 \
          --val-house C --test-house D --out mpc/   # house-disjoint: A, B train; C val; D test
      mpchair generate ... --shard 3/8        # one job of a cluster array
    """
    from mpchair.core.atomic import check_writable
    from mpchair.core.heap import keep_freed_memory
    from mpchair.dataset.generate import GenerateRequest
    from mpchair.dataset.generate import generate as run

    keep_freed_memory()  # this process makes frames itself when --workers 1 (see mpchair/core/heap.py)

    check_writable(out, folder=True)
    if (val_houses or test_houses) and (click.get_current_context().get_parameter_source("split_mode")
                                        == click.core.ParameterSource.DEFAULT):
        split_mode = "house"
    req = GenerateRequest(
        root=root, houses=tuple(houses), frames=frames, out=out, sensor=sensor, seed=seed, height=height,
        robot_radius=robot_radius, categories=tuple(categories), keep_empty=keep_empty, split_mode=split_mode,
        val_houses=tuple(val_houses), test_houses=tuple(test_houses),
        backend=backend, workers=workers, shard=_parse_shard(shard), max_attempts=max_attempts, progress=not quiet,
        viewpoints=viewpoints,
    )  # fmt: skip
    echo_summary(run(req), as_json)
