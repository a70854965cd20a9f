"""The AP gap between two models with a 95 % confidence interval that holds both sources of chance: which seed trained
each model, and which test frames happened to be drawn.

Method (a paired, pooled percentile bootstrap): draw ``B`` resamples of the test frames (with replacement, the same
frame indices for every model, so that frame difficulty cancels in each difference); on every resample evaluate every
seed of both models; every (seed of A, seed of B) pair gives one gap ``AP(B) - AP(A)`` per resample. The interval is
the 2.5th and 97.5th percentiles of all pairs' gaps pooled (seed-to-seed spread widens it: pairs whose gaps differ
spread the pool), the point estimate the mean over pairs of the gap on the whole test split. With one seed per model
the interval holds frame resampling only, which the summary says (``seeds``).

Frames that are not independent draws (the consecutive frames of one streaming episode see the same chairs) are
resampled in groups: with ``groups`` each resample draws whole groups (episodes) with replacement and pools their
frames, so the interval reflects how much the gap varies between episodes, not between neighbouring frames.

AP is the KITTI protocol's (:func:`detector.eval.evaluate`, ``overall`` level, R40) or the reference's Open3D-ML mAP
(:func:`detector.eval.evaluate_open3d_ml`), in percent.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from mpchair.kitti import Labels

#: An AP function: (ground truth per frame, detections per frame) -> AP in percent.
APFunction = Callable[[Sequence[Labels], Sequence[Labels]], float]


@dataclass(frozen=True)
class GapEstimate:
    """``b - a`` AP gap: ``mean`` over seed pairs on the whole split, ``ci95`` ``(lo, hi)`` of the pooled bootstrap,
    the per-pair whole-split gaps, the seeds of each side, resamples drawn and frames."""

    mean: float
    ci95: tuple[float, float]
    pair_gaps: tuple[float, ...]
    seeds: tuple[int, int]
    resamples: int
    frames: int
    groups: int | None = None

    def to_json(self) -> dict:
        return {"mean": self.mean, "ci95": list(self.ci95), "pair_gaps": list(self.pair_gaps),
                "seeds": {"a": self.seeds[0], "b": self.seeds[1]}, "resamples": self.resamples,
                "frames": self.frames, **({} if self.groups is None else {"groups": self.groups})}

    @classmethod
    def from_json(cls, d: dict) -> GapEstimate:
        """The estimate of :meth:`to_json`'s data."""
        return cls(mean=float(d["mean"]), ci95=(float(d["ci95"][0]), float(d["ci95"][1])),
                   pair_gaps=tuple(float(x) for x in d["pair_gaps"]), seeds=(int(d["seeds"]["a"]),
                                                                              int(d["seeds"]["b"])),
                   resamples=int(d["resamples"]), frames=int(d["frames"]), groups=d.get("groups"))

    def verdict(self, reference: float) -> str:
        """What the interval supports about the gap against ``reference`` (e.g. the paper's sparse - dense gap)."""
        lo, hi = self.ci95
        if lo <= reference <= hi and lo <= 0.0 <= hi:
            return (f"inconclusive: the interval holds both no gap and the paper's {reference:+.2f}")
        if lo <= reference <= hi:
            return f"consistent with the paper's {reference:+.2f} (the interval excludes zero)"
        if lo <= 0.0 <= hi:
            return f"no gap can be told apart from zero, and the paper's {reference:+.2f} lies outside the interval"
        side = "smaller" if reference < lo else "larger"
        return f"a gap {side} in size than the paper's {reference:+.2f}, and not zero"


def kitti_ap(cls: str, metric: str = "3d") -> APFunction:
    """The KITTI protocol's ``overall`` AP_R40 of ``cls`` for ``metric`` (``3d`` or ``bev``)."""
    from detector.eval.kitti import evaluate

    def ap(gt: Sequence[Labels], dt: Sequence[Labels]) -> float:
        return float(evaluate(gt, dt, [cls]).overall[cls][metric]["R40"])

    return ap


def open3d_ml_ap(cls: str, metric: str = "3d") -> APFunction:
    """The reference's Open3D-ML mAP of ``cls`` for ``metric`` (``3d`` or ``bev``); needs Open3D-ML."""
    from detector.eval.open3d_ml import evaluate_open3d_ml

    def ap(gt: Sequence[Labels], dt: Sequence[Labels]) -> float:
        return float(evaluate_open3d_ml(gt, dt, [cls]).ap[cls][metric])

    return ap


def bootstrap_gap(gt: Sequence[Labels], a: Sequence[Sequence[Labels]], b: Sequence[Sequence[Labels]],
                  ap: APFunction, *, resamples: int = 200, seed: int = 0,
                  groups: Sequence[Sequence[int]] | None = None) -> GapEstimate:
    """The gap ``AP(b) - AP(a)`` with its pooled paired-bootstrap 95 % interval (module docstring). ``gt[f]``: the
    ground truth of test frame f; ``a[i][f]`` / ``b[j][f]``: seed i of model A's / seed j of model B's detections
    on it; ``groups``: the frame indices of each group (e.g. a stream's episodes) that a resample draws whole (None:
    every frame on its own). Same arguments and seed, same result."""
    n = len(gt)
    if n == 0 or not a or not b:
        raise ValueError("bootstrap_gap needs test frames and at least one seed of each model")
    if any(len(d) != n for d in (*a, *b)):
        raise ValueError("every seed's detections must cover every test frame")
    if groups is not None and (not groups or sorted(i for g in groups for i in g) != list(range(n))):
        raise ValueError("groups must split the test frames: every frame in exactly one group")
    full_a = [ap(gt, d) for d in a]
    full_b = [ap(gt, d) for d in b]
    pair_gaps = [fb - fa for fa in full_a for fb in full_b]
    rng = np.random.default_rng(seed)
    pooled = []
    for _ in range(resamples):
        if groups is None:
            idx = rng.integers(0, n, n)
        else:
            idx = [i for k in rng.integers(0, len(groups), len(groups)) for i in groups[k]]
        g = [gt[i] for i in idx]
        aps_a = [ap(g, [d[i] for i in idx]) for d in a]
        aps_b = [ap(g, [d[i] for i in idx]) for d in b]
        pooled += [fb - fa for fa in aps_a for fb in aps_b]
    lo, hi = (float(x) for x in np.percentile(pooled, [2.5, 97.5])) if pooled else (float("nan"), float("nan"))
    return GapEstimate(mean=float(np.mean(pair_gaps)), ci95=(lo, hi), pair_gaps=tuple(pair_gaps),
                       seeds=(len(a), len(b)), resamples=resamples, frames=n,
                       groups=None if groups is None else len(groups))
