"""Benchmark: read a 3-million-face house in the Matterport3D release format (target: <= 2 s for ``read_house``).

Writes, to a temporary folder, the ``.house`` of a synthetic house together with a ``.ply`` of 1.5 M vertices and
3 M faces in the real binary header layout (35-byte vertices, 25-byte faces) whose ``material_id`` values are that
house's segment ids, plus the matching ``.fsegs.json`` and ``.semseg.json``. Then times, best of ``--repeat``:

* ``read_ply``: bytes from disk → vertices / faces / per-face fields;
* ``read_house(side_files=False)``: ``.house`` + ``.ply`` + the face → object → category chain;
* ``read_house``: the same plus ``.fsegs.json`` (3 M ids) and ``.semseg.json``.

Usage: ``python tools/bench_ply_read.py [--faces 3000000] [--repeat 3]``; prints one line per measurement.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from mpchair.atomic import write_bytes
from mpchair.matterport import find_houses, read_house
from mpchair.matterport.housefile import format_house
from mpchair.matterport.jsonfiles import encode_fsegs, encode_semseg
from mpchair.matterport.ply import encode_ply, read_ply
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
        src = find_houses(folder)[hid]

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
            ]
        for name, (wall, cpu) in rows:
            print(f"{name:<42}: wall {wall:.3f} s, cpu {cpu:.3f} s")


if __name__ == "__main__":
    main()
