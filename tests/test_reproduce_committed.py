"""``tools/reproduce.py --weights committed`` (issue 48): the train step takes the committed weights instead of
training (on a small model packed here, never the repository's detector/pretrained), their provenance reaches the
report and the record, and ``--bench-runs N`` makes the bench steps run N processes whose median and min-max the
report quotes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml

import detector.pretrained as pretrained
from detector.bench.repeat import format_repeated, repeated
from detector.bench.result import BenchResult
from detector.checkpoint import Checkpoint, load_checkpoint, load_model, pack_pretrained, save_checkpoint
from detector.config import CONFIG_DIR, load_experiment
from detector.models import build_model
from mpchair.core.config import to_dict
from reproduction.cli import main
from reproduction.committed import folder_conflict, install, read_committed
from reproduction.committed import main as committed_main
from reproduction.record import save_record
from reproduction.report import targets_section, write_report
from reproduction.runner import Runner
from reproduction.scales import SCALES
from reproduction.status import status_lines
from reproduction.steps import Plan, run_train


@pytest.fixture(scope="module")
def packed(tmp_path_factory) -> dict:
    """A folder of packed weights like detector/pretrained, with ``dense`` and ``sparse`` (seeded random models of
    the reproduction's CPU configs, the models the install checks the files against, saved as a training's
    checkpoint with its resolved config, packed in bf16 by the same code as tools/pack_pretrained.py)."""
    tmp = tmp_path_factory.mktemp("committed")
    folder = tmp / "pretrained"
    configs = {}
    for m in ("dense", "sparse"):
        cfg = load_experiment(CONFIG_DIR / f"mpchair_{m}_cpu.yaml")
        configs[m] = tmp / f"{m}.yaml"
        configs[m].write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))  # as detector train writes it
        torch.manual_seed(1)
        save_checkpoint(tmp / f"{m}.pt", Checkpoint(model=build_model(cfg.model).state_dict(), config=to_dict(cfg)))
        pack_pretrained(tmp / f"{m}.pt", {m: f"mpchair_{m}_cpu"}, folder)
    return {"tmp": tmp, "folder": folder, "configs": configs}


def _commands(text: str) -> list[str]:
    return [ln[2:] for ln in text.splitlines() if ln.startswith("$ ")]


def test_dry_run_lists_the_committed_weights_and_the_bench_runs(packed, tmp_path: Path, capsys) -> None:
    """The full list for ``--weights committed`` (full scale: 3 bench runs): no ``detector train``, one
    ``reproduction.committed`` per model into its run folder, ``--runs 3`` on the bench step's two benches and the
    deploy step's runtime bench (not its --rate budget, which detector bench refuses to repeat)."""
    out = tmp_path / "w"
    assert main(["--dry-run", "--weights", "committed", "--pretrained", str(packed["folder"]), "--out",
                 str(out)]) == 0
    cmds = _commands(capsys.readouterr().out)
    assert not [c for c in cmds if " train " in c]
    installs = [c for c in cmds if "-m reproduction.committed" in c]
    assert [c.split("-m reproduction.committed ")[1] for c in installs] == [
        f"--model {m} --out {out / 'runs' / m} --pretrained {packed['folder']}" for m in ("dense", "sparse")]
    bench = [c for c in cmds if "/detector bench " in c]
    timed = [c for c in bench if "--rate" not in c and "kitti_car" not in c and "sparse1_dense23" not in c]
    assert len(timed) == 3 and all("--trials 3 --runs 3 " in c for c in timed)  # bench x2 allocators, deploy
    assert [c for c in bench if "--rate" in c] and all("--runs" not in c for c in bench if "--rate" in c)
    assert all("--runs" not in c for c in bench if "sparse1_dense23" in c)  # the ablation benches run once
    # --bench-runs 1: the commands as before it existed; the quick scale runs once by default
    assert main(["--dry-run", "--weights", "committed", "--pretrained", str(packed["folder"]), "--bench-runs", "1",
                 "--steps", "bench", "--out", str(out)]) == 0
    assert all("--runs" not in c for c in _commands(capsys.readouterr().out))
    assert main(["--dry-run", "--scale", "small", "--steps", "bench", "--out", str(tmp_path / "s")]) == 0
    assert all("--runs" not in c for c in _commands(capsys.readouterr().out))


