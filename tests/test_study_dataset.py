"""The accuracy study's dataset identity (reproduction/study_dataset.py): a regenerated dataset whose bytes differ from
the record's only in float bits is accepted as an equivalent on request, and recorded; one whose labels, splits or
totals differ is refused, naming what differs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from mpchair.core.errors import InputError
from mpchair.dataset.generate import GenerateRequest, generate
from mpchair.synth import synthesize_house, write_house
from mpchair.synth.realism import CLEAN
from reproduction.record import dataset_fingerprint
from reproduction.study import Study, read_study_record, read_zip_texts, save
from reproduction.study_cli import _check_dataset
from reproduction.study_dataset import accepted, dataset_parts, equivalence_problems


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path]:
    """A 6-frame house-split dataset (three houses: train / val / test) and the study record made from it."""
    base = tmp_path_factory.mktemp("study")
    ids = []
    for seed in (3, 4, 5):
        house = synthesize_house(seed, levels=1, realism=CLEAN)
        write_house(base / "houses", house)
        ids.append(house.id)
    out = base / "out"
    generate(GenerateRequest(root=base / "houses", houses=tuple(ids), frames=2, out=out / "dataset", seed=1,
                             progress=False, workers=1, split_mode="house"))
    record = base / "record"
    save(Study(out=out, record=record), dataset_fingerprint(out / "dataset"))
    return out, record


def _copy(out: Path, tmp_path: Path) -> Study:
    shutil.copytree(out / "dataset", tmp_path / "out" / "dataset")
    return Study(out=tmp_path / "out", record=tmp_path / "record")


def _flip_a_point(study: Study) -> None:
    scan = sorted((study.data / "training" / "velodyne").glob("*.bin"))[0]
    data = bytearray(scan.read_bytes())
    data[0] ^= 1  # the lowest mantissa bit of the first point's x
    scan.write_bytes(bytes(data))


def test_float_bits_are_accepted_on_request_and_recorded(recorded, tmp_path):
    """One flipped mantissa bit in a scan: the fingerprint differs, nothing that the equivalence compares does; the
    check refuses without --accept-dataset (pointing at it), accepts with it, and once saved the record takes that
    fingerprint by itself and keeps its own."""
    out, record = recorded
    shutil.copytree(record, tmp_path / "record")
    study = _copy(out, tmp_path)
    original = dataset_fingerprint(study.data)
    _flip_a_point(study)
    fingerprint = dataset_fingerprint(study.data)
    assert fingerprint != original
    assert equivalence_problems(study.data, study.record, read_zip_texts(study.record / "test_labels.zip")) == []
    with pytest.raises(InputError, match="--accept-dataset"):
        _check_dataset(study, fingerprint, accept=False)
    entry = _check_dataset(study, fingerprint, accept=True)
    assert entry is not None and entry["cpu"] and entry["date"]
    assert entry["parts_sha256"] == dataset_parts(study.data)
    save(study, fingerprint, ("a note",), entry)
    meta = read_study_record(study.record)
    assert meta["dataset_sha256"] == original  # the record keeps the fingerprint it started with
    assert meta["dataset_equivalents"][fingerprint]["parts_sha256"] == entry["parts_sha256"]
    assert accepted(meta, fingerprint) and accepted(meta, original) and not accepted(meta, "0" * 64)
    assert _check_dataset(study, fingerprint, accept=False) is None  # a later session needs no flag


def test_parts_locate_the_difference(recorded, tmp_path):
    """The per-part hashes differ exactly in the flipped scan's kind and house."""
    out, _ = recorded
    study = _copy(out, tmp_path)
    before = dataset_parts(study.data)
    _flip_a_point(study)
    after = dataset_parts(study.data)
    manifest = json.loads((study.data / "manifest.json").read_text())
    first_house = next(h for h, e in manifest["houses"].items() if e["frames"][0] == 0)
    assert {k for k in before if before[k] != after[k]} == {f"velodyne/{first_house}"}
    assert len(before) == len(manifest["houses"]) * 5  # calib, image_2, label_2, pose, velodyne


@pytest.mark.parametrize("change", ["test_label", "imageset", "manifest_total"])
def test_other_differences_are_refused_even_with_the_flag(recorded, tmp_path, change):
    """A changed test label, split list or manifest total is not float bits: refused with --accept-dataset too, and
    the error names what differs."""
    out, record = recorded
    shutil.copytree(record, tmp_path / "record")
    study = _copy(out, tmp_path)
    if change == "test_label":
        test_id = (study.data / "ImageSets" / "test.txt").read_text().split()[0]
        label = study.data / "training" / "label_2" / f"{test_id}.txt"
        label.write_text(label.read_text() + "Chair 0.00 0 0.00 0 0 10 10 1.00 0.50 0.50 1.00 1.00 1.00 0.00\n")
        expect = "test label"
    elif change == "imageset":
        (study.data / "ImageSets" / "val.txt").write_text("")
        expect = "ImageSets/val.txt"
    else:
        manifest = json.loads((study.data / "manifest.json").read_text())
        manifest["totals"]["points"] += 1
        (study.data / "manifest.json").write_text(json.dumps(manifest))
        expect = "'totals'"
    fingerprint = dataset_fingerprint(study.data)
    with pytest.raises(InputError, match=expect):
        _check_dataset(study, fingerprint if change != "manifest_total" else "f" * 64, accept=True)
