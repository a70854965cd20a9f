"""Benchmark: read a 3-million-face house in the Matterport3D release and habitat formats (target: <= 2 s for
``read_house``).

Writes, to a temporary folder, the ``.house`` of a synthetic house together with a ``.ply`` of 1.5 M vertices and
3 M faces in the real binary header layout (35-byte vertices, 25-byte faces) whose ``material_id`` values are that
house's segment ids, plus the matching ``.fsegs.json`` and ``.semseg.json``; the same mesh as habitat's
``_semantic.ply`` (15-byte vertices, 17-byte faces, ``object_id``); and the release files zipped as the download
script fetches them. Then times, best of ``--repeat``:

* ``read_ply``: bytes from disk → vertices / faces / per-face fields;
* ``read_house(side_files=False)``: ``.house`` + ``.ply`` + the face → object → category chain;
* ``read_house``: the same plus ``.fsegs.json`` (3 M ids) and ``.semseg.json``;
* the same ``read_house`` from ``house_segmentations.zip`` (members inflated under their size cap);
* ``read_semantic_ply`` and ``read_house`` of the habitat layout (``object_id`` → object, frame check).

Usage: ``python tools/bench_ply_read.py [--faces 3000000] [--repeat 3]``; prints one line per measurement.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np

from mpchair.core.atomic import write_bytes
from mpchair.matterport import find_houses, read_house
from mpchair.matterport.housefile import format_house
from mpchair.matterport.jsonfiles import encode_fsegs, encode_semseg
from mpchair.matterport.ply import encode_ply, encode_semantic_ply, read_ply, read_semantic_ply
from mpchair.synth import synthesize_house


def build(folder: Path, n_faces: int, seed: int = 0) -> str:
    """Write the benchmark house into ``folder``; return its id."""
    rng = np.random.default_rng(seed)
    syn = synthesize_house(seed, "BENCH3MFACE", levels=2)
    hf = syn.house_file
    n_verts = n_faces // 2
    lo, hi = hf.header.bbox[:3], hf.header.bbox[3:]
    vertices = rng.uniform(lo, hi, (n_verts, 3))
    faces = rng.integers(0, n_verts, (n_faces, 3))
    seg_ids = np.array([e.id for e in hf.segments], dtype=np.int64)
    seg_obj = np.array([e.object for e in hf.segments], dtype=np.int64)
    pick = rng.integers(0, len(seg_ids), n_faces)
    material = seg_ids[pick]
    segment = seg_obj[pick]
    mapping = np.array([hf.categories[o.category].mapping_index for o in hf.objects] + [-1], dtype=np.int64)
    category = mapping[segment]
    normals = np.tile(np.array([0.0, 0.0, 1.0]), (n_verts, 1))
    files = {
        ".house": format_house(hf).encode(),
        ".ply": encode_ply(vertices, faces, material, segment, category, normals=normals),
        ".fsegs.json": encode_fsegs(material, syn.id),
        ".semseg.json": encode_semseg(syn.id, list(syn.seg_groups)),
    }
    for suffix, data in files.items():
        write_bytes(folder / f"{syn.id}{suffix}", data)
    habitat = folder / "mp3d" / syn.id
    write_bytes(habitat / f"{syn.id}.house", files[".house"])
    write_bytes(habitat / f"{syn.id}_semantic.ply", encode_semantic_ply(vertices, faces, segment))
    zipped = folder / "zip" / "v1" / "scans" / syn.id
    zipped.mkdir(parents=True)
    with zipfile.ZipFile(zipped / "house_segmentations.zip", "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for suffix in files:
            zf.write(folder / f"{syn.id}{suffix}", f"{syn.id}/house_segmentations/{syn.id}{suffix}")
    return syn.id


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faces", type=int, default=3_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        hid = build(folder, args.faces)
        ply = folder / f"{hid}.ply"
        print(f"wrote {args.faces} faces, {ply.stat().st_size / 1e6:.1f} MB .ply in {time.perf_counter() - t0:.1f} s")
        src = find_houses(folder)[hid]  # release wins over the habitat copy below it
        zsrc = find_houses(folder / "zip")[hid]
        hsrc = find_houses(folder / "mp3d")[hid]
        sem = folder / "mp3d" / hid / f"{hid}_semantic.ply"

        def best(fn) -> tuple[float, float]:
            # Wall time, and this process's CPU time: on a shared, overloaded machine the CPU time is the number
            # that says what the code costs (the reader is single-threaded numpy).
            walls, cpus = [], []
            for _ in range(args.repeat):
                t, c = time.perf_counter(), time.process_time()
                fn()
                walls.append(time.perf_counter() - t)
                cpus.append(time.process_time() - c)
            return min(walls), min(cpus)

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rows = [
                ("read_ply (bytes from disk + parse)", best(lambda: read_ply(ply.read_bytes(), str(ply)))),
                ("read_house(side_files=False)", best(lambda: read_house(src, side_files=False))),
                ("read_house (+ .fsegs.json, .semseg.json)", best(lambda: read_house(src))),
                ("read_house from house_segmentations.zip", best(lambda: read_house(zsrc))),
                ("read_semantic_ply (habitat, disk + parse)", best(lambda: read_semantic_ply(sem.read_bytes()))),
                ("read_house (habitat layout)", best(lambda: read_house(hsrc))),
            ]
        for name, (wall, cpu) in rows:
            print(f"{name:<43}: wall {wall:.3f} s, cpu {cpu:.3f} s")


if __name__ == "__main__":
    main()