def test_the_dry_run_says_what_the_train_step_installs_also_for_a_restored_record(packed, tmp_path: Path,
                                                                                   capsys) -> None:
    """``--weights committed --dry-run`` and the dry run of a record made with committed weights (``--from-record``,
    which a dry run does not restore) list the install of each ``pretrained:<name>`` into ``runs/<model>/``, as the
    real run does it, and no ``detector train``."""
    def train_step(argv: list[str], out: Path) -> list[str]:
        assert main(["--dry-run", "--steps", "train", "--pretrained", str(packed["folder"]), *argv, "--out",
                     str(out)]) == 0
        text = capsys.readouterr().out
        assert not [c for c in _commands(text) if " train " in c]
        assert [c.split("-m reproduction.committed ")[1] for c in _commands(text)] == [
            f"--model {m} --out {out / 'runs' / m} --pretrained {packed['folder']}" for m in ("dense", "sparse")]
        return [ln for ln in text.splitlines() if "would install" in ln]

    index = pretrained.read_index(packed["folder"])
    want = [f"[train] {m}: no training; would install pretrained:{m} ({m}.pt, sha256 {index[m].sha256[:12]}) into "
            f"{tmp_path / 'w' / 'runs' / m}/ (last.pt, config.yaml, done)" for m in ("dense", "sparse")]
    assert train_step(["--weights", "committed"], tmp_path / "w") == want
    # a record of a --weights committed run: its runs/<model>/done name the committed weights (no last.pt)
    made = tmp_path / "made"
    for m in ("dense", "sparse"):
        install(made / "runs" / m, m, packed["folder"], tmp_path / "no-study")
    (made / "results").mkdir()
    (made / "results" / "density.json").write_text("{}\n")  # the stats step's output
    save_record(made, tmp_path / "record", "full", SCALES["full"], [])
    assert not list((tmp_path / "record").rglob("last.pt"))
    assert train_step(["--from-record", str(tmp_path / "record")], tmp_path / "w") == want
    assert not (tmp_path / "w" / "runs").exists()  # a dry run restores nothing
    # ... but lists the steps as the real run, which restores first, runs them (runs/<model>/done and config.yaml,
    # results/density.json): the record's stats are done
    assert main(["--dry-run", "--steps", "stats,train", "--pretrained", str(packed["folder"]), "--from-record",
                 str(tmp_path / "record"), "--out", str(tmp_path / "w")]) == 0
    text = capsys.readouterr().out
    assert f"would restore 5 file(s) of the record {tmp_path / 'record'} into {tmp_path / 'w'} first" in text
    assert "[stats] outputs exist, skipped" in text and not [c for c in _commands(text) if " stats " in c]
    assert len([c for c in _commands(text) if "-m reproduction.committed" in c]) == 2


