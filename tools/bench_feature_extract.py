"""Feature Extract (voxelize + pillar net), the compiled form against the torch form before it: ms per frame,
interleaved frame by frame in one process, and whether the outputs are the same.

    .venv/bin/python tools/bench_feature_extract.py --config detector/configs/mpchair_sparse.yaml --data out/dataset
    .venv/bin/python tools/bench_feature_extract.py --config detector/configs/kitti_car_sparse.yaml \\
        --data ../shared/kitti_sample --split train

Per frame of ``--split`` (points as at inference: ``detector.data.experiment.load_eval_frames``), eval mode, no
autograd, batch 1, both forms run back to back in alternating order (old first on even trials, new first on odd):

* old: :func:`detector.models.voxelizer.voxelize_torch` + ``PillarFeatureNet.forward_torch`` (the code before);
* new: ``model.voxelize`` + ``model.pillar_net``, what ``detector bench``'s Feature Extract column times.

Printed: the mean over frames of each trial, median over trials, and the mean over frames of each frame's fastest
trial (steadier on a shared machine), for the voxelizer, the pillar net and both, with the old / new ratios; minor
page faults per frame; and the exactness check over every frame: voxels bit for bit, pillar features bitwise
fraction and largest absolute difference. Without ``--checkpoint`` the weights are seeded
random ones with random BatchNorm statistics (so that the BN affine is not the identity); the timings do not depend
on the weights. The grid is the config's (Matterport 768 x 512 or KITTI 496 x 432).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from detector.checkpoint import load_model
from detector.config import load_experiment
from detector.data.experiment import load_eval_frames
from detector.device import machine_info
from detector.models import PointPillars
from detector.models.voxelizer import voxelize_torch

STAGES = ("voxelize", "pillar_net", "feature_extract")


def _minor_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def _old(model: PointPillars, pts: torch.Tensor):
    v = voxelize_torch([pts], point_cloud_range=model.point_cloud_range, voxel_size=model.voxel_size,
                       output_shape=model.output_shape, max_points=model.max_points_per_pillar,
                       max_pillars=model.max_pillars_test)
    t = time.perf_counter()
    return v, model.pillar_encoder.forward_torch(v.pillars, v.num_points, v.coords), t


def _new(model: PointPillars, pts: torch.Tensor):
    v = model.voxelize([pts])
    t = time.perf_counter()
    return v, model.pillar_net(v)[0], t


@torch.no_grad()
def run(model: PointPillars, frames: list[np.ndarray], trials: int) -> dict:
    """Interleaved timings (ms per frame per trial) and the exactness check of both forms on ``frames``."""
    forms = {"old": _old, "new": _new}
    ms = {f: {s: [] for s in STAGES} for f in forms}
    best = {f: np.full((len(frames), 3), np.inf) for f in forms}  # per frame, the fastest trial
    faults = {f: [] for f in forms}
    for form in forms.values():  # warm-up: numba loads its cached kernels, torch its thread pool
        form(model, torch.from_numpy(frames[0]))
    outputs: dict[str, list] = {f: [] for f in forms}
    for trial in range(trials):
        sums = {f: np.zeros(3) for f in forms}
        nflt = {f: 0 for f in forms}
        order = ("old", "new") if trial % 2 == 0 else ("new", "old")
        for i, points in enumerate(frames):
            pts = torch.from_numpy(points)
            for f in order:
                f0 = _minor_faults()
                t0 = time.perf_counter()
                v, feats, t1 = forms[f](model, pts)
                t2 = time.perf_counter()
                nflt[f] += _minor_faults() - f0
                sums[f] += (t1 - t0, t2 - t1, t2 - t0)
                best[f][i] = np.minimum(best[f][i], (t1 - t0, t2 - t1, t2 - t0))
                if trial == 0:
                    outputs[f].append((v, feats))
        for f in forms:
            for s, total in zip(STAGES, sums[f]):
                ms[f][s].append(total / len(frames) * 1e3)
            faults[f].append(nflt[f] / len(frames))
    voxels_equal = all(all(torch.equal(a, b) for a, b in zip(vo[:3], vn[:3]))
                       for (vo, _), (vn, _) in zip(outputs["old"], outputs["new"]))
    fo = torch.cat([o for _, o in outputs["old"]])
    fn = torch.cat([o for _, o in outputs["new"]])
    result = {f: {s: statistics.median(v) for s, v in ms[f].items()} for f in forms}
    fastest = {f: dict(zip(STAGES, (best[f].mean(axis=0) * 1e3).tolist())) for f in forms}
    return {
        "ms_per_frame": result,
        "ratio_old_over_new": {s: result["old"][s] / result["new"][s] for s in STAGES},
        "ms_per_frame_fastest": fastest,
        "ratio_fastest": {s: fastest["old"][s] / fastest["new"][s] for s in STAGES},
        "minor_faults_per_frame": {f: statistics.median(v) for f, v in faults.items()},
        "voxels_bitwise_equal": voxels_equal,
        "features_bitwise_fraction": float((fo == fn).float().mean()) if fo.numel() else 1.0,
        "features_max_abs_diff": float((fo - fn).abs().max()) if fo.numel() else 0.0,
        "pillars_per_frame": fo.shape[0] / len(frames),
        "points_per_frame": float(np.mean([len(p) for p in frames])),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", type=Path, required=True, help="experiment YAML (its grid and pillar caps)")
    p.add_argument("--data", type=Path, required=True, help="KITTI-format folder")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, default=30, help="first N frames of the split")
    p.add_argument("--trials", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--checkpoint", type=Path, default=None, help="trained weights (default: seeded random ones)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of lines")
    args = p.parse_args(argv)
    if args.frames < 1 or args.trials < 1 or args.threads < 1:
        print("error: --frames, --trials and --threads must be >= 1", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    cfg = load_experiment(args.config)
    model = load_model(cfg, args.checkpoint, torch.device("cpu"))
    if args.checkpoint is None:
        gen = torch.Generator().manual_seed(0)
        bn = model.pillar_encoder.norm
        with torch.no_grad():
            for t, lo, hi in ((bn.running_mean, -1, 1), (bn.running_var, 0.05, 3), (bn.weight, 0.5, 2),
                              (bn.bias, -1, 1)):
                t.copy_(torch.rand(t.shape, generator=gen) * (hi - lo) + lo)
    frames = [f.points for f in load_eval_frames(cfg, args.data, args.split, args.frames)]
    result = run(model, frames, args.trials)
    result["machine"] = machine_info(torch.device("cpu"))
    result["config"], result["frames"], result["trials"] = str(args.config), len(frames), args.trials
    result["weights"] = str(args.checkpoint) if args.checkpoint else "seeded random, random BN statistics"
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    m = result["machine"]
    print(f"{args.config.name}: {len(frames)} frames of {args.split}, {result['points_per_frame']:.0f} points and "
          f"{result['pillars_per_frame']:.0f} pillars per frame; {args.trials} trials, {m['torch_threads']} threads, "
          f"{m['cpu']}, allocator {m['allocator']}, load {m['loadavg_1m']:.1f}; weights: {result['weights']}")
    print("  ms per frame: median over trials of the mean over frames | mean over frames of each frame's fastest trial")
    for s in STAGES:
        old, new = result["ms_per_frame"]["old"][s], result["ms_per_frame"]["new"][s]
        fo, fn = result["ms_per_frame_fastest"]["old"][s], result["ms_per_frame_fastest"]["new"][s]
        print(f"  {s:<16} old {old:8.3f}  new {new:7.3f}  old / new {old / new:6.1f}x  |  old {fo:8.3f}  new {fn:7.3f}"
              f"  old / new {fo / fn:6.1f}x")
    fl = result["minor_faults_per_frame"]
    print(f"  minor page faults per frame: old {fl['old']:.0f}, new {fl['new']:.0f}")
    print(f"  voxels bit for bit: {result['voxels_bitwise_equal']}; pillar features bitwise equal: "
          f"{result['features_bitwise_fraction']:.4%}, largest |old - new| {result['features_max_abs_diff']:.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
