"""Embree with its instruction set pinned (mpchair/scan/embree.py): the same hits as embreex on the same ISA, and the
AVX2 machine's frame bit for bit on any x86-64 CPU with AVX2."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mpchair.core.cpu import cpu_flags
from mpchair.scan.embree import PinnedEmbreeScene, _api, requested_isa
from mpchair.synth import synthesize_house
from mpchair.synth.realism import CLEAN

BIN = Path(sys.executable).parent
PINNABLE = _api() is not None and requested_isa() is not None
needs_pin = pytest.mark.skipif(not PINNABLE, reason="Embree's ISA is pinned on Linux x86-64 CPUs with AVX2 only")

#: sha256 of frame 72 of house Ai8EB6Cgkn5 (``synth --houses 1 --seed 0``; ``generate --frames 400 --seed 0 --sensor
#: mp3d-depth90``): the accuracy study's scan 000472, one of the 23 of its 4,800 scans in which one point differs (by
#: 1.2e-7 m) between the AVX2 kernels and the AVX-512 ones. AVX2 is the AVX2-only EPYC's bytes (the study's record).
SCAN_472 = {"avx2": "0f70cbdbba9c290054ddbb3ca725185e08c7de7c273f02b60ebca06f26fd62b1",
            "avx512": "9aa2b7a262ae09a09fdd781ea8c729bb9ab7295b55e20b9ce1277f946a389bd8"}


@needs_pin
def test_the_binding_gives_embreexs_hits_on_the_same_isa():
    """Embree's own ISA choice through our binding and through embreex: the same face and the same float32 tfar for
    every one of 20,000 random rays through a house (and misses at -1 / 1e37)."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    house = synthesize_house(3, levels=1, realism=CLEAN)
    v = np.asarray(house.vertices, dtype=np.float64)
    v32 = (v - 0.5 * (v.min(0) + v.max(0))).astype(np.float32)
    f = np.asarray(house.faces)
    rng = np.random.default_rng(0)
    lo, hi = v32.min(0), v32.max(0)
    o = (lo + (hi - lo) * rng.random((20000, 3))).astype(np.float32)
    d = rng.normal(size=(20000, 3)).astype(np.float32)
    ours = PinnedEmbreeScene(v32, f, None).run(o, d, output=1)
    ours_face, ours_t = ours["primID"], ours["tfar"]
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=scene, vertices=v32, indices=f.astype(np.int32))
    theirs = scene.run(o, d, output=1)
    assert np.array_equal(ours_face, np.asarray(theirs["primID"], dtype=np.int64))
    assert np.array_equal(ours_t, np.asarray(theirs["tfar"], dtype=np.float32))
    assert 0 < (ours_face >= 0).sum() < len(d)  # hits and misses both exercised
    assert np.array_equal(PinnedEmbreeScene(v32, f, None).run(o, d), ours_face)  # faces only, as embreex's default
    shared_face = PinnedEmbreeScene(v32, f, None).run(o[:1], d)  # one origin for every ray
    assert np.array_equal(shared_face, scene.run(np.repeat(o[:1], len(d), axis=0), d).astype(np.int64))


def _scan_72(tmp_path: Path, isa: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "MPCHAIR_EMBREE_ISA"}
    if isa:
        env["MPCHAIR_EMBREE_ISA"] = isa
    houses, out = tmp_path / "houses", tmp_path / f"out-{isa}"
    if not houses.exists():
        subprocess.run([str(BIN / "mpchair"), "synth", "--out", str(houses), "--houses", "1", "--seed", "0"], env=env,
                       check=True, capture_output=True)
    subprocess.run([str(BIN / "mpchair"), "generate", "--root", str(houses), "--house", "Ai8EB6Cgkn5", "--frames",
                    "400", "--sensor", "mp3d-depth90", "--seed", "0", "--workers", "1", "--quiet", "--shard", "72/400",
                    "--out", str(out)], env=env, check=True, capture_output=True)
    return hashlib.sha256((out / "training" / "velodyne" / "000072.bin").read_bytes()).hexdigest()


@needs_pin
def test_the_avx2_machines_scan_comes_out_bit_for_bit(tmp_path):
    """The scan in which the AVX2 and AVX-512 kernels differ comes out as the AVX2 machine wrote it; on an AVX-512 CPU,
    Embree's own choice (``MPCHAIR_EMBREE_ISA=native``) gives the other bytes, so the pin is what makes them equal."""
    assert _scan_72(tmp_path, None) == SCAN_472["avx2"]
    if "avx512f" in cpu_flags():
        assert _scan_72(tmp_path, "native") == SCAN_472["avx512"]


def test_a_bad_isa_is_one_line_and_nothing_written(tmp_path):
    env = {**os.environ, "MPCHAIR_EMBREE_ISA": "avx9000"}
    out = tmp_path / "out"
    proc = subprocess.run([str(BIN / "mpchair"), "generate", "--root", str(tmp_path), "--frames", "1", "--out",
                           str(out)], env=env, capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "error: environment variable MPCHAIR_EMBREE_ISA='avx9000': choose one of sse2, sse4.2, avx, avx2, avx512, "
        "native (or unset it)"]
    assert not out.exists()