def test_a_missing_name_or_another_dataset_is_one_line_before_any_step(packed, tmp_path: Path, capsys) -> None:
    only_dense = tmp_path / "only_dense"
    pack_pretrained(packed["tmp"] / "dense.pt", {"dense": "mpchair_dense_cpu"}, only_dense)
    assert main(["--dry-run", "--weights", "committed", "--pretrained", str(only_dense), "--out",
                 str(tmp_path / "w")]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and not _commands(captured.out)
    assert err.startswith("error: --weights committed: no committed weights pretrained:sparse in")
    assert "index.json lists dense" in err and "tools/pack_pretrained.py" in err and "--weights train" in err
    # the committed weights were trained on the full scale's house-split dataset: the quick scales are refused
    for argv in (["--scale", "small"], ["--seed", "1"]):
        assert main(["--dry-run", "--weights", "committed", "--pretrained", str(packed["folder"]), *argv, "--out",
                     str(tmp_path / "x")]) == 2
        captured = capsys.readouterr()
        assert len(captured.err.strip().splitlines()) == 1 and not _commands(captured.out)
        assert "the committed weights were trained on the accuracy study's dataset (12 houses x 400 frames" in (
            captured.err)


def test_a_file_that_is_not_the_model_its_name_says_is_one_line_and_installs_nothing(packed, tmp_path: Path,
                                                                                     capsys) -> None:
    """An index whose names point at the other model's weights (each file's SHA-256 right, so only its contents
    tell): tools/reproduce.py refuses it before any step and the train step's install refuses it before writing,
    each in one line naming the file and the name, exit 2, no run folder filled."""
    swapped = tmp_path / "swapped"
    pack_pretrained(packed["tmp"] / "dense.pt", {"sparse": "mpchair_sparse_cpu"}, swapped)  # sparse.pt: dense weights
    pack_pretrained(packed["tmp"] / "sparse.pt", {"dense": "mpchair_dense_cpu"}, swapped)  # dense.pt: sparse weights
    out = tmp_path / "w"
    assert main(["--weights", "committed", "--pretrained", str(swapped), "--steps", "train", "--out", str(out)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and not _commands(captured.out)
    assert err.startswith(f"error: {swapped / 'dense.pt'}: pretrained:dense is not the dense model index.json lists "
                          "it as: its weights do not fit the model mpchair_dense_cpu.yaml builds (")
    assert "tensor(s) missing" in err and "nothing installed" in err and "--weights train" in err
    assert not (out / "runs").exists()
    run = out / "runs" / "sparse"
    assert committed_main(["--model", "sparse", "--out", str(run), "--pretrained", str(swapped)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(
        f"error: {swapped / 'sparse.pt'}: pretrained:sparse is not the sparse model index.json lists it as: its "
        "weights do not fit the model mpchair_sparse_cpu.yaml builds (")
    assert "tensor(s) of another shape (first backbone." in err
    assert not run.exists()
    # the right files install (the same check passes them)
    assert committed_main(["--model", "sparse", "--out", str(run), "--pretrained", str(packed["folder"])]) == 0
    assert read_committed(run).name == "sparse"


def test_the_train_step_puts_the_committed_weights_where_the_later_steps_read_them(packed, tmp_path: Path,
                                                                                  monkeypatch) -> None:
    """A real train step (its command in a process of its own): runs/<model>/last.pt loads to exactly the state dict
    ``--checkpoint pretrained:NAME`` gives (bf16 upcast by the one loader), config.yaml is the weights' experiment,
    done names the file and its SHA-256; a second run finds the step done; the work folder then refuses
    ``--weights train``."""
    out = tmp_path / "w"
    plan = Plan(out=out, scale=SCALES["full"], steps=("train",), weights="committed", pretrained=packed["folder"])
    run_train(plan, Runner(False, out / "commands.log"))
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", packed["folder"])
    index = pretrained.read_index()
    for m in ("dense", "sparse"):
        run = out / "runs" / m
        cfg = load_experiment(packed["configs"][m])
        ours, theirs = (load_model(cfg, c).state_dict() for c in (run / "last.pt", f"pretrained:{m}"))
        assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
        assert next(v for v in load_checkpoint(run / "last.pt").model.values()
                    if v.is_floating_point()).dtype == torch.bfloat16
        assert load_experiment(run / "config.yaml") == cfg
        held = read_committed(run)
        assert (held.name, held.sha256, held.training) == (m, index[m].sha256, None)  # not one of the study's
    assert len((out / "commands.log").read_text().splitlines()) == 2
    run_train(plan, Runner(False, out / "commands.log"))  # done: nothing runs again
    assert len((out / "commands.log").read_text().splitlines()) == 2
    assert "holds the committed weights pretrained:dense" in folder_conflict(out, "train", None)
    assert "    dense: the committed weights pretrained:dense (training not found" in "\n".join(status_lines(out))


def test_the_report_and_the_record_name_the_committed_weights(packed, tmp_path: Path) -> None:
    """``done`` names the accuracy-study training whose config the weights store (its epochs and what ended it); the
    report's opening, status and training-time sections and the record's record.json say whose weights they are."""
    record = tmp_path / "accuracy"
    study_run = record / "runs" / "dense_s0"
    study_run.mkdir(parents=True)
    (study_run / "config.yaml").write_text(packed["configs"]["dense"].read_text())
    (study_run / "metrics.jsonl").write_text(
        "".join(json.dumps(r) + "\n" for r in ({"kind": "epoch", "epoch": 1, "time_s": 60.0},
                                               {"kind": "epoch", "epoch": 2, "time_s": 61.0},
                                               {"kind": "end", "epoch": 2, "reason": "plateau"})))
    out = tmp_path / "w"
    dense = install(out / "runs" / "dense", "dense", packed["folder"], record)
    install(out / "runs" / "sparse", "sparse", packed["folder"], record)
    assert (dense.training, dense.epochs, dense.ended_by) == ("dense_s0", 2, "plateau")
    sha = pretrained.read_index(packed["folder"])["dense"].sha256
    assert read_committed(out / "runs" / "dense") == dense and dense.sha256 == sha

    report = tmp_path / "results.md"
    write_report(report, out, out / "results", "full", SCALES["full"])
    text = report.read_text()
    opening = text.split("\n\n")[1]
    assert opening.startswith("Written by `tools/reproduce.py --scale full --weights committed` (12 synthetic houses "
                              "x 400 frames, no training: the accuracy study's committed weights pretrained:dense "
                              f"(dense_s0, 2 epochs, ended by plateau; sha256 {sha[:12]}) / pretrained:sparse "
                              "(training not found in the study's record; sha256 ")
    assert "bench 30 frames x 3 trials x 3 runs)" in opening and "training took" not in opening
    assert "**The models are the accuracy study's, not trained by this run:**" in text
    training = text.split("## Training time")[1].split("\n## ")[0]
    assert "not trained by this run (`--weights committed`)" in training and "not run" not in training

    save_record(out, tmp_path / "record", "full", SCALES["full"], [])
    meta = json.loads((tmp_path / "record" / "record.json").read_text())
    assert meta["weights"]["dense"] == {"weights": "committed", "name": "dense", "sha256": sha,
                                        "training": "dense_s0", "epochs": 2, "ended_by": "plateau",
                                        "record": str(record)}
    assert "runs/dense/done" in meta["files"] and "runs/dense/last.pt" not in meta["files"]


def _bench(backbone_ms: dict[str, float]) -> dict:
    """A bench JSON of dense and sparse with the given backbone ms (other components 1 ms)."""
    models = []
    for name, ms in backbone_ms.items():
        comps = {k: {"mean_ms": 1.0, "std_ms": 0.0} for k in ("to_device", "feature_extract", "feature_net", "head",
                                                             "bbox_extract")}
        comps["backbone"] = {"mean_ms": ms, "std_ms": 0.0}
        comps["total"] = {"mean_ms": ms + 5.0, "std_ms": 0.0}
        models.append({"name": name, "peer": None, "components": comps})
    return {"models": models}


def test_the_report_quotes_a_multi_run_bench_as_median_and_min_max(tmp_path: Path) -> None:
    """A ``detector bench --runs 3`` JSON (the first run's result with ``repeated``, as bench.repeat writes it): the
    target rows quote the median ratio and its min-max over the runs, the Markdown table lists the spread; a one-run
    JSON reads as before."""
    runs = [_bench({"dense": 100.0, "sparse": s}) for s in (25.0, 20.0, 100.0 / 3)]  # backbone 4x, 5x, 3x
    rep = repeated([BenchResult.from_json(r) for r in runs])
    (tmp_path / "bench_default.json").write_text(json.dumps({**runs[0], "repeated": rep.to_json()}))
    rows = targets_section(tmp_path)
    assert ("| dense / sparse, backbone time, allocator default | >= 15 (paper 13.3 on a robot CPU) | 4.0x (median "
            "of 3 runs, 3.0-5.0x) |") in rows
    # the bench step's table (detector bench --runs 3 --markdown) lists the spread one ratio row per line
    listed = format_repeated(rep, markdown=True).splitlines()
    assert listed[:2] == ["Over 3 runs, each in a process of its own: median [min-max]:", ""]
    assert listed[2].startswith("- dense / sparse: ") and "backbone 4.00x [3.00-5.00]" in listed[2]
    (tmp_path / "bench_default.json").write_text(json.dumps(runs[1]))
    assert "| dense / sparse, backbone time, allocator default | >= 15 (paper 13.3 on a robot CPU) | 5.0x |" in (
        targets_section(tmp_path))
