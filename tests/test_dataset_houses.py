"""``mpchair.dataset.houses.load_run_houses``: the houses of a run, read once and hashed by one rule per command
(``generate``: the files read; ``stream``: the files of the layout), with the errors both commands share."""

from __future__ import annotations

import hashlib
import re

import pytest

from mpchair import __version__
from mpchair.core.errors import InputError
from mpchair.dataset.houses import RunHouses, load_run_houses, package_versions
from mpchair.matterport.categories import resolve_categories
from mpchair.synth import synthesize_house, write_house

CHAIR = resolve_categories(["chair"])


@pytest.fixture(scope="module")
def roots(tmp_path_factory):
    base = tmp_path_factory.mktemp("run_houses")
    a, b = synthesize_house(7, levels=1), synthesize_house(17, levels=1)
    for h in (a, b):
        write_house(base / "release", h)
    write_house(base / "habitat", a, layout="habitat")
    return base, a, b


def test_houses_in_the_order_given_hashed_with_the_versions_of_the_run(roots):
    base, a, b = roots
    run = load_run_houses(base / "release", (b.id, a.id), CHAIR, backend="embree")
    assert isinstance(run, RunHouses) and run.ids == (b.id, a.id) and list(run.houses) == [b.id, a.id]
    for h in (a, b):
        files = h.files()
        assert run.files_sha256[h.id] == {f"{h.id}{s}": hashlib.sha256(files[s]).hexdigest() for s in files}
        assert run.objects_of_class[h.id] == sum(o.mpcat40_index in CHAIR for o in run.houses[h.id].objects) > 0
    assert run.versions == package_versions("embree") and run.versions["mpchair"] == __version__
    assert "numpy" in run.versions and "open3d" not in run.versions


def test_the_navmesh_is_hashed_when_read_or_as_a_file_of_the_layout(roots):
    base, a, _ = roots
    nav, house, mesh = f"{a.id}.navmesh", f"{a.id}.house", f"{a.id}_semantic.ply"
    read = load_run_houses(base / "habitat", (a.id,), CHAIR, backend="embree")  # generate --viewpoints auto
    assert read.houses[a.id].navmesh is not None and sorted(read.files_sha256[a.id]) == [house, nav, mesh]
    unread = load_run_houses(base / "habitat", (a.id,), CHAIR, backend="embree", navmesh=False)  # --viewpoints regions
    assert unread.houses[a.id].navmesh is None and sorted(unread.files_sha256[a.id]) == [house, mesh]
    layout = load_run_houses(base / "habitat", (a.id,), CHAIR, backend="embree", navmesh=False, hashed="layout")
    assert layout.files_sha256[a.id] == read.files_sha256[a.id]  # stream: every file of the habitat layout


def test_errors_come_in_house_order_before_the_next_house_is_read(roots):
    base, a, b = roots
    available = re.escape(", ".join(sorted([a.id, b.id])))
    with pytest.raises(InputError, match=rf"unknown house 'nope' \(available: {available}\)"):
        load_run_houses(base / "release", (a.id, "nope"), CHAIR, backend="embree")
    with pytest.raises(InputError, match=rf"{a.id}\.house: house {a.id} has no object of class toilet \(it has: "):
        load_run_houses(base / "release", (a.id, b.id), resolve_categories(["toilet"]), backend="embree")
    seen = []

    def refuse_first(house) -> None:
        seen.append(house.id)
        raise InputError(f"house {house.id}: refused")

    with pytest.raises(InputError, match=f"house {b.id}: refused"):
        load_run_houses(base / "release", (b.id, a.id), CHAIR, backend="embree", check=refuse_first)
    assert seen == [b.id]
