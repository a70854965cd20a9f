"""Hostile config files (the audit of issue 33): every one is a one-line ``error: file[:line]: ...``, exit 2, and
nothing written — no traceback, no run folder, no run that never ends, no memory exhausted."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from detector.cli import main
from detector.config import experiment_yaml, load_experiment, memory_floor_bytes
from mpchair.core.config import MAX_CONFIG_DEPTH, load_yaml
from mpchair.core.errors import InputError

REPO = Path(__file__).resolve().parents[1]
SMOKE = REPO / "detector" / "configs" / "mpchair_sparse_smoke.yaml"


def _edited(tmp_path: Path, section: str, key: str, value) -> Path:
    data = experiment_yaml(SMOKE)  # the smoke config with its base merged in
    data.setdefault(section, {})[key] = value
    path = tmp_path / f"{section}-{key}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


#: (section, key, value) → the message after ``file: ``.
BAD_VALUES = {
    "300,000 layers": ("model", "layer_nums", [300000, 5, 5], "model: needs at least"),
    "a million pillar channels": ("model", "pfn_channels", 1_000_000, "model: needs at least"),
    "a 10^10-cell canvas": ("model", "output_shape", [100000, 100000], "model: needs at least"),
    "a billion points per pillar": ("model", "max_points_per_pillar", 10**9, "model: needs at least"),
    "a zero stride": ("model", "layer_strides", [0, 2, 2], "model.layer_strides: every value must be >= 1"),
    "a negative seed": ("train", "seed", -1, "train.seed: between 0 and 2**32 - 1, got -1"),
    "endless epochs": ("train", "epochs", 10**26, "train.epochs: at most 100,000"),
    "a thousand workers": ("train", "num_workers", 1000, "train.num_workers: between 0 and 64"),
    "negative samples per epoch": ("train", "samples_per_epoch", -5, "train.samples_per_epoch: between 1 and"),
    "an eval class never trained": ("eval", "classes", ["Sofa"], "eval.classes: 'Sofa' is not a trained class"),
}


@pytest.mark.parametrize("case", list(BAD_VALUES))
def test_train_refuses_a_hostile_config_before_writing(tmp_path, capsys, case):
    section, key, value, message = BAD_VALUES[case]
    cfg = _edited(tmp_path, section, key, value)
    with pytest.raises(InputError) as err:
        load_experiment(cfg)
    # a message about one key names its line (README's error: file:line:), one about the whole section does not
    lines = cfg.read_text().splitlines()
    at = lines.index(f"{section}:")
    line = next(i + 1 for i, text in enumerate(lines) if i > at and text.startswith(f"  {key}:"))
    where = f"{cfg}:{line}" if message.startswith(f"{section}.{key}") else f"{cfg}"
    assert str(err.value).startswith(f"{where}: {message}"), err.value
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--config", str(cfg), "--data", str(tmp_path / "nodata"), "--out", str(out)])
    captured = capsys.readouterr()
    assert exit_.value.code == 2
    assert (captured.out + captured.err).strip().splitlines() == [f"error: {err.value}"]
    assert not out.exists()


def test_the_memory_floor_passes_every_shipped_config_and_grows_with_the_model():
    """The bound refuses only configs that cannot run: every shipped config is far below this machine's memory, and
    the bound grows with the canvas and the layers."""
    for path in sorted((REPO / "detector" / "configs").glob("*.yaml")):
        cfg = load_experiment(path)  # would raise if the bound refused it
        assert 0 < memory_floor_bytes(cfg.model, cfg.train.batch_size) < 8 * 2**30, path.name
    small = load_experiment(SMOKE).model
    from dataclasses import replace

    assert memory_floor_bytes(replace(small, output_shape=(512, 768))) > memory_floor_bytes(small)
    assert memory_floor_bytes(replace(small, layer_nums=(30, 5, 5))) > memory_floor_bytes(small)


@pytest.mark.parametrize("text, message, line", [
    (b"model:\n  lr: 1\n  lr: 2\n", "duplicate key 'lr' (first on line 2)", 3),
    (b"a: " + b"[" * 100_000 + b"\n", f"nested deeper than {MAX_CONFIG_DEPTH} levels", 1),
    (b"model:\n  name: caf\xe9\n", "not UTF-8 text (byte 18 is 0xe9)", 2),
    (b"model: [1, 2\n", "invalid YAML", 2),
    (b"- 1\n- 2\n", "expected a YAML mapping at the top level", None),
])
def test_yaml_loader_refuses_hostile_files_in_one_line(tmp_path, text, message, line):
    path = tmp_path / "c.yaml"
    path.write_bytes(text)
    with pytest.raises(InputError) as err:
        load_yaml(path)
    assert err.value.line == line and message in err.value.message, err.value
    assert "\n" not in str(err.value)


def test_yaml_reads_numbers_as_yaml_1_2_does(tmp_path):
    """``1e-9`` (no dot) is a string in YAML 1.1; a config author means a number."""
    path = tmp_path / "c.yaml"
    path.write_text("a: 1e-9\nb: -3E+2\nc: 12\nd: .5\ne: 1.5e3\nf: text\ng: '1e-9'\n")
    assert load_yaml(path) == {"a": 1e-9, "b": -300.0, "c": 12, "d": 0.5, "e": 1500.0, "f": "text", "g": "1e-9"}
    assert isinstance(load_yaml(path)["c"], int)


def test_an_oversized_config_is_refused_without_reading_it(tmp_path):
    path = tmp_path / "big.yaml"
    with path.open("wb") as f:
        f.truncate(2 << 20)
    with pytest.raises(InputError, match="not a config file"):
        load_yaml(path)
