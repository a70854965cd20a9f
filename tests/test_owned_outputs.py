"""A command never deletes or rewrites what it did not create (docs/reliability.md): an output folder is replaced only
when it is new, empty or the command's own (mpchair.core.owned's marker); everything else is refused with one line
and left byte for byte as it was. Covers the shared helper, ``tools/reproduce.py --steps record --record DIR``,
``detector export --out``, ``detector eval``'s ``OUT/data/`` and ``detector train --out``."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
from pathlib import Path

import pytest
from helpers_detector import detector_cli, make_tiny_dataset, write_test_config
from helpers_faults import kill_at_swap, run_forked

from detector.infer import write_results
from detector.train.run_folder import remove_stale_temps
from mpchair.core.errors import InputError
from mpchair.core.owned import (
    MARKER,
    check_replaceable,
    clear_leftovers,
    read_marker,
    remove_leftovers,
    replace_folder,
    work_dir,
)
from mpchair.kitti import Labels
from reproduction.cli import main as reproduce_main
from reproduction.record import RECORD_JSON, RecordError, save_record
from reproduction.scales import SCALES


def _user_folder(path: Path, **extra: str) -> dict[str, bytes]:
    """A folder a user owns (a thesis with its git folder, raw measurements); returns its files' bytes."""
    files = {"thesis.tex": "\\documentclass{article}\n", ".git/HEAD": "ref: refs/heads/main\n",
             "raw/measurements.csv": "t,x\n0,1\n", **extra}
    for rel, text in files.items():
        (path / rel).parent.mkdir(parents=True, exist_ok=True)
        (path / rel).write_text(text)
    return _snapshot(path)


def _snapshot(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


# --- the shared helper ---------------------------------------------------------------------------------------------


def _stage(parent: Path, name: str, files: dict[str, str]) -> Path:
    stage = work_dir(parent, f".{name}.work", "cmd")
    for rel, text in files.items():
        (stage / rel).parent.mkdir(parents=True, exist_ok=True)
        (stage / rel).write_text(text)
    return stage


def test_a_folder_is_replaced_only_when_it_is_the_commands_own(tmp_path, monkeypatch):
    out = tmp_path / "out"
    replace_folder(_stage(tmp_path, "out", {"a.txt": "1", "sub/b.txt": "2"}), out, "cmd")
    assert read_marker(out)["files"] == ["a.txt", "sub/b.txt"] and (out / "a.txt").read_text() == "1"
    replace_folder(_stage(tmp_path, "out", {"a.txt": "3"}), out, "cmd")  # its own: swapped whole
    assert sorted(_snapshot(out)) == [MARKER, "a.txt"] and (out / "a.txt").read_text() == "3"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no work or old folder left

    (out / "notes.txt").write_text("mine")  # a file the user added to the command's folder
    with pytest.raises(InputError, match=rf"^{out}: will not replace this folder: it holds notes.txt, which cmd did "
                                         "not write"):
        check_replaceable(out, "cmd")
    with pytest.raises(InputError):
        replace_folder(_stage(tmp_path, "out", {"a.txt": "4"}), out, "cmd")
    assert (out / "notes.txt").read_text() == "mine" and (out / "a.txt").read_text() == "3"

    user = tmp_path / "user"
    before = _user_folder(user)
    with pytest.raises(InputError, match="it holds files cmd did not write"):
        check_replaceable(user, "cmd")
    with pytest.raises(InputError, match="it was made by cmd, not other"):
        check_replaceable(out, "other")
    (tmp_path / "empty").mkdir()
    check_replaceable(tmp_path / "empty", "cmd")
    check_replaceable(tmp_path / "missing", "cmd")
    monkeypatch.chdir(out)  # the current folder (and what holds it) is never replaced, even the command's own
    with pytest.raises(InputError, match="is the current folder or holds it"):
        check_replaceable(Path("."), "cmd")
    assert _snapshot(user) == before


def test_leftovers_of_a_killed_run_are_removed_only_when_marked_as_the_commands(tmp_path):
    killed = _stage(tmp_path, "out", {"half.bin": "x"})  # a killed run's work folder
    other = work_dir(tmp_path, ".out.work", "another command")
    users = tmp_path / ".out.work-mine"
    before = _user_folder(users)
    assert remove_leftovers(tmp_path, (".out.work",), "cmd") == [killed]
    assert other.is_dir() and _snapshot(users) == before



@pytest.mark.parametrize("moment", ["before", "after", "between"])
def test_a_replace_killed_at_its_swap_leaves_a_complete_folder_and_the_next_run_clears_up(tmp_path, moment):
    """SIGKILL at the final swap (issue 47: an export killed in its final rename left ``.OUT.old<pid>`` and
    ``.OUT.work*`` for good, and OUT briefly did not exist). Before or after the exchange, OUT holds the old or the
    new folder, complete; where the file system lacks the exchange and the kill lands between its two renames, OUT is
    missing until the next run puts the old folder back. Either way the next run leaves OUT complete and removes the
    command's leftovers, and only those (a user's ``.out.old7`` stays)."""
    out = tmp_path / "out"
    replace_folder(_stage(tmp_path, "out", {"a.txt": "old"}), out, "cmd")
    old = _snapshot(out)
    users = tmp_path / ".out.old7"
    mine = _user_folder(users)
    stage = _stage(tmp_path, "out", {"a.txt": "new", "b.txt": "new"})
    status = run_forked(lambda: (kill_at_swap(moment), replace_folder(stage, out, "cmd")))
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, status
    left = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".out.") and p != users)
    if moment == "between":
        assert not out.exists() and len(left) == 2 and re.fullmatch(r"\.out\.old\d+", left[0]), left
    else:
        assert left == [stage.name] and read_marker(out)["files"] == (["a.txt"] if moment == "before" else
                                                                     ["a.txt", "b.txt"])
    new = _snapshot(out) if moment == "after" else None

    clear_leftovers(out, "cmd")  # what the next run does first, under the output's lock
    assert _snapshot(out) == (new if moment == "after" else old)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".out.")] == [users.name]
    assert _snapshot(users) == mine
    replace_folder(_stage(tmp_path, "out", {"c.txt": "next"}), out, "cmd")
    assert read_marker(out)["files"] == ["c.txt"] and (out / "c.txt").read_text() == "next"

