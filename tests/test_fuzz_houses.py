"""A seeded fuzz over mutated habitat houses, folders and zips (issue 33's audit family): whatever the bytes, the
reader either reads the house or raises one-line :class:`InputError` — never another exception, never a hang."""

from __future__ import annotations

import io
import os
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mpchair.core.errors import InputError
from mpchair.matterport import find_houses, read_house
from mpchair.scan.navmesh import NavmeshSampler
from mpchair.synth import plan_houses, synthesize_house, write_house

SEED = 2026
FILES = (".house", "_semantic.ply", ".navmesh")
N_MUTATIONS = int(os.environ.get("MPCHAIR_FUZZ_N", "40"))  # more for a deeper local run


@pytest.fixture(scope="module")
def habitat_house(tmp_path_factory) -> tuple[str, dict[str, bytes]]:
    root = tmp_path_factory.mktemp("fuzz")
    hid, hs, lv = plan_houses(1, 3)[0]
    write_house(root, synthesize_house(hs, hid, levels=lv), layout="habitat")
    folder = next(root.rglob(f"{hid}.house")).parent
    return hid, {s: (folder / f"{hid}{s}").read_bytes() for s in FILES}


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """One of: flip bytes, cut the tail, cut a slice out, repeat a slice, insert junk, overwrite a token."""
    b = bytearray(data)
    kind = rng.integers(6)
    at = int(rng.integers(len(b)))
    if kind == 0:
        for i in rng.integers(len(b), size=int(rng.integers(1, 16))):
            b[i] = int(rng.integers(256))
    elif kind == 1:
        del b[at:]
    elif kind == 2:
        del b[at : at + int(rng.integers(1, 4096))]
    elif kind == 3:
        b[at:at] = b[at : at + int(rng.integers(1, 4096))]
    elif kind == 4:
        b[at:at] = rng.integers(256, size=int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
    else:
        b[at : at + 8] = rng.choice([b"nan     ", b"-1      ", b"1e300   ", b"99999999", b"\x00" * 8, b"\n\n\n\n"])
    return bytes(b)


def _read(root: Path, hid: str) -> None:
    found = find_houses(root)
    if hid not in found:  # a mutated member name: the reader found another (or no) house, which is its right
        raise InputError(f"no house {hid} (found {sorted(found)})", root)
    house = read_house(found[hid])
    if house.navmesh is not None:  # what `generate --viewpoints navmesh` and `mpchair houses` do next
        try:
            NavmeshSampler(house.navmesh)
        except ValueError:
            pass  # "no island large enough": generate and houses report it in words


def _expect_clean(root: Path, hid: str, what: str) -> str:
    t0 = time.monotonic()
    try:
        _read(root, hid)
        outcome = "read"
    except InputError as e:
        assert "\n" not in str(e), (what, str(e))
        outcome = "refused"
    assert time.monotonic() - t0 < 30, what
    return outcome


@pytest.mark.parametrize("suffix", FILES)
def test_mutated_habitat_files_are_read_or_refused_in_one_line(habitat_house, tmp_path, suffix):
    hid, files = habitat_house
    rng = np.random.default_rng([SEED, FILES.index(suffix)])
    outcomes = []
    for k in range(N_MUTATIONS):
        folder = tmp_path / f"m{k}" / "mp3d" / hid
        folder.mkdir(parents=True)
        for s, data in files.items():
            (folder / f"{hid}{s}").write_bytes(mutate(data, rng) if s == suffix else data)
        outcomes.append(_expect_clean(tmp_path / f"m{k}", hid, f"{suffix} mutation {k}"))
    # the fuzz reaches the checks (a mutation that changes nothing proves nothing), and not every mutation is fatal
    assert outcomes.count("refused") >= 10, outcomes


def test_mutated_habitat_zips_are_read_or_refused_in_one_line(habitat_house, tmp_path):
    hid, files = habitat_house
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for s, data in files.items():
            zf.writestr(f"mp3d/{hid}/{hid}{s}", data)
    good = buf.getvalue()
    rng = np.random.default_rng([SEED, 99])
    outcomes = []
    for k in range(N_MUTATIONS):
        z = tmp_path / f"z{k}" / "mp3d_habitat.zip"
        z.parent.mkdir()
        z.write_bytes(mutate(good, rng))
        outcomes.append(_expect_clean(z, hid, f"zip mutation {k}"))
    assert outcomes.count("refused") >= 10, outcomes
