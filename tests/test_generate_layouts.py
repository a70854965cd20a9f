"""``mpchair generate`` on either Matterport3D layout: the same house in the release and the habitat layout, same seed
and flags, gives byte-identical frames (only the manifest differs: it names and hashes the files read), and
``--viewpoints auto`` uses a habitat house's navmesh."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mpchair.dataset.generate import GenerateRequest, generate
from mpchair.dataset.manifest import read_manifest
from mpchair.matterport import find_houses, read_house
from mpchair.scan.navmesh import NavmeshSampler, island_labels, snap_points
from mpchair.synth import synthesize_house, write_house
from mpchair.synth.realism import CLEAN

FRAMES = 2


@pytest.fixture(scope="module")
def roots(tmp_path_factory):
    base = tmp_path_factory.mktemp("layouts")
    house = synthesize_house(7, levels=1, realism=CLEAN)  # flat floors: navmesh points lie on the mesh floor
    write_house(base / "release", house)
    write_house(base / "habitat", house, layout="habitat", zip_files=True)
    return base, house


def _gen(root: Path, house, out: Path, viewpoints: str):
    return generate(GenerateRequest(root=root, houses=(house.id,), frames=FRAMES, out=out, seed=4, progress=False,
                                    viewpoints=viewpoints))  # fmt: skip


def _frames(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted((out / "training").rglob("*")) if p.is_file()}


def test_both_layouts_give_byte_identical_frames(roots, tmp_path: Path) -> None:
    base, house = roots
    a = _gen(base / "release", house, tmp_path / "a", "auto")  # no navmesh in the release layout: regions
    b = _gen(base / "habitat" / "mp3d_habitat.zip", house, tmp_path / "b", "regions")
    assert a.complete and b.complete and a.kept >= FRAMES
    fa, fb = _frames(tmp_path / "a"), _frames(tmp_path / "b")
    assert len(fa) == 5 * FRAMES and fa == fb  # velodyne, label_2, calib, image_2, pose
    ma, mb = (read_manifest(tmp_path / d) for d in "ab")
    assert ma.frames == mb.frames and ma.config == mb.config
    ha, hb = ma.houses[house.id].files_sha256, mb.houses[house.id].files_sha256
    assert sorted(ha) == [f"{house.id}{s}" for s in (".fsegs.json", ".house", ".ply", ".semseg.json")]
    assert sorted(hb) == [f"{house.id}.house", f"{house.id}_semantic.ply"]  # regions: the navmesh is not read
    assert ha[f"{house.id}.house"] == hb[f"{house.id}.house"]


def test_auto_viewpoints_use_the_navmesh_of_a_habitat_house(roots, tmp_path: Path) -> None:
    base, house = roots
    s = _gen(base / "habitat", house, tmp_path / "nav", "auto")
    assert s.complete and s.kept >= FRAMES
    settings = json.loads((tmp_path / "nav" / ".generate.json").read_text())
    assert settings["viewpoint_sources"] == {house.id: "navmesh"}
    manifest = read_manifest(tmp_path / "nav")
    assert f"{house.id}.navmesh" in manifest.houses[house.id].files_sha256
    # Every pose stands 1 m above a point of a navmesh island of radius >= 1.5 m.
    nav = read_house(find_houses(base / "habitat")[house.id]).navmesh
    pos = np.array([np.array(r.pose)[:, 3] for r in manifest.frames])
    snapped, tri = snap_points(nav, pos - [0, 0, 1.0])
    np.testing.assert_allclose(snapped, pos - [0, 0, 1.0], atol=1e-5)
    assert (NavmeshSampler(nav).island_radius[island_labels(nav)[nav.triangle_poly[tri]]] >= 1.5).all()
    _gen(base / "habitat", house, tmp_path / "reg", "regions")
    assert _frames(tmp_path / "nav") != _frames(tmp_path / "reg")  # another candidate source: other frames
