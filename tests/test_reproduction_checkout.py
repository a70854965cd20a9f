"""The experiment finds the clone in one place (``reproduction.checkout``), and each of its command lines refuses
to run outside one with a single ``error:`` line and exit 2, through the console scripts' error path."""

from __future__ import annotations

from pathlib import Path

import pytest

import reproduction.checkout as checkout
from mpchair.core.errors import InputError
from reproduction.cli import main as reproduce_main
from reproduction.stream.cli import main as stream_main
from reproduction.study_cli import main as study_main

ROOT = Path(__file__).resolve().parents[1]


def test_the_checkout_is_the_clone_that_holds_the_package():
    assert checkout.ROOT == ROOT and checkout.require_checkout() == ROOT and checkout.checkout_problem() is None


def test_a_folder_that_is_not_a_clone_is_refused(tmp_path: Path):
    (tmp_path / "pyproject.toml").write_text("[project]\n")
    (tmp_path / "tools").mkdir()  # no docs/: an installed package's site-packages has neither
    with pytest.raises(InputError, match=f"the reproduction runs in a clone of the repository.*{tmp_path} is not"):
        checkout.require_checkout(tmp_path)
    (tmp_path / "docs").mkdir()
    assert checkout.require_checkout(tmp_path) == tmp_path


@pytest.mark.parametrize("main, args", [
    (reproduce_main, ["--dry-run", "--scale", "small"]),
    (stream_main, ["--dry-run", "--scale", "small"]),
    (study_main, ["--status"]),
])
def test_each_command_refuses_outside_a_clone_in_one_line(main, args, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(checkout, "ROOT", tmp_path)
    assert main([*args, "--out", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: the reproduction runs in a clone") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "w").exists()  # refused before any work
