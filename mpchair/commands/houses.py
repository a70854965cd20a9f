"""``mpchair houses``: list the Matterport3D houses found under a root, or one house's objects (parse, call, print)."""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import click

from mpchair.errors import InputError


def _house_summary(house) -> dict:
    return {
        "id": house.id,
        "version": house.version,
        "levels": len(house.levels),
        "regions": len(house.regions),
        "objects": len(house.objects),
        "faces": int(len(house.faces)),
        "vertices": int(len(house.vertices)),
        "unlabelled_faces": house.unlabelled_faces,
        "label_mismatch_rate": house.label_mismatch_rate,
        "objects_by_category": house.objects_by_category(),
        "warnings": list(house.warnings),
    }


def _object_row(o) -> dict:
    return {
        "index": o.index,
        "id": o.id,
        "region": o.region,
        "raw_category": o.raw_category,
        "mpcat40_index": o.mpcat40_index,
        "mpcat40_name": o.mpcat40_name,
        "aligned_box": [float(v) for v in o.aligned_box],
        "tilt_deg": o.tilt_deg,
    }


@click.command(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.option("--root", required=True, type=click.Path(path_type=Path),
              help="Download root (v1/scans/<id>/...), a scans/ folder, a house folder or a house_segmentations.zip.")
@click.option("--house", "house_id", default=None, help="Only this house id.")
@click.option("--objects", "list_objects", is_flag=True, help="List the objects of --house with their aligned boxes.")
@click.option("--category", "categories", multiple=True,
              help="With --objects: only these mpcat40 classes (name or index; repeatable), e.g. chair or 3.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
def houses(root: Path, house_id: str | None, list_objects: bool, categories: tuple[str, ...], as_json: bool) -> None:
    """List every house found under ROOT: levels, regions, objects, faces, vertices, unlabelled faces and objects
    per mpcat40 class. With --house ID --objects: that house's objects and their vertically aligned boxes
    [x, y, z_center, l, w, h, yaw] (world frame, metres, radians CCW from +x).

    \b
    JSON shapes:
      {"houses": [{"id", "levels", "regions", "objects", "faces", "vertices", "unlabelled_faces",
                   "objects_by_category": {"chair": n, ...}, ...}]}
      --objects: {"id", "objects": [{"index", "id", "region", "raw_category", "mpcat40_index",
                   "mpcat40_name", "aligned_box": [7 numbers], "tilt_deg"}]}

    \b
    Examples:
      mpchair houses --root houses/ --json
      mpchair houses --root houses/ --house 17DRP5sb8fy --objects --category chair
    """
    from tqdm import tqdm

    from mpchair.matterport import find_houses, objects_of, read_house, resolve_categories

    if categories and not list_objects:
        raise click.UsageError("--category needs --objects")
    if list_objects and house_id is None:
        raise click.UsageError("--objects needs --house ID")
    wanted = resolve_categories(categories) if categories else None
    found = find_houses(root)
    if house_id is not None:
        if house_id not in found:
            raise InputError(f"house {house_id!r} not found (found: {', '.join(found)})", root)
        found = {house_id: found[house_id]}

    with warnings.catch_warnings():
        # Warnings are reported in the output (text and JSON), not as Python warnings on stderr.
        warnings.simplefilter("ignore")
        if list_objects:
            house = read_house(found[house_id], side_files=False)
            objs = objects_of(house, sorted(wanted)) if wanted else house.objects
            if as_json:
                click.echo(json.dumps({"id": house.id, "objects": [_object_row(o) for o in objs]}, indent=1))
                return
            click.echo(f"{house.id}: {len(objs)} objects")
            click.echo(f"{'index':>5} {'mpcat40':<14} {'raw category':<22} {'x':>8} {'y':>8} {'z':>7} "
                       f"{'l':>5} {'w':>5} {'h':>5} {'yaw':>7}")  # fmt: skip
            for o in objs:
                x, y, z, l, w, h, yaw = o.aligned_box
                click.echo(f"{o.index:>5} {o.mpcat40_name:<14} {o.raw_category[:22]:<22} {x:8.3f} {y:8.3f} {z:7.3f} "
                           f"{l:5.2f} {w:5.2f} {h:5.2f} {yaw:7.3f}")  # fmt: skip
            return

        rows = []
        bar = tqdm(found.values(), desc="reading houses", unit="house", disable=len(found) < 2 or None,
                   file=sys.stderr)  # fmt: skip
        for src in bar:
            rows.append(_house_summary(read_house(src, side_files=False)))
    if as_json:
        click.echo(json.dumps({"houses": rows}, indent=1))
        return
    for r in rows:
        cats = ", ".join(f"{k} {v}" for k, v in r["objects_by_category"].items()) or "none"
        click.echo(
            f"{r['id']}: ASCII {r['version']}, {r['levels']} levels, {r['regions']} regions, {r['objects']} objects, "
            f"{r['faces']} faces, {r['vertices']} vertices, {r['unlabelled_faces']} unlabelled faces, "
            f"label mismatch {r['label_mismatch_rate']:.2%}"
        )
        click.echo(f"    objects per class: {cats}")
        for w in r["warnings"]:
            click.echo(f"    warning: {w}")
