"""AP of deployed models (``detector eval --runtime R --precision P``) against eager fp32, with a briefly trained model:
fp32 in either runtime finds the same boxes, bf16 and int8 stay close. The full-scale AP drop is the reproduction's
``deploy`` step (docs/deployment.md)."""

from __future__ import annotations

import json

import pytest
from helpers_detector import make_tiny_dataset, write_test_config

from detector.checkpoint import Checkpoint, load_model, save_checkpoint
from detector.cli import main
from detector.config import load_experiment
from detector.data.experiment import open_split
from detector.deploy.cpu import cpu_flags, skip_reason
from detector.infer import recalibrate_batchnorm
from detector.train import train

pytest.importorskip("onnxruntime")
pytest.importorskip("openvino")
pytest.importorskip("nncf")

#: Epochs of the tiny training (8 frames, batch 2): enough for a BEV AP well above 0 on its own frames (the smoke
#: training of test_train.py measured 43.5 at 12 epochs, 65.0 at 15).
EPOCHS = 16

#: How far a bf16 / int8 deployment's AP may move from eager fp32's here, in boxes: one ground-truth box found or
#: lost moves Overall R40 AP by about 100 / n_gt points (29 chairs here: 3.4). Their rounding moves the briefly
#: trained models' marginal boxes across the score or IoU threshold, in either direction. Over 6 training seeds x 2
#: models x 3 deployments x BEV / 3D (72 moves, 2026-12-06): |move| <= 1 point in 58, 1.1-3.9 in 11, 5.0-6.7 in 3
#: (the fixed 5-point bound this test had failed those: it passed or failed with the training's rounding). A broken
#: deployment (a bad export, scale or calibration) loses most boxes. The full-scale drop is the reproduction's deploy
#: step (docs/deployment.md).
BOXES_OF_SLACK = 3


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """(data, {model: (config, checkpoint)}): the dense and the sparse model (exact head) trained on 8 frames, their
    BatchNorm statistics re-estimated on them (a short run leaves them near init) and saved with the weights."""
    base = tmp_path_factory.mktemp("deploy_eval")
    data = make_tiny_dataset(base / "ds", n_frames=8, seed=0)
    out = {}
    for backbone, head in (("dense", "dense"), ("sparse", "sparse_exact")):
        cfg_path = write_test_config(base / f"{backbone}.yaml", model=dict(backbone=backbone, head=head,
                                                                          score_thr=0.05),
                                     train=dict(batch_size=2, epochs=EPOCHS))
        train(cfg_path, data, base / backbone, threads=1, progress=False, log=lambda _: None)
        cfg = load_experiment(cfg_path)
        model = load_model(cfg, base / backbone / "last.pt", "cpu")
        recalibrate_batchnorm(model, open_split(cfg, data, "train"), cfg, progress=False)
        ckpt = base / f"{backbone}_bn.pt"
        save_checkpoint(ckpt, Checkpoint(model=model.state_dict()))
        out[backbone] = (cfg_path, ckpt)
    return data, out


def _eval(capsys, cfg, data, ckpt, out, *extra) -> dict:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in ["eval", "--config", cfg, "--data", data, "--checkpoint", ckpt, "--split", "train",
                               "--out", out, "--threads", "1", "--json", *extra]])
    stdout, err = capsys.readouterr()
    assert e.value.code == 0, err
    return json.loads(stdout)


def _chairs(data) -> int:
    """Ground-truth chairs of the (training) split the test evaluates on."""
    return sum(line.startswith("Chair ") for f in (data / "training" / "label_2").glob("*.txt")
               for line in f.read_text().splitlines())


def _ap(metrics: dict, metric: str) -> float:
    """Overall R40 AP of Chair (every box of the class)."""
    return metrics["Chair"][metric]["overall"]["R40"]


@pytest.mark.slow
@pytest.mark.parametrize("backbone", ["dense", "sparse"])
def test_deployed_ap_matches_eager(trained, backbone, tmp_path, capsys):
    data, models = trained
    cfg, ckpt = models[backbone]
    eager = _eval(capsys, cfg, data, ckpt, tmp_path / "eager")
    assert _ap(eager, "bev") > 20  # a model that finds chairs, so a drop can show
    flags = cpu_flags()
    for runtime, precision in (("onnxruntime", "fp32"), ("openvino", "fp32"), ("openvino", "bf16"),
                               ("openvino", "int8"), ("onnxruntime", "int8")):
        if skip_reason(runtime, precision, flags):
            continue
        out = tmp_path / f"{runtime}_{precision}"
        got = _eval(capsys, cfg, data, ckpt, out, "--runtime", runtime, "--precision", precision,
                    "--calibration-frames", "4")
        assert len(list((out / "data").glob("*.txt"))) == 8
        for metric in ("bev", "3d"):
            drop = _ap(eager, metric) - _ap(got, metric)
            # fp32: the same maps to 1e-4, so the same boxes. bf16 / int8: within three boxes (BOXES_OF_SLACK)
            bound = 1e-6 if precision == "fp32" else BOXES_OF_SLACK * 100 / _chairs(data)
            assert abs(drop) <= bound, (runtime, precision, metric, drop, bound)


def test_eval_refuses_a_combination_this_cpu_cannot_run(trained, tmp_path, capsys):
    data, models = trained
    cfg, ckpt = models["sparse"]
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in ["eval", "--config", cfg, "--data", data, "--checkpoint", ckpt, "--runtime",
                               "onnxruntime", "--precision", "bf16", "--out", tmp_path / "x"]])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "bf16 kernels" in err
    assert not (tmp_path / "x" / "data").exists()
