"""``tools/reproduce.py``'s estimate (reproduction/estimate.py): the record's measured command times, each
command's latest one, scaled to the planned sizes and to this machine's probe; printed before the first command."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from reproduction.checkout import ROOT
from reproduction.cli import main
from reproduction.estimate import (
    FP32_OVER_BF16_STEP,
    PROBE_FILE,
    command_step,
    estimate,
    estimate_lines,
    probe_seconds,
    recorded_times,
)
from reproduction.scales import Scale

RECORDED = Scale(houses=8, frames_per_house=625, epochs=4, bench_frames=30, bench_trials=3, ops_frames=200,
                 precision="bf16")
PLANNED = Scale(houses=2, frames_per_house=150, epochs=2, bench_frames=5, bench_trials=2, ops_frames=10,
                precision="bf16")
BENCH = ("detector bench --config configs/models/mpchair_dense.yaml --data out/r/dataset --json-out "
         "out/r/results/bench_default.json --markdown > out/r/results/bench_default.md")
LOG = f"""\
     10.0 s  .venv/bin/mpchair synth --out out/r/houses --houses 8 --seed 0
    100.0 s  .venv/bin/mpchair generate --root out/r/houses --frames 625 --out out/r/dataset
   1000.0 s  MALLOC_MMAP_MAX_=0 .venv/bin/detector train --config configs/models/mpchair_dense_cpu.yaml \
--out out/r/runs/dense
    800.0 s  .venv/bin/detector train --config configs/models/mpchair_sparse_cpu.yaml --out out/r/runs/sparse
    300.0 s  .venv/bin/{BENCH}
    200.0 s  .venv/bin/{BENCH}
"""


def _record(tmp_path: Path, probe: dict | None) -> Path:
    rec = tmp_path / "record"
    (rec / "results").mkdir(parents=True)
    (rec / "commands.log").write_text(LOG)
    (rec / "record.json").write_text(json.dumps({"scale": "full", "scale_sizes": dataclasses.asdict(RECORDED),
                                                 "files": []}))
    if probe is not None:
        (rec / PROBE_FILE).write_text(json.dumps(probe))
    return rec


def test_the_estimate_scales_each_steps_latest_time_by_size_and_by_the_probe(tmp_path: Path) -> None:
    rec = recorded_times(_record(tmp_path, {"cpu": "A", "logical_cpus": 2, "probe_s": 0.5}))
    # the bench command ran twice (a forced re-run): its latest time counts, once
    assert rec.seconds == {("synth", "houses"): 10.0, ("generate", "frames"): 100.0, ("train", "train"): 1800.0,
                           ("bench", "bench"): 200.0}
    est = estimate(rec, PLANNED, ["synth", "generate", "train", "bench"], {"cpu": "B", "logical_cpus": 2}, 1.0)
    # this machine's probe is 2x the record's: every step 2x, on top of the sizes (300 / 5000 frames, 2 / 4 epochs,
    # 5 x 2 / 30 x 3 timed frames)
    assert est.seconds == pytest.approx({"synth": 2 * 10 * 2 / 8, "generate": 2 * 100 * 300 / 5000,
                                         "train": 2 * 1800 * 300 / 5000 * 2 / 4, "bench": 2 * 200 * 10 / 90})
    assert "probe 1.00 s against 0.50 s" in est.basis
    lines = estimate_lines(est, done={"synth"})
    assert lines[0] == "estimate: ~3 min on this machine (generate 12 s, train 2 min, bench 44 s)"
    # steps not asked for are not counted
    assert set(estimate(rec, PLANNED, ["bench"], {}, 1.0).seconds) == {"bench"}


def test_without_a_probe_only_the_same_cpu_is_scaled_and_bf16_trainings_in_fp32_take_longer(tmp_path: Path) -> None:
    rec = recorded_times(_record(tmp_path, None))
    rec = dataclasses.replace(rec, machine={"cpu": "AMD EPYC", "logical_cpus": 2})
    same = estimate(rec, RECORDED, ["train"], {"cpu": "AMD EPYC", "logical_cpus": 2}, 0.3)
    assert same.seconds == {"train": 1800.0} and "the same CPU as the record's (AMD EPYC, 2 CPUs)" in same.basis
    other = estimate(rec, RECORDED, ["train"], {"cpu": "Intel Xeon", "logical_cpus": 2}, 0.3)
    assert other.seconds == {"train": 1800.0} and "not scaled to this machine" in other.basis
    # one model name covers CPUs with and without native bf16: those are not the same CPU
    rec = dataclasses.replace(rec, machine={"cpu": "AMD EPYC", "logical_cpus": 2, "bf16": True})
    no_bf16 = estimate(rec, RECORDED, ["train"], {"cpu": "AMD EPYC", "logical_cpus": 2, "bf16": False}, 0.3)
    assert "not scaled to this machine: the record ran on AMD EPYC (2 CPUs, native bf16)" in no_bf16.basis
    assert "this one is AMD EPYC (2 CPUs, no native bf16)" in no_bf16.basis
    fp32 = estimate(rec, dataclasses.replace(RECORDED, precision="fp32"), ["train"], {"cpu": "AMD EPYC",
                                                                                     "logical_cpus": 2}, None)
    assert fp32.seconds == pytest.approx({"train": 1800.0 * FP32_OVER_BF16_STEP}) and "fp32 here" in fp32.basis
    # a training whose length is not a number of epochs is not estimated, and said so
    plateau = estimate(rec, dataclasses.replace(RECORDED, epochs=None), ["train", "generate"], {}, None)
    assert plateau.seconds == {"train": None, "generate": 100.0}
    assert estimate_lines(plateau, set())[0] == "estimate: ~2 min on this machine plus train (generate 2 min, train ?)"


def test_every_command_of_the_committed_record_belongs_to_a_step() -> None:
    log = (ROOT / "docs" / "results-data" / "commands.log").read_text().splitlines()
    unknown = [line for line in log if line.strip() and command_step(line) is None]
    assert not unknown, unknown[:3]
    rec = recorded_times(ROOT / "docs" / "results-data")
    assert {"generate", "train", "bench", "deploy"} <= {step for step, _ in rec.seconds}


def test_reproduce_prints_its_estimate_before_the_first_command(tmp_path: Path, capsys) -> None:
    assert main(["--scale", "small", "--dry-run", "--out", str(tmp_path / "w")]) == 0
    out = capsys.readouterr().out.splitlines()
    first = next(i for i, line in enumerate(out) if line.startswith("$ "))
    (at,) = [i for i, line in enumerate(out) if line.startswith("estimate: ~")]
    assert at < first and "on this machine" in out[at] and "train " in out[at], out[: first + 1]
    assert "from the record" in out[at + 1] and "commands.log" in out[at + 1]
    # the small scale trains in the configs' fp32: the record's bf16 trainings count x7
    assert "fp32 here against the record's bf16" in out[at + 1]
    assert not (tmp_path / "w" / PROBE_FILE).exists()  # a dry run writes nothing


def test_the_probe_is_a_positive_time() -> None:
    assert 0 < probe_seconds(1, repeats=1) < 60