# --- tools/reproduce.py --steps record -----------------------------------------------------------------------------


def _work(out: Path) -> Path:
    for rel, text in {"commands.log": "log\n", "results/weights.json": "{}"}.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(text)
    return out


def test_the_record_step_never_replaces_a_folder_it_did_not_write(tmp_path, monkeypatch, capsys):
    work = _work(tmp_path / "w")
    thesis = tmp_path / "thesis"
    before = _user_folder(thesis)
    args = ["--scale", "small", "--steps", "record", "--out", str(work)]
    assert reproduce_main([*args, "--record", str(thesis)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert str(thesis) in line and "will not replace this folder" in line and "--record" in line
    assert _snapshot(thesis) == before

    monkeypatch.chdir(work)  # `--record .`: the work folder itself
    work_before = _snapshot(work)
    assert reproduce_main([*args, "--record", "."]) == 2
    assert "is the current folder" in _one_line(capsys.readouterr().err) and _snapshot(work) == work_before

    rec = tmp_path / "rec"
    assert reproduce_main([*args, "--record", str(rec)]) == 0
    # (results/probe.json: the machine probe every run writes for its duration estimate)
    assert json.loads((rec / RECORD_JSON).read_text())["files"] == ["commands.log", "results/probe.json",
                                                                     "results/weights.json"]
    (work / "commands.log").write_text("log 2\n")
    assert reproduce_main([*args, "--record", str(rec)]) == 0  # its own record: replaced whole
    assert (rec / "commands.log").read_text() == "log 2\n"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    (rec / "draft.md").write_text("mine")
    with pytest.raises(RecordError, match="it holds draft.md"):
        save_record(work, rec, "small", SCALES["small"], [])
    assert (rec / "draft.md").read_text() == "mine"


def test_a_record_made_before_markers_is_still_replaced(tmp_path):
    work = _work(tmp_path / "w")
    old = tmp_path / "old"
    (old / "results").mkdir(parents=True)
    (old / "results/weights.json").write_text("{}")
    sizes = dataclasses.asdict(SCALES["small"])
    meta = {"scale": "small", "scale_sizes": sizes, "files": ["results/weights.json"]}
    (old / RECORD_JSON).write_text(json.dumps(meta))
    save_record(work, old, "small", SCALES["small"], [])
    assert read_marker(old)["made_by"].startswith("tools/reproduce.py") and (old / "commands.log").is_file()


# --- detector export -----------------------------------------------------------------------------------------------


def test_export_replaces_only_its_own_folder_follows_a_symlink_and_clears_a_killed_runs_leftovers(tmp_path, capsys):
    pytest.importorskip("onnx")
    config = write_test_config(tmp_path / "slim.yaml")

    def export(out: Path) -> tuple[int, str, str]:
        return detector_cli(["export", "--config", config, "--format", "onnx", "--out", out], capsys)

    user = tmp_path / "project"
    before = _user_folder(user, **{"deploy.json": "{}", "main.c": "int main(){}\n"})
    code, _, err = export(user)
    assert code == 2 and "will not replace this folder" in _one_line(err) and _snapshot(user) == before

    out = tmp_path / "exported"
    assert export(out)[0] == 0
    (out / "main.c").write_text("int main(){}\n")  # a file added to an older export is never lost
    code, _, err = export(out)
    assert code == 2 and "it holds main.c" in _one_line(err) and (out / "main.c").is_file()
    (out / "main.c").unlink()

    killed = work_dir(tmp_path, ".exported.work", "detector export")  # what an export killed mid-way leaves
    (killed / "fp32.onnx").write_bytes(b"x" * 1000)
    swap = work_dir(tmp_path, ".exported.work", "detector export")  # and one killed inside its final swap, on a
    (swap / "model.onnx").write_bytes(b"y" * 1000)                  # file system without RENAME_EXCHANGE
    status = run_forked(lambda: (kill_at_swap("between"), replace_folder(swap, out, "detector export")))
    assert os.WIFSIGNALED(status) and not out.exists()  # the older export waits at .exported.old<pid>
    not_ours = tmp_path / ".exported.old123"
    not_ours.mkdir()
    (not_ours / "keep.txt").write_text("mine")
    code, stdout, _ = export(out)
    assert code == 0 and "wrote" in stdout and not killed.exists() and (not_ours / "keep.txt").is_file()
    assert sorted(os.listdir(out)) == [MARKER, "deploy.json", "model.onnx"]
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".exported")) == [".exported.old123"]

    link = tmp_path / "link"
    link.symlink_to(out, target_is_directory=True)
    code, _, err = export(link)
    assert code == 0, err
    assert link.is_symlink() and sorted(p.name for p in link.iterdir()) == [MARKER, "deploy.json", "model.onnx"]



