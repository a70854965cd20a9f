"""Packaged configs by name and derived configs (``_BASE_CONFIG_``): every shipped experiment resolves to exactly the
values it had as a full copy, a derived file changes only what it names, and a broken chain of bases is a one-line
error naming the file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from detector.config import (
    CONFIG_DIR,
    ExperimentConfig,
    available_configs,
    experiment_yaml,
    load_experiment,
)
from mpchair.core.config import from_dict, load_derived_yaml, merge_config
from mpchair.core.errors import InputError
from mpchair.geometry import geometry_from_model_yaml

#: Every shipped config as loaded before the configs derived from one another (written by load_experiment from the
#: 22 full copies of commit 42b8c3a): the derived files must give the same experiments, value for value.
RESOLVED = json.loads((Path(__file__).parent / "data" / "resolved_configs.json").read_text())


def test_the_packaged_configs_are_the_captured_ones():
    assert available_configs() == sorted(RESOLVED)
    assert CONFIG_DIR.name == "configs" and CONFIG_DIR.parent.name == "detector"


@pytest.mark.parametrize("name", sorted(RESOLVED))
def test_every_shipped_config_resolves_to_its_values_before_derivation(name):
    want = from_dict(ExperimentConfig, RESOLVED[name], source=name)
    assert load_experiment(name) == want  # by name
    assert load_experiment(CONFIG_DIR / f"{name}.yaml") == want  # by path


def test_the_copies_shrank_to_their_differences():
    """Only the four paper configs and the dense smoke config are full files; the rest derive from one of them."""
    full = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml") if "_BASE_CONFIG_" not in p.read_text())
    assert full == ["kitti_car_dense", "kitti_car_sparse", "mpchair_dense", "mpchair_dense_smoke", "mpchair_sparse"]
    exact = (CONFIG_DIR / "mpchair_sparse_exact.yaml").read_text()
    assert [ln for ln in exact.splitlines() if ln and not ln.startswith("#")] == [
        "_BASE_CONFIG_: mpchair_sparse.yaml", "model:",
        "  head: sparse_exact             # identical output to `dense`, computed on active sites only"]


def test_a_derived_config_merges_mappings_and_replaces_lists(tmp_path):
    base = load_experiment("mpchair_dense_smoke")
    child = tmp_path / "child.yaml"
    child.write_text("_BASE_CONFIG_: mpchair_dense_smoke\n"  # a packaged name
                     "model: {layer_nums: [1, 1, 1]}\n"
                     "data: {gt_sampling: {sample: 3}}\n"
                     "train: {epochs: 7}\n")
    cfg = load_experiment(child)
    assert cfg.model.layer_nums == (1, 1, 1) and cfg.train.epochs == 7
    assert cfg.data.gt_sampling.sample == 3 and cfg.data.gt_sampling.min_points == base.data.gt_sampling.min_points
    # nothing else moved
    assert cfg.model.output_shape == base.model.output_shape and cfg.train.lr == base.train.lr
    grand = tmp_path / "sub" / "grand.yaml"
    grand.parent.mkdir()
    grand.write_text("_BASE_CONFIG_: ../child.yaml\ntrain: {seed: 5}\n")  # a path, relative to the file's folder
    g = load_experiment(grand)
    assert (g.train.seed, g.train.epochs, g.model.layer_nums) == (5, 7, (1, 1, 1))
    assert merge_config({"a": {"b": 1, "c": [1, 2]}}, {"a": {"c": [3]}}) == {"a": {"b": 1, "c": [3]}}


def test_overrides_go_on_top_of_the_file_and_are_validated():
    changes = {"train": {"batch_size": 1}, "model": {"head": "sparse_exact"}}
    cfg = load_experiment("mpchair_sparse_cpu", overrides=changes)
    assert cfg.train.batch_size == 1 and cfg.model.head == "sparse_exact" and cfg.train.epochs == 25
    with pytest.raises(InputError, match=r"mpchair_sparse_cpu.yaml \(with overrides\): unknown key 'train.bogus'"):
        load_experiment("mpchair_sparse_cpu", overrides={"train": {"bogus": 1}})


def _one_line(err: pytest.ExceptionInfo) -> str:
    text = str(err.value)
    assert "\n" not in text
    return text


def test_a_cycle_of_bases_is_one_line_naming_the_file(tmp_path):
    (tmp_path / "a.yaml").write_text("_BASE_CONFIG_: b.yaml\n")
    (tmp_path / "b.yaml").write_text("_BASE_CONFIG_: a.yaml\n")
    with pytest.raises(InputError) as err:
        load_experiment(tmp_path / "a.yaml")
    assert _one_line(err) == f"{tmp_path / 'b.yaml'}: _BASE_CONFIG_ cycle: a.yaml -> b.yaml -> a.yaml"
    (tmp_path / "self.yaml").write_text("_BASE_CONFIG_: self.yaml\n")
    with pytest.raises(InputError, match=r"self.yaml: _BASE_CONFIG_ cycle: self.yaml -> self.yaml$"):
        load_experiment(tmp_path / "self.yaml")


def test_a_missing_or_malformed_base_is_one_line_naming_the_file(tmp_path):
    child = tmp_path / "child.yaml"
    child.write_text("_BASE_CONFIG_: nowhere.yaml\n")
    with pytest.raises(InputError) as err:
        load_experiment(child)
    assert _one_line(err).startswith(f"{child}: _BASE_CONFIG_: base file 'nowhere.yaml' not found")
    child.write_text("_BASE_CONFIG_: no_such_config\n")
    with pytest.raises(InputError) as err:
        load_experiment(child)
    assert _one_line(err).startswith(f"{child}: _BASE_CONFIG_: 'no_such_config' is not a known config name")
    child.write_text("_BASE_CONFIG_: [mpchair_dense]\n")
    with pytest.raises(InputError, match=r"child.yaml: _BASE_CONFIG_: expected a YAML path or a config name"):
        load_experiment(child)


def test_a_bad_key_is_named_by_the_file_that_holds_it(tmp_path):
    base = tmp_path / "base.yaml"
    base.write_text("_BASE_CONFIG_: mpchair_dense_smoke\ntrain: {bogus: 1}\n")
    child = tmp_path / "child.yaml"
    child.write_text("_BASE_CONFIG_: base.yaml\ntrain: {epochs: 1}\n")
    with pytest.raises(InputError, match=rf"^{base}: unknown key 'train.bogus'"):
        load_experiment(child)
    base.write_text("_BASE_CONFIG_: mpchair_dense_smoke\n")
    child.write_text("_BASE_CONFIG_: base.yaml\ntrain: {epoch: 1}\n")
    with pytest.raises(InputError, match=rf"^{child}:2: unknown key 'train.epoch'"):  # with the key's line
        load_experiment(child)


def test_a_path_wins_over_a_packaged_name_and_an_unknown_name_lists_them(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("mpchair_dense").write_text("_BASE_CONFIG_: mpchair_dense_smoke\ntrain: {epochs: 3}\n")
    assert load_experiment("mpchair_dense").train.epochs == 3  # the file here, not the packaged config
    with pytest.raises(InputError) as err:
        load_experiment("mpchair_dens")
    assert _one_line(err).startswith("unknown config 'mpchair_dens' (available: kitti_car_dense, ")
    with pytest.raises(InputError, match=r"^configs/models/mpchair_dense.yaml: config file not found \(packaged "
                                         r"configs, available by name: kitti_car_dense, "):
        load_experiment("configs/models/mpchair_dense.yaml")


def test_the_grid_reader_of_mpchair_stats_follows_the_base():
    """``mpchair stats --config`` reads the pillar grid only (mpchair never imports the detector): a derived config's
    grid is its base's."""
    g = geometry_from_model_yaml(CONFIG_DIR / "mpchair_sparse_exact_cpu.yaml")
    m = load_experiment("mpchair_sparse_exact_cpu").model
    assert g.point_cloud_range == m.point_cloud_range and g.grid == tuple(reversed(m.output_shape))
    assert load_derived_yaml(CONFIG_DIR / "mpchair_sparse_exact.yaml") == experiment_yaml(
        CONFIG_DIR / "mpchair_sparse_exact.yaml")
