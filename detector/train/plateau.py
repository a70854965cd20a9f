"""The ``plateau`` schedule: train until the validation AP stops rising, then lower the LR, and stop at the next
plateau.

The rule (docs/training.md, "Trained to a plateau"): after every epoch the weights are evaluated on the validation
split (``train.eval_every`` must be 1); the tracked number is the 3D AP, Overall, R40, of the eval classes (their
mean where there are several). The run has **plateaued** at epoch ``e`` when the best AP of the last
``plateau_patience`` epochs (``e - patience + 1 .. e``) is less than ``plateau_min_delta`` points above the best AP
of every epoch before them. Each of the first ``plateau_decays`` plateaus multiplies the LR by ``plateau_factor``
and restarts the window (the next plateau needs ``patience`` epochs after the decay); the plateau after them stops
the run. ``train.epochs`` stays the cap: a run that reaches it without a final plateau ends there, "not plateaued".

The LR of global step ``s`` is a pure function of ``s`` and the number of decays so far: a linear warm-up from
``lr / div_factor`` to ``lr`` over the first ``warmup_epochs`` epochs, then ``lr * plateau_factor ** decays``.
The decays are a function of the AP history alone, which the run's ``metrics.jsonl`` holds, so a resumed run
recomputes them from its log and continues exactly.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from detector.config import TrainConfig


@dataclass(frozen=True)
class PlateauState:
    """What the AP history decided: the LR decays so far and the epochs after which they came, and the epoch after
    which the run stopped (None: still training)."""

    decays: int
    decay_epochs: tuple[int, ...]
    stopped_at: int | None


def plateaued(aps: Sequence[float], *, patience: int, min_delta: float, since: int = 0) -> bool:
    """Whether the history ``aps`` (``aps[i]``: AP after epoch ``i + 1``) has plateaued at its last epoch: its last
    ``patience`` epochs all come after epoch ``since`` and their best is below the best before them + ``min_delta``."""
    n = len(aps)
    if n - since < patience or n <= patience:
        return False
    before, window = aps[: n - patience], aps[n - patience:]
    return max(window) < max(before) + min_delta


def plateau_state(aps: Sequence[float], tc: TrainConfig) -> PlateauState:
    """Replay the rule over the AP history ``aps`` (one value per completed epoch, from epoch 1)."""
    decay_epochs: list[int] = []
    since = 0
    for epoch in range(1, len(aps) + 1):
        if not plateaued(aps[:epoch], patience=tc.plateau_patience, min_delta=tc.plateau_min_delta, since=since):
            continue
        if len(decay_epochs) < tc.plateau_decays:
            decay_epochs.append(epoch)
            since = epoch
        else:
            return PlateauState(decays=len(decay_epochs), decay_epochs=tuple(decay_epochs), stopped_at=epoch)
    return PlateauState(decays=len(decay_epochs), decay_epochs=tuple(decay_epochs), stopped_at=None)


def plateau_lr(step: int, *, steps_per_epoch: int, decays: int, tc: TrainConfig) -> float:
    """The LR of global step ``step`` (0-based): linear warm-up over ``warmup_epochs``, then the decayed plateau LR."""
    warmup = int(round(tc.warmup_epochs * steps_per_epoch))
    if step < warmup:
        start = tc.lr / tc.div_factor
        return start + (tc.lr - start) * step / warmup
    return tc.lr * tc.plateau_factor ** decays


def tracked_ap(result: Mapping, classes: Sequence[str]) -> float:
    """The number the rule tracks in an evaluation record: 3D AP Overall R40, mean over ``classes`` (NaN: none)."""
    values = [float(result[c]["3d"]["overall"]["R40"]) for c in classes if c in result]
    return sum(values) / len(values) if values else math.nan