def test_a_second_export_on_a_busy_folder_names_that_folder(tmp_path, capsys, monkeypatch):
    """The third audit: the export lock's error named ``.`` (the lock's folder) instead of OUT. A live second process
    holds ``detector export``'s lock of ``exp`` (a relative ``--out``, as a user types it): the export is refused
    with one line naming ``exp`` and the holder, exit 2, and writes nothing."""
    import subprocess
    import sys

    pytest.importorskip("onnx")
    monkeypatch.chdir(tmp_path)
    config = write_test_config(tmp_path / "slim.yaml")
    hold = ("import sys; from mpchair.core.lock import folder_lock\n"
            "with folder_lock('.exp.export.lock', 'detector export', folder='exp'):\n"
            "    print('held', flush=True); sys.stdin.read()")
    holder = subprocess.Popen([sys.executable, "-c", hold], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    try:
        assert holder.stdout.readline() == "held\n"
        code, _, err = detector_cli(["export", "--config", config, "--format", "onnx", "--out", "exp"], capsys)
    finally:
        holder.communicate("")
    assert code == 2 and _one_line(err).startswith(f"error: exp: another detector export is writing this folder "
                                                   f"(pid {holder.pid})"), err
    assert not (tmp_path / "exp").exists()

# --- detector eval's OUT/data --------------------------------------------------------------------------------------


def test_eval_never_replaces_a_data_folder_it_did_not_write(tmp_path):
    labels = [Labels.empty(with_score=True)]
    out = tmp_path / "eval"
    user = out / "data"
    before = _user_folder(user)
    with pytest.raises(InputError, match=rf"^{user}: will not replace this folder"):
        write_results(out, ["000001"], labels)
    assert _snapshot(user) == before and sorted(os.listdir(out)) == ["data"]

    legacy = tmp_path / "legacy"  # a result folder written before markers: only <id>.txt files
    (legacy / "data").mkdir(parents=True)
    (legacy / "data/000009.txt").write_text("")
    write_results(legacy, ["000001"], labels)
    assert sorted(os.listdir(legacy / "data")) == [MARKER, "000001.txt"]
    assert sorted(os.listdir(legacy)) == ["data"]


@pytest.mark.parametrize("runtime", ["torch", "onnxruntime"])
def test_eval_on_the_command_line_refuses_a_users_data_folder_before_any_work(tmp_path, capsys, runtime):
    """The third audit's case as a user meets it: ``detector eval --out DIR`` replaced ``DIR/data/`` whole (a user's
    ``DIR/data/raw/measurements.csv`` deleted). Now one line naming ``DIR/data``, exit 2, before the inference (or a
    deployed runtime's export), and ``DIR`` holds what it held."""
    import torch

    from detector.checkpoint import Checkpoint, save_checkpoint
    from detector.config import load_experiment
    from detector.models import build_model

    if runtime != "torch":
        pytest.importorskip(runtime)
    config = write_test_config(tmp_path / "slim.yaml")
    torch.manual_seed(0)
    ckpt = tmp_path / "w.pt"
    save_checkpoint(ckpt, Checkpoint(model=build_model(load_experiment(config).model).state_dict()))
    data = make_tiny_dataset(tmp_path / "ds", n_frames=2)
    out = tmp_path / "ev"
    before = _user_folder(out / "data")
    code, _, err = detector_cli(["eval", "--config", config, "--data", data, "--checkpoint", ckpt, "--out", out,
                                 "--runtime", runtime, "--threads", "1"], capsys)
    line = _one_line(err)
    assert code == 2 and line.startswith(f"error: {out / 'data'}: will not replace this folder"), line
    assert _snapshot(out / "data") == before and os.listdir(out) == ["data"]


# --- detector train --out ------------------------------------------------------------------------------------------


def test_train_refuses_a_folder_that_is_not_a_run_and_removes_only_its_own_temp_files(tmp_path, capsys):
    config = write_test_config(tmp_path / "slim.yaml")
    user = tmp_path / "project"
    before = _user_folder(user, **{"config.yaml": "mine: 1\n", ".notes.tmp": "draft"})
    code, _, err = detector_cli(["train", "--config", config, "--data", tmp_path / "no-data", "--out", user], capsys)
    line = _one_line(err)
    assert code == 2 and str(user) in line and "is not a training run" in line and _snapshot(user) == before

    run = tmp_path / "run"
    (run / "eval").mkdir(parents=True)
    for name in ("eval/.metrics.json.0123456789ab.tmp", ".last.pt.a1b2c3d4e5f6.tmp", ".notes.tmp",
                 "eval/.x.tmp"):
        (run / name).write_text("x")
    remove_stale_temps(run)
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*") if p.is_file()) == [".notes.tmp", "eval/.x.tmp"]


# --- exports verified before `wrote` -------------------------------------------------------------------------------


def _onnx_with_external_weights(folder: Path, values, *, moved_to: Path | None = None) -> Path:
    """A one-node ONNX graph (y = x + w) saved as ``folder/model.onnx`` with its initializer ``w`` in
    ``folder/weights.bin`` (as a model over 2 GiB stores its weights); ``moved_to``: the graph file alone is then
    moved into that folder (what an export that forgot the weights file did)."""
    onnx = pytest.importorskip("onnx")
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper

    w = numpy_helper.from_array(np.asarray(values, dtype=np.float32), "w")
    graph = helper.make_graph([helper.make_node("Add", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [len(values)])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [len(values)])], [w])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    folder.mkdir(parents=True, exist_ok=True)
    onnx.save_model(model, str(folder / "model.onnx"), save_as_external_data=True, all_tensors_to_one_file=True,
                    location="weights.bin", size_threshold=0)
    if moved_to is None:
        return folder / "model.onnx"
    moved_to.mkdir(parents=True)
    return (folder / "model.onnx").rename(moved_to / "model.onnx")


