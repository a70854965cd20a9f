"""``mpchair houses``: list the Matterport3D houses found under a root, or one house's objects (parse, call, print)."""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import click

from mpchair.core.errors import InputError


def _navmesh_summary(house) -> dict | None:
    """The house's navmesh (None without one): islands, those --viewpoints navmesh samples (radius >= 1.5 m, where
    habitat's PointNav episodes start) and the walkable area (horizontal, m²)."""
    if house.navmesh is None:
        return None
    from mpchair.scan.navmesh import NavmeshSampler, island_labels, island_radii

    try:
        s = NavmeshSampler(house.navmesh)
        islands, big, area = len(s.island_radius), len(s.islands), float(s.island_area.sum())
    except ValueError:  # no island large enough: still describe the others
        try:
            s = NavmeshSampler(house.navmesh, min_island_radius=0.0)
            islands, big, area = len(s.island_radius), 0, float(s.island_area.sum())
        except ValueError:  # not one triangle with an area (coincident vertices): nothing walkable
            islands = len(island_radii(house.navmesh, island_labels(house.navmesh)))
            big, area = 0, 0.0
    return {
        "version": house.navmesh.version,
        "islands": islands,
        "islands_sampled": big,
        "walkable_area_m2": round(area, 3),
    }


def _house_summary(house) -> dict:
    return {
        "id": house.id,
        "layout": house.layout,
        "version": house.version,
        "levels": len(house.levels),
        "regions": len(house.regions),
        "objects": len(house.objects),
        "faces": int(len(house.faces)),
        "vertices": int(len(house.vertices)),
        "unlabelled_faces": house.unlabelled_faces,
        "label_mismatch_rate": house.label_mismatch_rate,
        "objects_by_category": house.objects_by_category(),
        "navmesh": _navmesh_summary(house),
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
              help="Where the houses are, searched at any depth: the folder holding v1, v1, v1/scans, one scan folder, "
                   "a house_segmentations.zip, mp3d_habitat.zip or its extracted mp3d/ (or mp3d/<id>/) folder.")
@click.option("--house", "house_id", default=None, help="Only this house id.")
@click.option("--objects", "list_objects", is_flag=True, help="List the objects of --house with their aligned boxes.")
@click.option("--category", "categories", multiple=True,
              help="With --objects: only these mpcat40 classes (name or index; repeatable), e.g. chair or 3.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
def houses(root: Path, house_id: str | None, list_objects: bool, categories: tuple[str, ...], as_json: bool) -> None:
    """List every house found under ROOT, in the release (house_segmentations) or habitat (mp3d_habitat) layout:
    levels, regions, objects, faces, vertices, unlabelled faces, objects per mpcat40 class and, when the house has a
    .navmesh, its islands. With --house ID --objects: that house's objects and their vertically aligned boxes
    [x, y, z_center, l, w, h, yaw] (world frame, metres, radians CCW from +x).

    \b
    JSON shapes:
      {"houses": [{"id", "layout": "release" | "habitat", "levels", "regions", "objects", "faces", "vertices",
                   "unlabelled_faces", "label_mismatch_rate" (null for habitat),
                   "objects_by_category": {"chair": n, ...},
                   "navmesh": null | {"version", "islands", "islands_sampled" (radius >= 1.5 m),
                                      "walkable_area_m2"}, ...}]}
      --objects: {"id", "objects": [{"index", "id", "region", "raw_category", "mpcat40_index",
                   "mpcat40_name", "aligned_box": [7 numbers], "tilt_deg"}]}

    \b
    Examples:
      mpchair houses --root houses/ --json
      mpchair houses --root /data/mp3d_habitat.zip
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
            house = read_house(found[house_id], side_files=False, navmesh=False)
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
        rate = r["label_mismatch_rate"]
        click.echo(
            f"{r['id']} ({r['layout']}): ASCII {r['version']}, {r['levels']} levels, {r['regions']} regions, "
            f"{r['objects']} objects, {r['faces']} faces, {r['vertices']} vertices, {r['unlabelled_faces']} unlabelled "
            f"faces, label mismatch {'n/a' if rate is None else f'{rate:.2%}'}"
        )
        click.echo(f"    objects per class: {cats}")
        nav = r["navmesh"]
        if nav is not None:
            click.echo(f"    navmesh: version {nav['version']}, {nav['islands']} islands "
                       f"({nav['islands_sampled']} with radius >= 1.5 m), "
                       f"{nav['walkable_area_m2']:.1f} m2 walkable")  # fmt: skip
        for w in r["warnings"]:
            click.echo(f"    warning: {w}")
