"""``mpchair stats``: pseudoimage density or box statistics of a KITTI-layout dataset (parse, call, print)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from mpchair.core.atomic import check_writable
from mpchair.core.errors import InputError


@click.command(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--density", "mode", flag_value="density", help="Pseudoimage density D per frame.")
@click.option("--boxes", "mode", flag_value="boxes", help="Box statistics (label_2 + scans [+ manifest.json]).")
@click.option("--config", "config", type=click.Path(path_type=Path), default=None,
              help="Detector experiment YAML: only its pillar grid is read and checked (model.point_cloud_range, "
                   "model.voxel_size, model.output_shape [ny, nx]); its other keys are not (detector train "
                   "validates the whole file).")
@click.option("--preset", type=click.Choice(["matterport", "kitti"]), default=None,
              help="Paper geometry: matterport (default; 0.05 m, 768 x 512 cells, ny x nx as the configs' "
                   "output_shape) or kitti (0.16 m, 504 x 440 padded).")
@click.option("--range", "pc_range", type=float, nargs=6, default=None,
              metavar="XMIN YMIN ZMIN XMAX YMAX ZMAX", help="Point cloud range (sensor frame, metres).")
@click.option("--voxel", type=float, nargs=2, default=None, metavar="VX VY", help="Pillar size (metres).")
@click.option("--grid", type=int, nargs=2, default=None, metavar="W H",
              help="Pseudoimage canvas (nx, ny); default: the range's own grid.")
@click.option("--split", default=None, help="Use ImageSets/<split>.txt (default: every training/velodyne/*.bin).")
@click.option("--fov-crop", is_flag=True, help="Crop scans to the image_2 field of view (calib + real image size).")
@click.option("--class", "classes", multiple=True,
              help="Only these label names, case-insensitive (--boxes; repeatable).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON (with per-frame values) instead of text.")
@click.option("--plot", type=click.Path(path_type=Path), default=None, help="Write a PNG figure here.")
def stats(dataset: Path, mode: str | None, config: Path | None, preset: str | None, pc_range, voxel, grid,
          split: str | None, fov_crop: bool, classes: tuple[str, ...], as_json: bool, plot: Path | None) -> None:
    """Statistics of DATASET (an mpchair dataset or a real KITTI folder).

    \b
    --density: D = non-empty pillars / (W x H) per frame, pillars indexed exactly as the detector's voxelizer
      (mpchair.geometry.pillar_coords: min <= p < max, floor((p - min) / voxel)). Geometry from --config, or
      --preset, or --range/--voxel[/--grid]; default: Matterport-Chair [0,-19,-2,25,19,2], 0.05 m, 768 x 512
      (ny x nx).
    --boxes: boxes per frame, mean/std of l, w, h (the anchor), points per box, distance, yaw, occlusion,
      truncation, and the manifest's rejected-box reasons.

    \b
    Examples:
      mpchair stats --density dataset/ --plot out/density.png
      mpchair stats --density tests/data/kitti --preset kitti --json
      mpchair stats --boxes dataset/ --plot out/boxes.png
    """
    from mpchair.analysis import render
    from mpchair.analysis import stats as lib

    if mode is None:
        raise click.UsageError("choose --density or --boxes")
    if plot is not None and plot.suffix.lower() != ".png":
        raise InputError("--plot must name a .png file", plot)
    if plot is not None:
        check_writable(plot)
    if mode == "density":
        given = [name for name, v in (("--config", config), ("--preset", preset), ("--range", pc_range)) if v]
        if len(given) > 1:
            raise click.UsageError(f"{' and '.join(given)} are exclusive: give one")
        if (voxel or grid) and not pc_range:
            raise click.UsageError("--voxel/--grid need --range")
        if pc_range and not voxel:
            raise click.UsageError("--range needs --voxel")
        if config is not None:
            geometry = lib.geometry_from_model_yaml(config)
        elif pc_range:
            real = _real_grid(pc_range, voxel)
            geometry = lib.PseudoimageGeometry(tuple(pc_range), tuple(voxel), tuple(grid) if grid else real)
        else:
            geometry = lib.PRESETS[preset or "matterport"]
        result = lib.density_stats(dataset, geometry, split=split, fov_crop=fov_crop)
        if plot is not None:
            render.plot_density_histogram(result, plot)
        text = lib.format_density(result)
    else:
        if config or preset or pc_range or voxel or grid or fov_crop:
            raise click.UsageError("--config/--preset/--range/--voxel/--grid/--fov-crop apply to --density only")
        result = lib.box_stats(dataset, split=split, classes=list(classes) or None)
        if plot is not None:
            render.plot_box_stats(result, plot)
        text = lib.format_boxes(result)
    click.echo(json.dumps(result, indent=1) if as_json else text)
    if plot is not None and not as_json:
        click.echo(f"wrote {plot}")


def _real_grid(pc_range, voxel) -> tuple[int, int]:
    from mpchair.geometry import grid_size

    try:
        return grid_size(pc_range, voxel)
    except ValueError as e:
        raise InputError(f"--range/--voxel: {e}") from None
