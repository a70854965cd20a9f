"""``mpchair synth``: write procedural houses in the exact Matterport3D release or habitat format (parse, call,
print)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from mpchair.core import limits


@click.command(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.option("--out", "out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Output root; houses go to OUT/v1/scans/<id>/house_segmentations/ (habitat: OUT/mp3d/<id>/).")
@click.option("--houses", "n", default=3, show_default=True, type=click.IntRange(1, 1000), help="Number of houses.")
@click.option("--seed", default=0, show_default=True, type=limits.SEED, help="Seed (same seed: same bytes).")
@click.option("--layout", type=click.Choice(["release", "habitat"]), default="release", show_default=True,
              help="release: house_segmentations files; habitat: mp3d/<id>/<id>_semantic.ply, .house and .navmesh.")
@click.option("--zip", "zip_files", is_flag=True,
              help="Write the zips the download script fetches instead: OUT/v1/scans/<id>/house_segmentations.zip "
                   "(habitat: one OUT/mp3d_habitat.zip).")
@click.option("--subdivide", default=0, show_default=True, type=click.IntRange(0, 6),
              help="Split every triangle into 4, this many times (x4 faces each; 3-4 give real Matterport3D face "
                   "counts, ~0.4-1.7 M, for benchmarks). Same geometry and labels.")
@click.option("--realism", "realism_name", type=click.Choice(["clean", "default"]), default="default",
              show_default=True,
              help="Reconstruction artifacts and clutter (mpchair.synth.realism): default = calibrated to Matterport3D "
                   "scans (noise, holes, label bleed, clutter); clean = the plain procedural houses (tests).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON: {\"root\", \"houses\": [ids]}.")
def synth(out: Path, n: int, seed: int, layout: str, zip_files: bool, subdivide: int, realism_name: str,
          as_json: bool) -> None:
    """Write N synthetic houses: several furnished rooms joined by doors, windows, a ceiling hole, optionally a
    second level with stairs, 10-30 chairs of five styles plus stools, sofas, tables, cabinets and beds, a random
    global offset and yaw. Release files: <id>.house (ASCII 1.1, every record kind), <id>.ply (binary, per-face
    material_id / segment_id / category_id), <id>.fsegs.json and <id>.semseg.json. Habitat files: the same
    <id>.house, <id>_semantic.ply (the same mesh, per-face object_id) and <id>.navmesh (Recast/Detour MSET, built
    from the free floor). The same seed gives the same houses in both layouts. --realism default (the default) adds
    Matterport3D-like reconstruction artifacts (vertex noise, wavy walls, holes, label bleed, fragments) and clutter
    (plants, shelving, counters, objects, doors); --realism clean writes the plain houses.

    \b
    Examples:
      mpchair synth --out houses/ --houses 4 --seed 1
      mpchair synth --out clean/ --houses 4 --seed 1 --realism clean
      mpchair synth --out habitat/ --houses 4 --seed 1 --layout habitat --zip
      mpchair houses --root houses/
    """
    from tqdm import tqdm

    from mpchair.synth import write_synthetic_houses
    from mpchair.synth.realism import realism_preset

    with tqdm(total=n, desc="synthesizing houses", unit="house", file=sys.stderr, disable=None) as bar:
        ids = write_synthetic_houses(out, n, seed, zip_files=zip_files, progress=bar.update, subdivide=subdivide,
                                     layout=layout, realism=realism_preset(realism_name))
    if as_json:
        click.echo(json.dumps({"root": str(out), "houses": ids}))
    else:
        for hid in ids:
            click.echo(hid)
