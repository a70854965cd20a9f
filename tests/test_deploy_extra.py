"""Without the deploy extra, every export / runtime path stops with one ``error:`` line naming
``pip install '.[deploy]'``, before any work and without a traceback. The missing package is simulated the way Python
sees one that is not installed: a subprocess whose ``sys.modules`` maps it to None (its import raises ImportError)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers_detector import make_tiny_dataset, write_test_config

ROOT = Path(__file__).resolve().parents[1]
HINT = "pip install '.[deploy]'"


def _detector_without(blocked: list[str], args: list) -> subprocess.CompletedProcess:
    """``detector ARGS`` in a fresh interpreter where the ``blocked`` packages cannot be imported."""
    code = ("import sys\n"
            f"for name in {blocked!r}:\n"
            "    sys.modules[name] = None\n"
            "from detector.cli import main\n"
            f"main({[str(a) for a in args]!r})\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=300)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    base = tmp_path_factory.mktemp("extra")
    return make_tiny_dataset(base / "ds", n_frames=2), write_test_config(base / "sparse.yaml",
                                                                         model=dict(backbone="sparse")), base


@pytest.mark.parametrize("blocked, args, package", [
    (["onnx"], ["export", "--format", "onnx"], "onnx"),
    (["openvino"], ["export", "--format", "openvino"], "openvino"),
    (["onnxruntime"], ["bench", "--runtime", "onnxruntime"], "onnxruntime"),
    (["openvino"], ["bench", "--runtime", "openvino"], "openvino"),
    (["nncf"], ["bench", "--runtime", "openvino", "--precision", "int8"], "nncf"),
    (["onnxruntime"], ["eval", "--runtime", "onnxruntime"], "onnxruntime"),
], ids=["export-onnx", "export-openvino", "bench-ort", "bench-openvino", "bench-int8-nncf", "eval-ort"])
def test_a_missing_deploy_package_is_one_line_naming_the_extra(setup, blocked, args, package, tmp_path):
    data, cfg, _ = setup
    out = tmp_path / "out"
    if args[0] == "export":
        full = [*args, "--config", cfg, "--out", out]
    elif args[0] == "bench":
        full = [*args, "--config", cfg, "--data", data, "--frames", "1", "--trials", "1", "--threads", "1",
                "--calibration-split", "test", "--calibration-frames", "1", "--json-out", out / "b.json"]
    else:
        from detector.checkpoint import Checkpoint, save_checkpoint
        from detector.config import load_experiment
        from detector.models import build_model

        ckpt = tmp_path / "w.pt"
        save_checkpoint(ckpt, Checkpoint(model=build_model(load_experiment(cfg).model).state_dict()))
        full = [*args, "--config", cfg, "--data", data, "--checkpoint", ckpt, "--split", "test", "--out", out]
    res = _detector_without(blocked, full)
    assert res.returncode == 2, res.stderr
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("error: "), res.stderr
    assert "Traceback" not in res.stderr
    from detector.deploy.cpu import cpu_flags, skip_reason

    cpu_refuses = args[0] == "bench" and "--precision" in args and skip_reason(
        args[args.index("--runtime") + 1], args[args.index("--precision") + 1], cpu_flags()) is not None
    if cpu_refuses:  # a CPU without native int8 refuses the row before any package is needed: that line instead
        assert "native int8" in res.stderr, res.stderr
    else:
        assert HINT in res.stderr and package in res.stderr
    assert not out.exists() or not any(out.iterdir())  # nothing written


def test_the_eager_paths_need_no_deploy_package(setup, tmp_path):
    """bench and eval without --runtime import none of the extra."""
    data, cfg, _ = setup
    res = _detector_without(["onnx", "onnxruntime", "openvino", "nncf"],
                            ["bench", "--config", cfg, "--data", data, "--frames", "1", "--trials", "1",
                             "--warmup", "0", "--threads", "1"])
    assert res.returncode == 0, res.stderr
    assert "sparse" in res.stdout
