"""Distributed training: 2 CPU processes (torchrun, gloo) x batch 1 == 1 process x batch 2, step for step.

The equivalence holds because every BatchNorm uses global-batch statistics across ranks and the losses are
normalised by the global number of positive anchors (see ``detector/train/``). Compared per step: the total loss and
the gradient norm (both before the optimiser step, so they check the forward statistics and the all-reduced
gradients directly), the learning rate and beta1 of the one-cycle schedule (whose length counts global steps); after
the run: every weight's and BatchNorm buffer's change from the shared initial state. The job's output: one plan, epoch
line and summary (rank 0's) and no deprecation warning.

This is the suite's one torchrun launch (about 10 s of process start-up), so it checks all of that at once.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_detector import make_tiny_dataset, onecycle_curve, write_test_config

from detector.config import load_experiment
from detector.models import build_model
from detector.train import train

ROOT = Path(__file__).resolve().parents[1]
STEPS = 3


def _steps(run: Path) -> list[dict]:
    lines = (run / "metrics.jsonl").read_text().splitlines()
    return [r for r in map(json.loads, lines) if r["kind"] == "step"]


def _change(state: dict, initial: dict, keys: list[str]) -> torch.Tensor:
    """The run's change of the given tensors, flattened into one float64 vector."""
    return torch.cat([(state[k].double() - initial[k].double()).reshape(-1) for k in keys])


@pytest.mark.slow
def test_two_processes_equal_one_process_with_the_same_global_batch(tmp_path):
    data = make_tiny_dataset(tmp_path / "data", n_frames=6, seed=5)
    augment = dict(flip_y=True, rotation=[-0.2, 0.2], scaling=[0.95, 1.05])
    # 4 samples per epoch / global batch 2 = 2 global steps per epoch, 2 epochs: a 4-step one-cycle schedule in both
    # runs (counting per-rank steps would give 8 and another curve); the 3 steps cross an epoch boundary.
    schedule = dict(epochs=2, samples_per_epoch=4, schedule="onecycle", lr=0.003)
    per_rank = write_test_config(tmp_path / "per_rank.yaml", data=augment, train=dict(batch_size=1, **schedule))
    single = write_test_config(tmp_path / "single.yaml", data=augment, train=dict(batch_size=2, **schedule))

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2", "-m", "detector",
           "train", "--config", str(per_rank), "--data", str(data), "--out", str(tmp_path / "ddp"),
           "--max-steps", str(STEPS), "--threads", "1", "--no-progress"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    # Rank 0 speaks for the job (the summary once, not once per rank), and no rank warns about a deprecated call
    # (torch.distributed.nn.functional.all_reduce did, once per call site and rank).
    assert proc.stdout.count("trained 1 epoch(s), 3 step(s)") == 1, proc.stdout
    assert proc.stdout.count("training 3 step(s): 2 epochs x 2 steps (global batch 2)") == 1, proc.stdout
    assert proc.stdout.count("epoch 1/2: loss ") == 1, proc.stdout
    assert "FutureWarning" not in proc.stderr and "DeprecationWarning" not in proc.stderr, proc.stderr[-3000:]
    # nor about gradient layouts (1x1 convs on channels-last maps: tests/test_models_build.py checks every weight)
    assert "Grad strides do not match" not in proc.stderr, proc.stderr[-3000:]

    train(single, data, tmp_path / "one", max_steps=STEPS, threads=1, progress=False)

    ddp_steps, one_steps = _steps(tmp_path / "ddp"), _steps(tmp_path / "one")
    assert len(ddp_steps) == len(one_steps) == STEPS
    # Step 1 starts from identical weights: loss and gradient agree to float summation noise (measured: 6e-6 and
    # 1.5e-4 relative; rank-local BatchNorm statistics would change the loss itself). Later steps inherit AdamW's
    # amplification of that noise (near-zero gradients become +-lr updates): measured 3e-4 on the loss after 3 steps.
    np.testing.assert_allclose(ddp_steps[0]["loss_total"], one_steps[0]["loss_total"], rtol=1e-5)
    np.testing.assert_allclose(ddp_steps[0]["grad_norm"], one_steps[0]["grad_norm"], rtol=1e-3)
    curve = onecycle_curve(4, 0.003)[:STEPS]
    for a, b, (lr, beta1) in zip(ddp_steps, one_steps, curve):
        assert a["num_pos"] == b["num_pos"] > 0  # the same samples (and augmentations) make up each global batch
        np.testing.assert_allclose(a["loss_total"], b["loss_total"], rtol=2e-3)
        np.testing.assert_allclose(a["grad_norm"], b["grad_norm"], rtol=5e-3)
        np.testing.assert_allclose([a["lr"], a["beta1"]], [lr, beta1], rtol=1e-9)
        assert (a["lr"], a["beta1"]) == (b["lr"], b["beta1"])

    ddp_state = torch.load(tmp_path / "ddp" / "last.pt", weights_only=True)
    one_state = torch.load(tmp_path / "one" / "last.pt", weights_only=True)
    assert ddp_state["step"] == one_state["step"] == STEPS and ddp_state["global_batch"] == 2
    assert ddp_state["scheduler"]["total_steps"] == one_state["scheduler"]["total_steps"] == 4
    assert ddp_state["model"].keys() == one_state["model"].keys()
    # Both runs start from the weights train() builds under the config's seed. Compare what the 3 steps changed:
    # AdamW moves each weight by about lr per step, so single weights cannot tell a missing step from noise (a few
    # near-zero gradients flip sign between the runs: measured max |diff| 5.7e-3 against a largest change of 3.9e-3),
    # but the change of all weights together can. Measured |change(ddp) - change(one)| / |change(one)|: weights
    # 0.077, BatchNorm running statistics 0.001; stopping one run after 2 steps instead gives 0.33 for both.
    cfg = load_experiment(single)
    torch.manual_seed(cfg.train.seed)
    initial = build_model(cfg.model).state_dict()
    floats = [k for k, v in initial.items() if v.is_floating_point()]
    weights = [k for k in floats if "running_" not in k]
    stats = [k for k in floats if "running_" in k]
    for keys, tol in ((weights, 0.15), (stats, 0.01)):
        one = _change(one_state["model"], initial, keys)
        diff = _change(ddp_state["model"], initial, keys) - one
        assert float(one.norm()) > 0
        assert float(diff.norm() / one.norm()) < tol, (keys[0], float(diff.norm() / one.norm()))
    for key in initial.keys() - set(floats):  # BatchNorm's num_batches_tracked
        assert torch.equal(ddp_state["model"][key], one_state["model"][key]), key
