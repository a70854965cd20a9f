"""Trained weights by name (``--checkpoint pretrained:NAME``) on a tiny model these tests train: packed in half
precision with an index, resolved without network, read with ``torch.load(weights_only=True)``, and a missing or
damaged one is a one-line error. Also: ``train()`` takes an experiment built in memory."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers_detector import detector_cli, make_tiny_dataset, write_test_config

import detector.pretrained as pretrained
from detector.checkpoint import load_checkpoint, load_model, pack_pretrained
from detector.config import load_experiment
from detector.infer import default_results_dir
from detector.pretrained import read_index, resolve_checkpoint
from detector.train import train
from mpchair.core.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict:
    """A slim sparse model trained 2 steps on a tiny dataset, once from its YAML and once from the same experiment in
    memory (with a seed override that makes it differ from the file's)."""
    tmp = tmp_path_factory.mktemp("pretrained")
    data = make_tiny_dataset(tmp / "data", n_frames=4, seed=3)
    cfg_path = write_test_config(tmp / "sparse.yaml", model=dict(backbone="sparse"), train=dict(batch_size=2))
    train(cfg_path, data, tmp / "from_file", max_steps=2, threads=1, progress=False)
    cfg = load_experiment(cfg_path)
    train(cfg, data, tmp / "in_memory", max_steps=2, threads=1, progress=False)
    reseeded = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, seed=7))
    train(reseeded, data, tmp / "reseeded", max_steps=2, threads=1, progress=False)
    return {"tmp": tmp, "data": data, "cfg_path": cfg_path, "cfg": cfg}