def test_an_export_whose_weights_lie_outside_its_folder_is_refused_and_nan_weights_warn(tmp_path):
    from detector.deploy.folder import verify_export

    inside = tmp_path / "ok"
    _onnx_with_external_weights(inside, [1.0, 2.0])
    verify_export(inside, "onnx", ["model.onnx", "weights.bin"])  # complete: passes

    outside = tmp_path / "bad"  # the weights stayed in the work folder (deleted afterwards), not in the export
    _onnx_with_external_weights(tmp_path / "work", [1.0, 2.0], moved_to=outside)
    with pytest.raises(InputError, match=rf"^{outside}: the graph refers to weights.bin, which is not in the export; "
                                         "nothing was replaced"):
        verify_export(outside, "onnx", ["model.onnx"])
    (outside / "weights.bin").write_bytes(b"")  # a file of that name, listed, but not the weights: does not load
    with pytest.raises(InputError, match="the written graph does not load"):
        verify_export(outside, "onnx", ["model.onnx", "weights.bin"])

    nan = tmp_path / "nan"
    _onnx_with_external_weights(nan, [float("nan"), 1.0])
    with pytest.warns(UserWarning, match="NaN or infinite values"):
        verify_export(nan, "onnx", ["model.onnx", "weights.bin"])


def test_an_export_of_all_nan_weights_warns_in_one_line_naming_the_export(tmp_path, capsys):
    """The third audit: ``detector export`` of a checkpoint whose weights are all NaN wrote the graph without a word.
    Through the command line: the export is written (exit 0, a ``wrote`` line: the graph is a valid graph), followed
    by one ``warning:`` line naming the folder asked for (not the hidden work folder) and the NaN weights."""
    pytest.importorskip("onnx")
    import torch

    from detector.checkpoint import Checkpoint, save_checkpoint
    from detector.config import load_experiment
    from detector.models import build_model

    config = write_test_config(tmp_path / "slim.yaml")
    weights = build_model(load_experiment(config).model).state_dict()
    nan = {k: torch.full_like(v, float("nan")) if v.is_floating_point() else v for k, v in weights.items()}
    ckpt = tmp_path / "nan.pt"
    save_checkpoint(ckpt, Checkpoint(model=nan))
    out = tmp_path / "exported"
    code, stdout, err = detector_cli(["export", "--config", config, "--checkpoint", ckpt, "--format", "onnx",
                                      "--out", out], capsys)
    lines = err.strip().splitlines()
    assert code == 0 and stdout.startswith(f"wrote {out}/") and len(lines) == 1, (stdout, err)
    assert lines[0].startswith(f"warning: {out}: the exported weights hold NaN or infinite values ("), err
    assert sorted(os.listdir(out)) == [MARKER, "deploy.json", "model.onnx"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".exported.work")]

    finite = tmp_path / "finite"  # the same export of finite weights: no warning (the line above is the NaNs')
    save_checkpoint(ckpt, Checkpoint(model=weights))
    code, _, err = detector_cli(["export", "--config", config, "--checkpoint", ckpt, "--format", "onnx",
                                 "--out", finite], capsys)
    assert code == 0 and err == "", err
