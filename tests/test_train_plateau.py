"""The plateau schedule (detector.train.plateau): the rule on AP histories, the LR it sets, and a real training that
the rule stops, resumes exactly and refuses to configure wrongly."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from helpers_detector import make_tiny_dataset, write_test_config

from detector.config import TrainConfig, load_experiment
from detector.train import train
from detector.train.plateau import plateau_lr, plateau_state, plateaued, tracked_ap
from mpchair.core.errors import InputError


def test_plateaued_compares_the_last_window_with_everything_before():
    rising = [10.0, 20.0, 30.0, 40.0, 50.0, 60.0]
    assert not plateaued(rising, patience=5, min_delta=1.0)
    flat = [10.0, 50.0, 50.5, 50.9, 49.0, 50.2, 50.99]  # best of the last 5 (50.99) < 50.5 + 1.0 ... vs before 50.5
    assert plateaued(flat, patience=5, min_delta=1.0)
    assert not plateaued(flat[:-1] + [51.6], patience=5, min_delta=1.0)  # 51.6 >= 50.5 + 1.0: still rising
    assert not plateaued(flat[:5], patience=5, min_delta=1.0)  # nothing before the window yet
    assert not plateaued(flat, patience=5, min_delta=1.0, since=3)  # the window must follow the last decay


def test_plateau_state_decays_then_stops_and_restarts_the_window():
    tc = TrainConfig(schedule="plateau", eval_every=1, plateau_patience=2, plateau_min_delta=1.0, plateau_decays=1)
    aps = [10.0, 20.0, 20.5, 20.2]  # plateau at epoch 4 (best of 3-4 = 20.5 < 20 + 1): the decay
    s = plateau_state(aps, tc)
    assert (s.decays, s.decay_epochs, s.stopped_at) == (1, (4,), None)
    s = plateau_state([*aps, 20.1], tc)  # one epoch after the decay: the window is not full yet
    assert (s.decays, s.stopped_at) == (1, None)
    s = plateau_state([*aps, 20.1, 20.3], tc)  # two epochs after it, no gain of 1 point: stop
    assert (s.decays, s.decay_epochs, s.stopped_at) == (1, (4,), 6)
    s = plateau_state([*aps, 25.0, 20.3], tc)  # the decay paid off: keep going
    assert s.stopped_at is None
    no_decay = TrainConfig(schedule="plateau", eval_every=1, plateau_patience=2, plateau_decays=0)
    assert plateau_state(aps, no_decay).stopped_at == 4


def test_plateau_lr_warms_up_linearly_then_decays():
    tc = TrainConfig(schedule="plateau", eval_every=1, lr=1e-3, div_factor=10.0, warmup_epochs=1.0,
                     plateau_factor=0.1)
    assert plateau_lr(0, steps_per_epoch=10, decays=0, tc=tc) == pytest.approx(1e-4)
    assert plateau_lr(5, steps_per_epoch=10, decays=0, tc=tc) == pytest.approx(5.5e-4)
    assert plateau_lr(10, steps_per_epoch=10, decays=0, tc=tc) == pytest.approx(1e-3)
    assert plateau_lr(99, steps_per_epoch=10, decays=2, tc=tc) == pytest.approx(1e-5)
    no_warmup = TrainConfig(schedule="plateau", eval_every=1, lr=1e-3, warmup_epochs=0.0)
    assert plateau_lr(0, steps_per_epoch=10, decays=0, tc=no_warmup) == pytest.approx(1e-3)


def test_tracked_ap_is_the_3d_overall_r40_mean():
    rec = {"Chair": {"3d": {"overall": {"R40": 40.0, "R11": 1.0}}}, "Table": {"3d": {"overall": {"R40": 60.0}}}}
    assert tracked_ap(rec, ("Chair",)) == 40.0
    assert tracked_ap(rec, ("Chair", "Table")) == 50.0


@pytest.mark.parametrize("train_keys, message", [
    (dict(schedule="plateau", eval_every=2), "eval_every"),
    (dict(schedule="plateau", eval_every=1, plateau_factor=1.5), "plateau_factor"),
    (dict(schedule="plateau", eval_every=1, plateau_patience=0), "plateau_patience"),
    (dict(schedule="plateau", eval_every=1, plateau_min_delta=float("nan")), "plateau_min_delta"),
])
def test_bad_plateau_settings_are_refused(tmp_path, train_keys, message):
    path = write_test_config(tmp_path / "cfg.yaml", train=dict(batch_size=2, epochs=3, **train_keys))
    with pytest.raises(InputError, match=message):
        load_experiment(path)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny"), n_frames=4, seed=0)


def _records(run: Path, kind: str) -> list[dict]:
    return [r for r in map(json.loads, (run / "metrics.jsonl").read_text().splitlines()) if r["kind"] == kind]


def test_a_real_training_is_stopped_by_the_rule_and_resumes_exactly(data, tmp_path):
    """A huge min_delta makes every window a plateau: with patience 1 and one decay the run decays after epoch 2 and
    stops after epoch 3 (the cap is 50), logs an eval per epoch and an end record, and its LR follows plateau_lr.
    Cut by --max-steps after 3 steps and resumed, it ends in the same state."""
    keys = dict(batch_size=2, epochs=50, schedule="plateau", eval_every=1, plateau_patience=1,
                plateau_min_delta=1000.0, plateau_decays=1, plateau_factor=0.1, warmup_epochs=1.0, lr=1e-3,
                div_factor=10.0, checkpoint_every=0)
    cfg = write_test_config(tmp_path / "cfg.yaml", train=keys)
    whole = train(cfg, data, tmp_path / "whole", threads=1, split="train", eval_split="val", progress=False)
    assert (whole.ended_by, whole.epoch, whole.finished) == ("plateau", 3, True)
    assert [r["epoch"] for r in _records(tmp_path / "whole", "eval")] == [1, 2, 3]
    (end,) = _records(tmp_path / "whole", "end")
    assert (end["reason"], end["epoch"], end["decay_epochs"]) == ("plateau", 3, [2])
    steps = _records(tmp_path / "whole", "step")  # 2 steps per epoch: warm-up (1e-4, 5.5e-4), lr, lr x 0.1
    assert [round(r["lr"], 8) for r in steps] == [1e-4, 5.5e-4, 1e-3, 1e-3, 1e-4, 1e-4]

    cut = train(cfg, data, tmp_path / "cut", threads=1, split="train", eval_split="val", progress=False,
                max_steps=3)
    assert (cut.ended_by, cut.finished) == ("max-steps", False)
    resumed = train(cfg, data, tmp_path / "cut", threads=1, split="train", eval_split="val", progress=False,
                    resume=True)
    assert (resumed.ended_by, resumed.epoch, resumed.step) == ("plateau", 3, 6)
    a = torch.load(tmp_path / "whole" / "last.pt", weights_only=True)
    b = torch.load(tmp_path / "cut" / "last.pt", weights_only=True)
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key
    again = train(cfg, data, tmp_path / "whole", threads=1, split="train", eval_split="val", progress=False,
                  resume=True)  # a finished plateau run has nothing left to train
    assert (again.ended_by, again.step) == ("plateau", 6)


def test_max_minutes_stops_at_a_step_and_says_how_to_resume(data, tmp_path):
    cfg = write_test_config(tmp_path / "cfg.yaml", train=dict(batch_size=2, epochs=5, eval_every=0))
    with pytest.raises(InputError, match="--max-minutes"):
        train(cfg, data, tmp_path / "bad", threads=1, max_minutes=float("nan"), progress=False)
    result = train(cfg, data, tmp_path / "run", threads=1, max_minutes=1e-9, progress=False)
    assert (result.ended_by, result.step, result.finished) == ("time", 0, False)
    assert (tmp_path / "run" / "last.pt").is_file()