def _weights(run: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(run / "last.pt").model


def test_train_takes_an_experiment_in_memory(trained):
    tmp = trained["tmp"]
    a, b, c = _weights(tmp / "from_file"), _weights(tmp / "in_memory"), _weights(tmp / "reseeded")
    assert all(torch.equal(a[k], b[k]) for k in a)  # the same experiment, from a file or from memory
    assert not all(torch.equal(a[k], c[k]) for k in a)  # and the in-memory change took effect
    assert "seed: 7" in (tmp / "reseeded" / "config.yaml").read_text()
    with pytest.raises(InputError, match="overrides apply to a config file or name"):
        train(trained["cfg"], trained["data"], tmp / "x", overrides={"train": {"seed": 1}}, progress=False)
    assert not (tmp / "x").exists()


def test_train_applies_overrides_to_a_config_file(trained, tmp_path):
    run = tmp_path / "run"
    train(trained["cfg_path"], trained["data"], run, max_steps=1, threads=1, progress=False,
          overrides={"train": {"seed": 7}})
    assert "seed: 7" in (run / "config.yaml").read_text()


def test_packed_weights_load_by_name_in_half_precision(trained, tmp_path, monkeypatch):
    folder = tmp_path / "pretrained"
    run = trained["tmp"] / "from_file"
    out = pack_pretrained(run / "last.pt", {"sparse": "mpchair_sparse_cpu", "sparse_exact": "mpchair_sparse_exact_cpu"},
                          folder, dtype="bf16")
    assert out == folder / "sparse.pt"
    index = read_index(folder)
    assert sorted(index) == ["sparse", "sparse_exact"] and index["sparse_exact"].file == "sparse.pt"
    assert index["sparse"].config == "mpchair_sparse_cpu"
    raw = torch.load(out, weights_only=True)
    assert set(raw["model"]) == set(_weights(run)) and raw["optimizer"] is None and raw["rng"] is None
    floats = [v for v in raw["model"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.bfloat16 for v in floats)
    assert out.stat().st_size < 0.6 * (run / "last.pt").stat().st_size  # no optimiser state, half the bytes
    # by name, through the one checkpoint reader: the trained weights rounded to bf16, back in fp32
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", folder)
    assert resolve_checkpoint("pretrained:sparse") == out
    model = load_model(trained["cfg"], "pretrained:sparse")
    trained_w = _weights(run)
    for k, v in model.state_dict().items():
        want = trained_w[k].to(torch.bfloat16).to(v.dtype) if trained_w[k].is_floating_point() else trained_w[k]
        assert torch.equal(v, want), k
    assert default_results_dir("pretrained:sparse", "val") == Path("pretrained_sparse_val")
    # a second pack keeps the other names
    pack_pretrained(run / "last.pt", {"dense": "mpchair_dense_cpu"}, folder, dtype="fp16")
    assert sorted(read_index(folder)) == ["dense", "sparse", "sparse_exact"]


def test_the_cli_evaluates_packaged_weights_by_name(trained, tmp_path, monkeypatch, capsys):
    folder = tmp_path / "pretrained"
    pack_pretrained(trained["tmp"] / "from_file" / "last.pt", {"sparse": "mpchair_sparse_cpu"}, folder)
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", folder)
    code, out, err = detector_cli(["eval", "--config", trained["cfg_path"], "--data", trained["data"], "--checkpoint",
                                   "pretrained:sparse", "--split", "val", "--out", tmp_path / "ev", "--json"], capsys)
    assert code == 0, err
    doc = json.loads(out)
    assert doc["num_gt_overall"]["Chair"] > 0 and set(doc["Chair"]["3d"]) == {"R11", "R40", "overall"}
    assert len(list((tmp_path / "ev").rglob("00000*.txt"))) == 4  # one result file per val frame


def test_unlisted_weights_are_one_line_saying_where_they_go(tmp_path, monkeypatch, capsys, trained):
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "empty")
    code, out, err = detector_cli(["eval", "--config", trained["cfg_path"], "--data", trained["data"],
                                   "--checkpoint", "pretrained:dense", "--out", tmp_path / "ev"], capsys)
    lines = (out + err).strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith("error: no pretrained weights 'dense' in this install (installed: none yet; published "
                               "names: dense, sparse, sparse_exact): put the packed file and its index.json in "
                               f"{tmp_path / 'empty'} (tools/pack_pretrained.py packs")
    assert not (tmp_path / "ev").exists()


class Payload:
    """A class the unpickler would have to import: weights_only must refuse it."""


def test_a_damaged_or_unsafe_packaged_file_is_refused(trained, tmp_path):
    folder = tmp_path / "pretrained"
    out = pack_pretrained(trained["tmp"] / "from_file" / "last.pt", {"sparse": "mpchair_sparse_cpu"}, folder)
    out.write_bytes(out.read_bytes()[:-10])
    with pytest.raises(InputError, match=r"sparse.pt: pretrained weights 'sparse': the file's SHA-256 differs"):
        resolve_checkpoint("pretrained:sparse", folder)
    # a file whose index entry matches but whose pickle would import a class: torch.load(weights_only=True) refuses
    torch.save({"format": 1, "model": {}, "config": Payload()}, out)
    pretrained.add_to_index(folder, out, {"sparse": "mpchair_sparse_cpu"})
    with pytest.raises(InputError, match=r"refused: loading it would call .*Payload"):
        load_checkpoint(resolve_checkpoint("pretrained:sparse", folder))
    (folder / "index.json").write_text('{"format": 1, "weights": {"sparse": {"file": "../x.pt"}}}')
    with pytest.raises(InputError, match=r"index.json: weights.sparse: expected strings file, config, sha256"):
        read_index(folder)


def test_the_pack_tool_is_a_front_end(trained, tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "pack_pretrained.py"),
                           str(trained["tmp"] / "from_file" / "last.pt"), "--name", "sparse=mpchair_sparse_cpu",
                           "--dtype", "fp16", "--out", str(tmp_path / "p")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"wrote {tmp_path / 'p' / 'sparse.pt'} (") and "pretrained:sparse" in proc.stdout
    packed = torch.load(tmp_path / "p" / "sparse.pt", weights_only=True)["model"].values()
    assert {v.dtype for v in packed if v.is_floating_point()} == {torch.float16}
    bad = subprocess.run([sys.executable, str(ROOT / "tools" / "pack_pretrained.py"), str(tmp_path / "none.pt"),
                          "--name", "sparse", "--out", str(tmp_path / "q")], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines() == [
        "error: --name takes NAME=CONFIG (e.g. sparse=mpchair_sparse_cpu)"]
    assert not (tmp_path / "q").exists()
