"""Both console scripts: every registered subcommand exists and has --help; InputError, OSError and click's usage
errors → one line + exit 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import click
import click.testing
import numpy as np
import pytest

from detector.cli import COMMANDS as DETECTOR_COMMANDS
from detector.cli import cli as detector_cli
from mpchair.cli import COMMANDS as MPCHAIR_COMMANDS
from mpchair.cli import cli as mpchair_cli
from mpchair.core.clitools import run_cli, run_script
from mpchair.core.errors import InputError
from mpchair.kitti import Labels, read_imageset, read_labels, write_labels

#: What a command's help must tell beyond its options.
HELP_MENTIONS = {("detector", "train"): ("torchrun",)}
ALL = [("mpchair", name) for name in MPCHAIR_COMMANDS] + [("detector", name) for name in DETECTOR_COMMANDS]


@pytest.mark.parametrize(("prog", "name"), ALL)
def test_every_registered_command_has_help(prog: str, name: str) -> None:
    group = mpchair_cli if prog == "mpchair" else detector_cli
    ctx = click.Context(group)
    command = group.get_command(ctx, name)
    assert command is not None, f"{prog} {name} is registered but its module is missing"
    runner = click.testing.CliRunner()
    result = runner.invoke(group, [name, "--help"], prog_name=prog)
    assert result.exit_code == 0, result.output
    assert result.output.startswith(f"Usage: {prog} {name} [OPTIONS]") and "--help" in result.output
    # every option is documented, and the command's description is shown
    for param in command.params:
        if isinstance(param, click.Option) and not param.hidden:
            assert max(param.opts, key=len) in result.output, (name, param.opts)
    assert command.help and command.help.split("\n")[0].strip()[:40] in " ".join(result.output.split())
    for word in HELP_MENTIONS.get((prog, name), ()):
        assert word in result.output, (name, word)


def test_group_help_lists_every_command() -> None:
    runner = click.testing.CliRunner()
    out = runner.invoke(mpchair_cli, ["--help"]).output
    assert all(name in out for name in MPCHAIR_COMMANDS)
    out = runner.invoke(detector_cli, ["--help"]).output
    assert all(name in out for name in DETECTOR_COMMANDS)


def test_detector_help_trains_the_cpu_configs() -> None:
    """``detector --help``'s examples that train or run a model on a stream use the CPU-sized configs (the paper's
    GPU-sized ones plan ~70 days of training on 2 cores), and every config they name exists."""
    out = click.testing.CliRunner().invoke(detector_cli, ["--help"]).output
    joined = out.replace("\\\n", " ")
    examples = [" ".join(line.split()) for line in joined.splitlines() if line.strip().startswith("detector ")]
    trains = [e for e in examples if e.split()[1] in ("train", "eval", "stream-eval")]
    assert len(trains) == 3 and all("--config mpchair_sparse_cpu " in e + " " for e in trains), trains
    from detector.config import available_configs

    named = {e.split()[e.split().index("--config") + 1] for e in examples if "--config" in e.split()}
    assert named and named <= set(available_configs()), named  # packaged configs, by name


def test_a_config_error_names_the_file_and_the_line_of_the_key(tmp_path: Path, capsys) -> None:
    """README's promise, for errors other than YAML syntax: ``error: FILE:LINE: ...`` with the line of the key at
    fault (a misspelt value, an unknown key), as ``detector train`` reads the config before anything else."""
    from detector.cli import main

    smoke = Path(__file__).resolve().parents[1] / "detector" / "configs" / "mpchair_dense_smoke.yaml"
    text = smoke.read_text()
    for bad, line, message in (
            (text.replace("  backbone: dense", "  backbone: sprase"), 15, "model.backbone: 'sprase' is not one of"),
            (text.replace("  score_thr: 0.1", "  score_thresh: 0.1"), 40, "unknown key 'model.score_thresh'")):
        cfg = tmp_path / "cfg.yaml"
        cfg.write_text(bad)
        with pytest.raises(SystemExit) as e:
            main(["train", "--config", str(cfg), "--data", str(tmp_path), "--out", str(tmp_path / "run")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.startswith(f"error: {cfg}:{line}: {message}"), err
        assert len(err.splitlines()) == 1 and not (tmp_path / "run").exists()


def test_input_error_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    @click.command()
    def boom() -> None:
        raise InputError("record has 3 tokens, expected 5", "house.house", 12)

    with pytest.raises(SystemExit) as exc:
        run_cli(boom, [])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err == "error: house.house:12: record has 3 tokens, expected 5\n"


def test_run_script_is_the_console_scripts_error_path(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    """The argparse command lines (tools/, the experiment) get run_cli's outcomes: an InputError or OSError is one
    line and 2, a RunError 1, a warning is held until a success and dropped after a failure."""
    import warnings

    from mpchair.core.errors import RunError

    def fail(error: Exception):
        def work() -> int:
            warnings.warn("held back", stacklevel=1)
            raise error
        return work

    assert run_script(fail(InputError("bad option", "x.yaml", 3))) == 2
    assert capsys.readouterr().err == "error: x.yaml:3: bad option\n"
    assert run_script(fail(OSError(13, "Permission denied", str(tmp_path / "out")))) == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'out'}: Permission denied\n"
    assert run_script(fail(RunError("a worker died"))) == 1
    assert capsys.readouterr().err == "error: a worker died\n"

    def fine() -> int:
        warnings.warn("a note", stacklevel=1)
        print("done")
        return 0

    assert run_script(fine) == 0 and run_script(lambda: 3) == 3
    out = capsys.readouterr()
    assert out.out == "done\n" and out.err == "warning: a note\n"


def test_console_scripts_run_as_modules() -> None:
    out = subprocess.run([sys.executable, "-m", "detector", "--help"], capture_output=True, text=True, check=False)
    assert out.returncode == 0 and "Usage:" in out.stdout
    out = subprocess.run([sys.executable, "-m", "mpchair.cli", "nope"], capture_output=True, text=True, check=False)
    assert out.returncode == 2 and out.stderr.startswith("error: No such command 'nope'")


@pytest.mark.parametrize(("group", "args", "message", "command"), [
    (mpchair_cli, ["generate", "--root", "r"], "Missing option '--house'.", "generate"),
    (mpchair_cli, ["stats", "d"], "choose --density or --boxes", "stats"),
    (detector_cli, ["train", "--config", "c", "--epochs", "x"],
     "Invalid value for '--epochs': 'x' is not a valid integer.", "train"),
])
def test_usage_errors_are_one_line_and_exit_2(capsys: pytest.CaptureFixture[str], group, args, message,
                                              command) -> None:
    with pytest.raises(SystemExit) as exc:
        run_cli(group, args)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    # The hint names the program as it was started (``mpchair``, ``python -m mpchair.cli``, ...).
    assert err.startswith(f"error: {message} (see '") and err.endswith(f" {command} --help')\n")
    assert err.count("\n") == 1


def test_an_os_error_is_one_line_with_its_path_and_exit_2(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    @click.command()
    def full() -> None:
        raise OSError(28, "No space left on device", str(tmp_path / "x.bin"))

    with pytest.raises(SystemExit) as exc:
        run_cli(full, [])
    assert exc.value.code == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'x.bin'}: No space left on device\n"


def _detector(capsys: pytest.CaptureFixture[str], *args) -> tuple[int, str, str]:
    from detector.cli import main

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return e.value.code, out, err


def test_eval_min_overlap_sets_the_bbox_bev_3d_thresholds(tmp_path: Path, capsys) -> None:
    """``detector eval --min-overlap``: ``CLASS=T`` sets all three IoU thresholds, ``CLASS=BBOX,BEV,3D`` each one.
    The results are the real KITTI cars with their own 2D boxes (2D IoU 1) moved a quarter of their length along
    their heading, so that BEV and 3D IoU are 0.6: they match at 0.5 and not at the default 0.7."""
    kitti = Path(__file__).parent / "data" / "kitti"
    results = tmp_path / "results"
    ids = read_imageset(kitti / "ImageSets" / "val.txt")
    cars = 0
    for fid in ids:
        gt = read_labels(kitti / "training" / "label_2" / f"{fid}.txt")
        keep = gt.names == "Car"
        cars += int(keep.sum())
        loc, ry, length = gt.location[keep], gt.rotation_y[keep], gt.dims_hwl[keep, 2]
        moved = loc + (length / 4)[:, None] * np.stack([np.cos(ry), np.zeros_like(ry), -np.sin(ry)], axis=1)
        write_labels(results / f"{fid}.txt", Labels(gt.names[keep], gt.truncated[keep], gt.occluded[keep],
                                                    gt.alpha[keep], gt.bbox[keep], gt.dims_hwl[keep], moved, ry,
                                                    score=np.full(int(keep.sum()), 0.9)))
    assert cars == 5
    base = ["eval", "--labels", kitti / "training" / "label_2", "--results", results, "--split",
            kitti / "ImageSets" / "val.txt", "--classes", "Car", "--json"]

    def best(*extra: str) -> dict[str, float]:
        code, out, err = _detector(capsys, *base, *extra)
        assert code == 0, err
        ap = json.loads(out)["Car"]
        return {m: max(ap[m]["R40"]) for m in ("bbox", "bev", "3d")}

    default, half, mixed = best(), best("--min-overlap", "Car=0.5"), best("--min-overlap", "Car=0.9,0.5,0.7")
    # Every car matches in 2D at any threshold < 1 (the AP of a few GT stays far below 100: R40 needs 40 of them).
    assert default["bbox"] > 0 and default["bev"] == default["3d"] == 0  # Car's default threshold is 0.7
    assert half == {"bbox": default["bbox"], "bev": default["bbox"], "3d": default["bbox"]}
    assert mixed == {"bbox": default["bbox"], "bev": default["bbox"], "3d": 0}
    for bad in ("Car", "Car=", "=0.5", "Car=1.0", "Car=-0.1", "Car=a", "Car=0.5,0.5"):
        code, out, err = _detector(capsys, *base, "--min-overlap", bad)
        assert code == 2 and out == "" and err == (f"error: --min-overlap {bad!r}: expected CLASS=T or "
                                                   "CLASS=BBOX,BEV,3D with values in [0, 1)\n"), err


def test_outputs_that_cannot_be_written_fail_before_the_work_naming_the_folder(tmp_path, capsys, monkeypatch):
    """An output below a file (or in a read-only folder) is one error line naming that folder, before any work (the
    work is replaced by a failure here): no hidden temp name, nothing after minutes of drawing, timing or training. A
    writer that still meets such a folder names the folder, not its temp file."""
    import os

    from helpers_detector import make_tiny_dataset

    import detector.bench
    import mpchair.analysis.render
    from mpchair.cli import main as mpchair_main
    from mpchair.core.atomic import write_text

    def no_work(*args, **kwargs):
        raise AssertionError("the work ran before the output was checked")

    monkeypatch.setattr(mpchair.analysis.render, "frame_picture", no_work)
    monkeypatch.setattr(detector.bench, "run_bench", no_work)
    data = make_tiny_dataset(tmp_path / "ds", n_frames=2)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")

    with pytest.raises(SystemExit) as e:
        mpchair_main(["view", str(data), "--frame", "0", "--out", str(blocker / "x.png")])
    assert e.value.code == 2
    assert capsys.readouterr().err == f"error: {blocker}: is not a folder, so {blocker / 'x.png'} cannot be written\n"
    code, _, err = _detector(capsys, "bench", "--config", "detector/configs/mpchair_dense_smoke.yaml", "--data", data,
                             "--json-out", blocker / "out" / "b.json")
    assert code == 2 and err.splitlines()[-1].startswith(f"error: {blocker}: is not a folder"), err
    code, _, err = _detector(capsys, "train", "--config", "detector/configs/mpchair_dense_smoke.yaml", "--data", data,
                             "--out", blocker / "run")
    assert code == 2 and err == f"error: {blocker}: is not a folder, so {blocker / 'run'} cannot be written\n"
    with pytest.raises(NotADirectoryError) as exc:
        write_text(blocker / "x.txt", "x")
    assert exc.value.filename == str(blocker)
    if os.geteuid() != 0:  # root writes into a read-only folder anyway
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(SystemExit) as e:
            mpchair_main(["view", str(data), "--frame", "0", "--out", str(ro / "x.png")])
        assert e.value.code == 2
        assert capsys.readouterr().err.startswith(f"error: {ro}: folder not writable (Permission denied)")


def test_help_examples_name_ids_synth_makes_and_write_under_out() -> None:
    """``view-house --help`` shows no house id that ``mpchair synth`` never makes (it says how to list the ids), and the
    picture examples of ``view``, ``view-house`` and ``stats`` write under ``out/``, not into the repository root."""
    import re

    runner = click.testing.CliRunner()
    for name in ("view", "view-house", "stats"):
        text = runner.invoke(mpchair_cli, [name, "--help"], prog_name="mpchair").output
        examples = text.split("Example", 1)[1]
        assert "synth0000" not in examples
        written = re.findall(r"--(?:out|plot) (\S+\.png)", examples)
        assert written and all(p.startswith("out/") for p in written), (name, written)
    assert "mpchair houses --root" in runner.invoke(mpchair_cli, ["view-house", "--help"]).output
