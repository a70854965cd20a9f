"""tests/hostile_audit.py (issue 47's families re-run as real command lines) stays runnable: the first four runs of
its ``threads`` family (``detector eval``, ``stream-eval``, ``bench`` and ``train`` with ``--threads 100000``, on
the tests' tiny dataset, slim config and a random checkpoint), through its command line, write the documented JSON
and find nothing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_audit_tool_runs_a_family_and_finds_nothing(tmp_path):
    out = tmp_path / "runs.json"
    res = subprocess.run([sys.executable, str(ROOT / "tests" / "hostile_audit.py"), "--family", "threads", "--limit",
                          "4", "--json", str(out), "--bin", str(Path(sys.executable).parent)],
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.splitlines()[0].startswith(" 5 threads: 4 runs, 0 failed (-)"), res.stdout
    doc = json.loads(out.read_text())
    assert set(doc) == {"seed", "timeout_s", "seconds", "families", "runs"}
    assert doc["families"]["threads"] == {"item": 5, "runs": 4, "failed": 0, "skipped": None,
                                          "seconds": doc["families"]["threads"]["seconds"]}
    assert len(doc["runs"]) == 4
    for run in doc["runs"]:
        assert set(run) == {"family", "name", "command", "env", "exit_code", "seconds", "failures", "stderr_tail"}
        assert run["family"] == "threads" and run["failures"] == [] and run["exit_code"] == 2
        assert run["command"][0].endswith("detector") and run["command"][-2:] == ["--threads", "100000"]
        assert "--threads" in run["stderr_tail"] and "Traceback" not in run["stderr_tail"]
