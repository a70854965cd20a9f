"""One OpenBLAS kernel on AVX2 and AVX-512 CPUs (mpchair/core/blas.py): the accuracy study's houses come out byte for
byte as recorded on the AVX2 machine that made them, whatever x86-64 CPU runs the test."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RECORD_MANIFEST = ROOT / "docs" / "results-data" / "accuracy" / "dataset" / "manifest.json"


def _run_python(code: str, env: dict[str, str]) -> str:
    clean = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "MPCHAIR_KEEP_BLAS_KERNEL")}
    out = subprocess.run([sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True,
                         check=True, cwd=ROOT)
    return out.stdout.strip()


def _x86_avx2() -> bool:
    from mpchair.core.cpu import cpu_flags

    return sys.platform == "linux" and {"avx2", "fma"} <= cpu_flags()


@pytest.mark.skipif(not _x86_avx2(), reason="the pin applies to Linux x86-64 CPUs with AVX2 + FMA only")
def test_importing_mpchair_pins_the_kernel_unless_the_user_chose():
    """A fresh process that imports mpchair runs OpenBLAS's Haswell kernels; a user's OPENBLAS_CORETYPE or
    MPCHAIR_KEEP_BLAS_KERNEL=1 is respected; importing numpy first leaves the environment untouched."""
    show = "import os, mpchair; print(os.environ.get('OPENBLAS_CORETYPE'))"
    assert _run_python(show, {}) == "Haswell"
    assert _run_python(show, {"OPENBLAS_CORETYPE": "Zen"}) == "Zen"
    assert _run_python(show, {"MPCHAIR_KEEP_BLAS_KERNEL": "1"}) == "None"
    assert _run_python("import numpy, os, mpchair; print(os.environ.get('OPENBLAS_CORETYPE'))", {}) == "None"
    kernel = "import mpchair; from mpchair.core.blas import openblas_kernel; print(openblas_kernel())"
    assert _run_python(kernel, {}) == "Haswell"


@pytest.mark.skipif(not _x86_avx2(), reason="the record's houses were made on an x86-64 AVX2 CPU")
def test_synth_writes_the_recorded_study_houses(tmp_path):
    """``mpchair synth --houses 12 --seed 0`` writes the 48 files whose sha256 the accuracy study's record holds
    (made on an AVX2-only EPYC; without the pin an AVX-512 CPU wrote 3 different semseg files)."""
    manifest = json.loads(RECORD_MANIFEST.read_text())
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "MPCHAIR_KEEP_BLAS_KERNEL")}
    subprocess.run([str(Path(sys.executable).parent / "mpchair"), "synth", "--out", str(tmp_path), "--houses", "12",
                    "--seed", "0"], env=env, check=True, capture_output=True)
    differ = []
    for house, entry in manifest["houses"].items():
        for name, sha in entry["files_sha256"].items():
            path = tmp_path / "v1" / "scans" / house / "house_segmentations" / name
            if hashlib.sha256(path.read_bytes()).hexdigest() != sha:
                differ.append(name)
    assert len(manifest["houses"]) == 12
    assert differ == []
