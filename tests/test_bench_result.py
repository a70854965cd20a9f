"""``detector bench --json`` has one definition (``detector.bench.result.BenchResult``): every committed bench result
of the run record reads back through it and writes out byte for byte as it was written, and a file of an earlier
version (keys missing) still reads with the documented defaults."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from detector.bench.report import format_table
from detector.bench.result import BenchResult
from detector.device import Machine

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results-data" / "results"
BENCHES = sorted(p.name for p in RESULTS.glob("*bench*.json") if "budget" not in p.name and "reference" not in p.name)


def test_the_record_holds_bench_results() -> None:
    assert {"bench_default.json", "bench_reuse.json", "deploy_bench.json"} <= set(BENCHES)


@pytest.mark.parametrize("name", BENCHES)
def test_a_committed_bench_result_reads_and_writes_back_byte_for_byte(name: str) -> None:
    text = (RESULTS / name).read_text()
    result = BenchResult.from_json(json.loads(text))
    assert json.dumps(result.to_json(), indent=2) + "\n" == text
    assert result.machine.machine.cpu and result.machine.gemm in ("onednn", "mkl")
    assert result.protocol.frames == len(result.protocol.frame_ids) and result.density.frames >= 1
    assert "| model | To Device |" in format_table(result, markdown=True)


def test_an_earlier_files_missing_keys_read_as_their_defaults() -> None:
    """Rows without runtime / precision are eager fp32; a machine without ``gemm`` ran MKL; the protocol's old
    ``precision`` key survives a round trip; unknown machine keys are kept as versions."""
    d = json.loads((RESULTS / "bench_default.json").read_text())
    for m in d["models"]:
        del m["runtime"], m["precision"], m["back_to_back"]
    del d["machine"]["gemm"], d["machine"]["precision_flags"]
    d["machine"]["open3d"] = "0.19.0"
    d["protocol"]["precision"] = "fp32"
    result = BenchResult.from_json(d)
    assert {(m.runtime, m.precision) for m in result.models} == {("torch", "fp32")}
    assert result.machine.gemm == "mkl" and result.machine.precision_flags is None
    assert result.machine.versions == {"open3d": "0.19.0"} and result.machine.native_flags() == set()
    assert BenchResult.from_json(result.to_json()) == result
    assert "eager fp32 GEMMs: mkl" in format_table(result)


def test_the_machine_record_round_trips_and_tolerates_a_partial_one() -> None:
    m = Machine(cpu="Test CPU", logical_cpus=4, torch_threads=2, torch="2.13", python="3.11", device="cpu",
                malloc_env={"MALLOC_MMAP_MAX_": None}, allocator="default")
    assert Machine.from_json(m.to_json()) == m and list(m.to_json())[:3] == ["cpu", "logical_cpus", "torch_threads"]
    assert Machine.from_json({"torch_threads": 1}) == Machine(cpu="", logical_cpus=None, torch_threads=1, torch=None)
