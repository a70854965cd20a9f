"""``mpchair view`` (a frame: bird's-eye view, optional 3D view) and ``mpchair view-house`` (a house, top-down)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from mpchair.core.atomic import check_writable
from mpchair.core.clitools import FRAME_ID
from mpchair.core.errors import InputError

_CTX = {"help_option_names": ["-h", "--help"], "max_content_width": 110}


def _png(path: Path, option: str) -> Path:
    if path.suffix.lower() != ".png":
        raise InputError(f"{option} must name a .png file", path)
    check_writable(path)  # now, not after the drawing
    return path


#: The largest picture side (pixels) ``view`` draws: matplotlib's Agg canvas takes at most 2^16, and a 8192 x 8192
#: RGBA picture already needs 256 MiB.
MAX_PICTURE_SIDE = 8192


@click.command(context_settings=_CTX)
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--frame", "frame", type=FRAME_ID, help="Frame id (123 or 000123).")
@click.option("--sequence", default=None, metavar="NN",
              help="On a stream (mpchair stream): the sequence whose --frame to draw (DIR/sequences/NN); not needed "
                   "when the stream holds one sequence.")
@click.option("--out", type=click.Path(path_type=Path), help="Bird's-eye view PNG.")
@click.option("--rerun", "rerun_out", type=click.Path(path_type=Path), default=None,
              help="Instead of a picture: write DATASET (a stream or a dataset) as a Rerun recording (.rrd): per frame "
                   "the points, labelled boxes and sensor pose in the house frame (needs the rerun extra).")
@click.option("--mcap", "mcap_out", type=click.Path(path_type=Path), default=None,
              help="Instead of a picture: write DATASET (a stream or a dataset) as a ROS 2 bag (.mcap) for Foxglove or "
                   "ros2 bag play: per frame /points, /tf, /ground_truth (+ markers); a stream's /trajectory (needs "
                   "the ros extra).")
@click.option("--limit", type=int, default=None, help="With --rerun or --mcap on a dataset: only its first N frames.")
@click.option("--rate", type=float, default=10.0, show_default=True,
              help="With --mcap on a dataset: frames per second of the bag's timeline (a stream has its own times).")
@click.option("--results", type=click.Path(path_type=Path), default=None,
              help="Folder of KITTI result files (16 columns): detections drawn in red with scores.")
@click.option("--3d", "three_d", is_flag=True,
              help="Also render the 3D view (pyvista/VTK off-screen) to <out stem>-3d.png beside --out.")
@click.option("--fov-crop", is_flag=True, help="Show only points inside the image_2 field of view.")
@click.option("--size", type=int, nargs=2, default=(1000, 1000), show_default=True, metavar="W H",
              help="Picture size in pixels.")
@click.option("--extent", type=float, nargs=4, default=None, metavar="XMIN XMAX YMIN YMAX",
              help="BEV window (sensor frame, metres); default: fit the points and boxes.")
@click.option("--zmax", default="auto", show_default=True, metavar="Z|auto|none",
              help="Drop points at or above this z (sensor frame, metres). auto: on an mpchair dataset 2.0 m above the "
                   "floor (2.0 - the sensor height in its manifest: z = 1.0 at generate's default --height 1.0), so "
                   "the ceiling does not cover the room; nothing on other folders (real KITTI). none: keep every "
                   "point.")
@click.option("--json", "as_json", is_flag=True, help="Print what was drawn as JSON.")
def view(dataset: Path, frame: str | None, sequence: str | None, out: Path | None, rerun_out: Path | None,
         mcap_out: Path | None, limit: int | None, rate: float, results: Path | None, three_d: bool, fov_crop: bool,
         size: tuple[int, int], extent, zmax: str, as_json: bool) -> None:
    """Picture of one frame of DATASET: bird's-eye view of the scan (coloured by z) with its labelled boxes (green,
    class names) and, with --results, detections (red, dashed, scores). Headless; PNG output. With --rerun, a Rerun
    recording of a whole stream (mpchair stream) or dataset instead, to watch in the Rerun viewer; with --mcap, a
    ROS 2 bag of it, to open in Foxglove or replay with ros2 bag play (no ROS install needed to write it).

    \b
    Examples:
      mpchair view dataset/ --frame 3 --out out/frame.png --3d  # writes out/frame.png and out/frame-3d.png
      mpchair view dataset/ --frame 3 --out out/all.png --zmax none  # the ceiling too
      mpchair view stream/ --sequence 00 --frame 5 --out out/stream-frame.png
      mpchair view stream/ --rerun stream.rrd && rerun stream.rrd
      mpchair view stream/ --mcap stream.mcap && ros2 bag play -s mcap stream.mcap
    """
    if rerun_out is not None and mcap_out is not None:
        raise InputError("give --rerun or --mcap, not both")
    if rerun_out is not None or mcap_out is not None:
        fmt, rec_out = ("rerun", rerun_out) if rerun_out is not None else ("mcap", mcap_out)
        _record(fmt, dataset, rec_out, limit, rate, as_json, other=frame is not None or out is not None)
        return
    from mpchair.analysis.render import RenderError, default_zmax, frame_picture, stream_zmax

    if frame is None or out is None:
        raise InputError("give --frame and --out (a picture of one frame), or --rerun OUT.rrd, or --mcap OUT.mcap")
    fid = frame
    _png(out, "--out")
    if min(size) < 64 or max(size) > MAX_PICTURE_SIDE:  # 100000 x 100000 asked for 40 GB and ended in bad_alloc
        raise click.BadParameter(f"pictures need from 64 x 64 to {MAX_PICTURE_SIDE} x {MAX_PICTURE_SIDE} pixels",
                                 param_hint="--size")
    if extent is not None and not (all(math.isfinite(v) for v in extent) and extent[0] < extent[1]
                                   and extent[2] < extent[3]):  # a NaN window drew an empty picture, exit 0
        raise click.BadParameter(f"expected finite XMIN < XMAX and YMIN < YMAX metres, got {list(extent)}",
                                 param_hint="--extent")
    folder, split_dir, sequence = _frame_folder(dataset, sequence, fov_crop)
    if not (folder / split_dir / "velodyne" / f"{fid}.bin").is_file():
        raise InputError(f"frame {fid} not found (no {Path(split_dir) / 'velodyne' / (fid + '.bin')})", folder)
    out_3d = out.with_name(out.stem + "-3d.png") if three_d else None
    auto = zmax.strip().lower() == "auto"
    cut = (stream_zmax(dataset) if sequence is not None else default_zmax(dataset)) if auto else _zmax(zmax)
    try:
        info = frame_picture(folder, fid, out, results=results, out_3d=out_3d, fov_crop=fov_crop, size=tuple(size),
                             extent=tuple(extent) if extent else None, zmax=cut, split_dir=split_dir)
    except RenderError as e:
        raise click.ClickException(str(e)) from None
    if as_json:
        click.echo(json.dumps(info, indent=1))
    else:
        left_out = ("" if cut is None else f" ({info['above_zmax']} at z >= {cut:g} m left out; --zmax none draws "
                    "them)")
        click.echo(f"wrote {out}" + (f" and {out_3d}" if out_3d else "") + f": frame {fid}, {info['points']} points"
                   f"{left_out}, {info['boxes']} boxes" + ("" if info["detections"] is None else
                                                            f", {info['detections']} detections"))


def _frame_folder(dataset: Path, sequence: str | None, fov_crop: bool) -> tuple[Path, str, str | None]:
    """``(folder, split_dir, sequence)`` holding the frames to draw: a dataset's ``training/``, or a stream's
    ``sequences/NN/`` (``--sequence NN``; a stream of one sequence needs none). A stream of several sequences without
    ``--sequence`` is an :class:`InputError` that lists them."""
    is_stream = (dataset / "stream.json").is_file()
    if sequence is None and not is_stream:
        return dataset, "training", None
    if not is_stream:
        raise InputError("--sequence applies to a stream (mpchair stream); this folder has no stream.json", dataset)
    seqs = sorted(p.name for p in (dataset / "sequences").iterdir() if p.is_dir()) if (
        dataset / "sequences").is_dir() else []
    if sequence is None:
        if len(seqs) != 1:
            raise InputError(f"a stream: pick the sequence with --sequence NN (it has {', '.join(seqs) or 'none'}); "
                             "frame ids count from 000000 in each", dataset)
        (sequence,) = seqs
    if fov_crop:
        raise InputError("--fov-crop needs image_2, which a stream does not write", dataset)
    folder = dataset / "sequences" / sequence
    if not folder.is_dir():
        raise InputError(f"no sequence {sequence} (it has {', '.join(seqs) or 'none'})", dataset)
    return folder, "", sequence


def _zmax(value: str) -> float | None:
    """``--zmax`` other than ``auto``: ``none`` (no cut) or a finite number (sensor frame, metres)."""
    if value.strip().lower() == "none":
        return None
    try:
        z = float(value)
    except ValueError:
        z = math.nan
    if not math.isfinite(z):
        raise click.BadParameter(f"{value!r} is not a number, auto or none", param_hint="--zmax")
    return z


def _record(fmt: str, dataset: Path, out: Path, limit: int | None, rate: float, as_json: bool, other: bool) -> None:
    """``mpchair view --rerun`` / ``--mcap``: a stream (``stream.json``) or a dataset as a Rerun recording or a
    ROS 2 bag (``fmt``: ``"rerun"`` or ``"mcap"``)."""
    if other:
        what = "a recording" if fmt == "rerun" else "a bag"
        raise InputError(f"--{fmt} writes {what} of the whole folder; leave out --frame / --out")
    if limit is not None and limit < 1:
        raise InputError(f"--limit must be >= 1, got {limit}")
    is_stream = (Path(dataset) / "stream.json").is_file()
    kind = "stream" if is_stream else "dataset"
    if fmt == "rerun":
        from mpchair.recording import rerun as rec

        rec.check_rerun_path(out)
        info = rec.log_stream(dataset, out) if is_stream else rec.log_dataset(dataset, out, limit)
        info = {"recording": str(out), "kind": kind, **info}
        text = f"wrote {out}: {kind} {dataset}, {info['frames']} frames (open it with: rerun {out})"
    else:
        from mpchair.recording import mcap as rec

        rec.check_mcap_path(out)
        info = rec.log_stream(dataset, out) if is_stream else rec.log_dataset(dataset, out, limit, rate)
        info = {"bag": str(out), "kind": kind, **info}
        text = (f"wrote {out}: {kind} {dataset}, {info['frames']} frames, {sum(info['topics'].values())} messages on "
                f"{len(info['topics'])} topics (open it in Foxglove, or replay it: ros2 bag play -s mcap {out})")
    click.echo(json.dumps(info, indent=1) if as_json else text)


@click.command("view-house", context_settings=_CTX)
@click.option("--root", type=click.Path(path_type=Path), required=True,
              help="Matterport3D root (folders or house_segmentations.zip), as for mpchair houses.")
@click.option("--house", "house_id", required=True, help="House id.")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="PNG to write.")
@click.option("--category", default="chair", show_default=True, help="mpcat40 class to highlight (name or index).")
@click.option("--dataset", type=click.Path(path_type=Path), default=None,
              help="An mpchair dataset: draw the viewpoints (pose/ files) of its frames in this house (manifest.json).")
@click.option("--level", type=int, default=None, help="Only this level (index into the house's levels).")
@click.option("--size", type=int, nargs=2, default=None, metavar="W H",
              help="Picture size in pixels [default: 800 x 860 per level panel].")
@click.option("--json", "as_json", is_flag=True, help="Print what was drawn as JSON.")
def view_house(root: Path, house_id: str, out: Path, category: str, dataset: Path | None, level: int | None,
               size: tuple[int, int], as_json: bool) -> None:
    """Top-down picture of a house mesh: up-facing surfaces in grey by height (ceilings left out, walls as dark
    outlines), objects of --category in orange with their aligned boxes, and with --dataset the sensor viewpoints
    (blue arrows: position and heading). Headless; PNG output.

    \b
    Example:
      mpchair houses --root houses/             # lists the house ids under the root
      mpchair view-house --root houses/ --house ID --out out/house.png --dataset dataset/
    """
    from mpchair.analysis.render import house_picture

    _png(out, "--out")
    if size is not None and min(size) < 64:
        raise click.BadParameter("pictures need at least 64 x 64 pixels", param_hint="--size")
    info = house_picture(root, house_id, out, category=category, dataset=dataset, level=level,
                         size=tuple(size) if size else None)
    if as_json:
        click.echo(json.dumps(info, indent=1))
    else:
        click.echo(f"wrote {out}: house {house_id}, {info['faces']} faces, {info['objects']} {category} object(s)"
                   + ("" if info["viewpoints"] is None else f", {info['viewpoints']} viewpoints"))
