"""Training: AdamW (constant or one-cycle LR) on a KITTI-format split, reproducible, resumable and optionally
distributed (torchrun + DDP).

One run lives in one folder ``RUN``::

    RUN/config.yaml              the experiment as loaded (with --epochs applied)
    RUN/gt_database.npz          the GT-sampling database of the training split (rebuilt if the data changes)
    RUN/metrics.jsonl            one JSON object per line: {"kind": "step" | "epoch" | "eval", ...}
    RUN/checkpoints/epoch_NNN.pt after every ``train.checkpoint_every`` epochs (and the last one)
    RUN/last.pt                  the newest state (also written at --max-steps and every SAVE_INTERVAL_S seconds)

**Distributed semantics (exactly a single process with batch G).** Every BatchNorm computes its statistics over the
whole global batch (:func:`convert_to_global_batchnorm`: torch's ``SyncBatchNorm`` refuses CPU tensors, so the
project uses its own all-reduce of sums), and the losses are normalised by the number of positive anchors of the
global batch. Therefore N processes x batch b and one process x batch N·b see the same statistics, losses and
gradients, up to float summation order.

Modules, in the order a run meets them:

- ``loop``: :func:`train` (the orchestrator: arguments, plan and checks, process group, folder lock) and the epoch
  loop (records, checkpoints, periodic evaluation).
- ``resume``: which ``last.pt`` may continue a config (only :data:`RESUMABLE_CHANGES` may differ) and restoring it.
- ``data_order``: :func:`epoch_frames` and :func:`rank_batches` (which samples every step of every rank sees, a
  function of ``(seed, epoch, slot)`` only) and the loader.
- ``schedule``: :func:`build_scheduler` (constant LR or one-cycle over the run's global steps).
- ``step``: :func:`train_step`, one forward / backward / AdamW step, returning its :class:`StepStats`.
- ``distributed``: :class:`DistInfo`, the global-batch BatchNorm, all-reduce, barrier, the process group.
- ``metrics``: :class:`MetricsLog` (``metrics.jsonl``) and the printed plan / estimate / epoch / validation lines.
- ``run_folder``: ``config.yaml``, the cached GT database, stale temp files.
"""

from detector.train.data_order import epoch_frames, rank_batches
from detector.train.distributed import DistInfo, convert_to_global_batchnorm, dist_info_from_env
from detector.train.loop import SAVE_INTERVAL_S, RunPlan, TrainResult, train
from detector.train.metrics import MetricsLog, format_duration
from detector.train.resume import RESUMABLE_CHANGES, Position
from detector.train.run_folder import load_or_build_database
from detector.train.schedule import build_scheduler
from detector.train.step import ModelAndOptimiser, StepSettings, StepStats, TrainingError, train_step

__all__ = [
    "RESUMABLE_CHANGES",
    "SAVE_INTERVAL_S",
    "DistInfo",
    "MetricsLog",
    "ModelAndOptimiser",
    "Position",
    "RunPlan",
    "StepSettings",
    "StepStats",
    "TrainResult",
    "TrainingError",
    "build_scheduler",
    "convert_to_global_batchnorm",
    "dist_info_from_env",
    "epoch_frames",
    "format_duration",
    "load_or_build_database",
    "rank_batches",
    "train",
    "train_step",
]
