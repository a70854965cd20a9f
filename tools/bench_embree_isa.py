"""Benchmark the Embree binding with its ISA pinned (mpchair/scan/embree.py) against embreex; asserts nothing.

The same random rays (origins uniform in the house's bounding box, directions uniform) are cast through three scenes of
one synthetic house (``synth --seed 0``, default realism), interleaved per batch in one process, one thread each:

* ``embreex``: embreex's own ``EmbreeScene.run`` (Embree's own ISA choice; what the raycaster used before the pin);
* ``pinned``: our binding with the pinned ISA (``avx2`` on x86-64 CPUs with AVX2, the raycaster's default now);
* ``native``: our binding with Embree's own ISA choice (the binding's overhead alone against embreex).

Prints per scene the median time per batch and the rate (Mrays/s), and the ratios to embreex. Also checks, on the
same rays, that ``native`` gives embreex's faces and distances bit for bit and counts the rays on which ``pinned``
differs (another ISA's rounding).

Usage: ``python tools/bench_embree_isa.py [--batches 40] [--rays 100000] [--seed 0] [--json-out FILE]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batches", type=int, default=40, help="timed batches per scene (interleaved)")
    p.add_argument("--rays", type=int, default=100_000, help="rays per batch")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json-out", type=Path, default=None, help="write the result as JSON to this file")
    args = p.parse_args(argv)
    if not (1 <= args.batches <= 10_000 and 1 <= args.rays <= 10_000_000):
        p.error("--batches must be in 1..10000 and --rays in 1..10000000")

    import numpy as np
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    from mpchair.scan.embree import PinnedEmbreeScene, _api, requested_isa
    from mpchair.synth import synthesize_house

    if _api() is None:
        print("error: embreex's Embree library was not found: nothing to compare", file=sys.stderr)
        return 2
    isa = requested_isa() or "native"
    house = synthesize_house(args.seed)  # the default (realistic) house
    v = np.asarray(house.vertices, dtype=np.float64)
    v32 = (v - 0.5 * (v.min(0) + v.max(0))).astype(np.float32)
    f = np.asarray(house.faces)
    emb = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=emb, vertices=v32, indices=f.astype(np.int32))
    scenes = {"embreex": emb, "pinned": PinnedEmbreeScene(v32, f, None if isa == "native" else isa),
              "native": PinnedEmbreeScene(v32, f, None)}
    rng = np.random.default_rng(args.seed)
    lo, hi = v32.min(0), v32.max(0)

    def batch():
        o = (lo + (hi - lo) * rng.random((args.rays, 3))).astype(np.float32)
        d = rng.normal(size=(args.rays, 3)).astype(np.float32)
        return o, d

    o, d = batch()
    for s in scenes.values():  # compile and warm up
        s.run(o[:1000], d[:1000])
    times = {k: [] for k in scenes}
    same_native, differ_pinned, hits = True, 0, 0
    for _ in range(args.batches):
        o, d = batch()
        out = {}
        for k, s in scenes.items():
            t = time.perf_counter()
            out[k] = s.run(o, d, output=1)
            times[k].append(time.perf_counter() - t)
        ref_face = np.asarray(out["embreex"]["primID"], dtype=np.int64)
        ref_t = np.asarray(out["embreex"]["tfar"], dtype=np.float32)
        same_native &= bool(np.array_equal(out["native"]["primID"], ref_face)
                            and np.array_equal(out["native"]["tfar"], ref_t))
        differ_pinned += int(((out["pinned"]["primID"] != ref_face) | (out["pinned"]["tfar"] != ref_t)).sum())
        hits += int((ref_face >= 0).sum())
    med = {k: float(np.median(v)) for k, v in times.items()}
    result = {
        "isa_pinned": isa, "rays_per_batch": args.rays, "batches": args.batches, "threads": 1,
        "median_ms": {k: round(v * 1e3, 2) for k, v in med.items()},
        "mrays_per_s": {k: round(args.rays / v / 1e6, 2) for k, v in med.items()},
        "time_over_embreex": {k: round(v / med["embreex"], 3) for k, v in med.items()},
        "native_equals_embreex": same_native,
        "pinned_rays_that_differ_from_embreex": differ_pinned, "rays": args.rays * args.batches, "hits": hits,
    }
    for k in scenes:
        print(f"{k:8s} median {result['median_ms'][k]:8.2f} ms per {args.rays} rays  {result['mrays_per_s'][k]:6.2f} "
              f"Mrays/s  time / embreex {result['time_over_embreex'][k]:.3f}")
    print(f"native == embreex bit for bit: {same_native}; pinned ({isa}) differs from embreex on "
          f"{differ_pinned} of {result['rays']} rays ({hits} hits)")
    if args.json_out:
        args.json_out.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
