"""mpchair.core.config (YAML → frozen dataclasses, errors named by file and key) and mpchair.core.atomic (no partial
files)."""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path
from typing import Literal

import pytest

from mpchair.core.atomic import atomic_open, write_bytes, write_text
from mpchair.core.config import from_dict, load_config, to_dict
from mpchair.core.errors import InputError


@dataclasses.dataclass(frozen=True)
class Lidar:
    channels: int
    fov_deg: tuple[float, float]
    pattern: Literal["uniform", "velodyne"] = "uniform"


@dataclasses.dataclass(frozen=True)
class Scene:
    name: str
    lidar: Lidar
    seeds: tuple[int, ...] = ()
    scale: float = 1.0
    noise: float | None = None
    enabled: bool = True


GOOD = """\
name: office
lidar:
  channels: 64
  fov_deg: [-25, 3]
  pattern: velodyne
seeds: [1, 2, 3]
scale: 2
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "scene.yaml"
    path.write_text(text)
    return path


def test_load_config_converts_types(tmp_path):
    cfg = load_config(Scene, write(tmp_path, GOOD))
    assert cfg == Scene(name="office", lidar=Lidar(64, (-25.0, 3.0), "velodyne"), seeds=(1, 2, 3), scale=2.0)
    assert isinstance(cfg.lidar.fov_deg, tuple) and isinstance(cfg.seeds, tuple)  # YAML lists become tuples
    assert isinstance(cfg.scale, float) and isinstance(cfg.lidar.fov_deg[0], float)
    assert cfg.noise is None and cfg.enabled is True
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.name = "x"  # type: ignore[misc]
    assert to_dict(cfg) == {"name": "office", "lidar": {"channels": 64, "fov_deg": [-25.0, 3.0], "pattern": "velodyne"},
                            "seeds": [1, 2, 3], "scale": 2.0, "noise": None, "enabled": True}  # fmt: skip
    assert from_dict(Scene, to_dict(cfg)) == cfg


@pytest.mark.parametrize(
    "text, match",
    [
        (GOOD + "colour: red\n", "unknown key 'colour'"),
        (GOOD.replace("  pattern: velodyne\n", "  pattern: velodyne\n  extra: 1\n"), "unknown key 'lidar.extra'"),
        (GOOD.replace("name: office\n", ""), "missing required key 'name'"),
        (GOOD.replace("  channels: 64\n", ""), "missing required key 'lidar.channels'"),
        (GOOD.replace("channels: 64", "channels: 64.5"), r"lidar\.channels: expected an integer, got 64\.5"),
        (GOOD.replace("channels: 64", "channels: true"), "lidar.channels: expected an integer"),
        (GOOD.replace("name: office", "name: 3"), "name: expected a string"),
        (GOOD + "enabled: 1\n", "enabled: expected true/false"),
        (GOOD.replace("scale: 2", "scale: .nan"), "scale: expected a finite number"),
        (GOOD.replace("scale: 2", "scale: big"), "scale: expected a number"),
        (GOOD.replace("pattern: velodyne", "pattern: spiral"), r"lidar\.pattern: 'spiral' is not one of"),
        (GOOD.replace("fov_deg: [-25, 3]", "fov_deg: [-25, 3, 4]"), "lidar.fov_deg: expected 2 values, got 3"),
        (GOOD.replace("fov_deg: [-25, 3]", "fov_deg: 3"), "lidar.fov_deg: expected a list"),
        (GOOD.replace("seeds: [1, 2, 3]", "seeds: [1, x]"), r"seeds\[1\]: expected an integer"),
        (GOOD.replace("fov_deg: [-25, 3]", "fov_deg: [-25, a]"), r"lidar\.fov_deg\[1\]: expected a number"),
        (GOOD + "noise: loud\n", "noise: expected a number"),
        (
            GOOD.replace("lidar:\n  channels: 64\n  fov_deg: [-25, 3]\n  pattern: velodyne\n", "lidar: 5\n"),
            r"lidar\.?: expected a mapping",
        ),
    ],
)
def test_config_errors_name_file_and_key(tmp_path, text, match):
    path = write(tmp_path, text)
    with pytest.raises(InputError, match=match) as info:
        load_config(Scene, path)
    assert info.value.path == str(path)
    # the line is the named key's (for a missing key, its section's; none when not even that is in the file)
    named = re.match(r"(?:unknown key |missing required key )?'?([\w.]+)", info.value.message).group(1).split(".")
    lines = text.splitlines()
    want = None
    for n in range(len(named), 0, -1):
        at = [i + 1 for i, ln in enumerate(lines) if ln.startswith(" " * 2 * (n - 1) + named[n - 1] + ":")]
        if at:
            want = at[0]
            break
    assert info.value.line == want, (info.value, want)
    assert str(info.value).startswith(f"{path}:{want}: " if want else f"{path}: ")


def test_config_file_level_errors(tmp_path):
    with pytest.raises(InputError, match="config file not found"):
        load_config(Scene, tmp_path / "missing.yaml")
    path = write(tmp_path, "name: [unclosed\n")
    with pytest.raises(InputError, match="invalid YAML") as info:
        load_config(Scene, path)
    assert info.value.path == str(path) and info.value.line is not None
    path = write(tmp_path, "- a\n- b\n")
    with pytest.raises(InputError, match="expected a YAML mapping"):
        load_config(Scene, path)


def test_optional_field_accepts_null_and_number(tmp_path):
    assert load_config(Scene, write(tmp_path, GOOD + "noise: null\n")).noise is None
    assert load_config(Scene, write(tmp_path, GOOD + "noise: 0.25\n")).noise == 0.25


# -------------------------------------------------------------------------------------------------------- atomic
def test_atomic_open_error_leaves_no_file_and_no_temp(tmp_path):
    target = tmp_path / "out" / "frame.txt"
    with pytest.raises(RuntimeError, match="boom"), atomic_open(target, "w") as f:
        f.write("half a file")
        raise RuntimeError("boom")
    assert not target.exists()
    assert os.listdir(target.parent) == []  # the temporary file is gone too


def test_atomic_open_error_keeps_the_previous_file(tmp_path):
    target = tmp_path / "frame.bin"
    write_bytes(target, b"old")
    with pytest.raises(KeyboardInterrupt), atomic_open(target, "wb") as f:
        f.write(b"new but unfinished")
        raise KeyboardInterrupt
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["frame.bin"]


def test_atomic_writes(tmp_path):
    target = tmp_path / "a" / "b.txt"
    write_text(target, "héllo\nworld\n")
    assert target.read_bytes() == "héllo\nworld\n".encode()
    with atomic_open(target, "w", fsync=True) as f:
        f.write("x")
    assert target.read_text() == "x"
    assert os.listdir(target.parent) == ["b.txt"]
    with pytest.raises(ValueError, match="mode"):
        with atomic_open(target, "a"):
            pass


def test_atomic_files_get_the_mode_open_would_give(tmp_path):
    old = os.umask(0o027)
    try:
        write_text(tmp_path / "deep" / "er" / "a.txt", "x")
        with open(tmp_path / "plain.txt", "w") as f:
            f.write("x")
    finally:
        os.umask(old)
    assert (tmp_path / "deep" / "er" / "a.txt").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "plain.txt").stat().st_mode & 0o777 == 0o640


@pytest.mark.parametrize("base", ["mpchair_sparse", "mpchair_sparse_cpu"])
def test_an_exact_head_config_is_its_sparse_config_but_the_head(base):
    """``<base>`` with ``head: sparse_exact`` (a config deriving from ``<base>``) must differ in the head only, or the
    exact head's rows (bench, deployed AP) would time or score another model."""
    import dataclasses

    from detector.config import load_experiment

    sparse = load_experiment(base)
    exact = load_experiment(base.replace("sparse", "sparse_exact", 1))
    assert sparse.model.head == "dense" and exact.model.head == "sparse_exact"
    assert dataclasses.replace(exact, model=dataclasses.replace(exact.model, head="dense")) == sparse
