"""Why BBox Extract can time differently in two models that share its code: count each model's NMS candidates and
time each model's ``postprocess`` on both models' head outputs (same frames, interleaved, one process).

    .venv/bin/python tools/bench_bbox_extract.py --work out/reproduce-full --frames 30 --trials 3

``--work`` is a `tools/reproduce.py` work folder (its dataset and runs/{dense,sparse}/last.pt); the paper's 768 x 512
configs are used, as in `detector bench`. If both postprocesses are slower on the same model's outputs, the gap is the
input (more candidates above the score threshold reach rotated NMS), not the code. If neither is, the gap in the
per-frame pipeline is the state each model's backbone leaves behind: `detector bench`'s back-to-back table times the
two models' post-processing after the same kind of stage (docs/benchmarks.md, "Shared components").
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from detector.checkpoint import load_model
from detector.config import load_experiment
from detector.data.experiment import load_eval_frames

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("dense", "sparse")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work", type=Path, default=ROOT / "out" / "reproduce-full", help="tools/reproduce.py work folder")
    p.add_argument("--frames", type=int, default=30, help="first N frames of the test split")
    p.add_argument("--trials", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", action="store_true", help="print one JSON object instead of lines")
    args = p.parse_args(argv)
    ckpts = {m: args.work / "runs" / m / "last.pt" for m in MODELS}
    missing = [str(c) for c in ckpts.values() if not c.exists()]
    if missing or args.frames < 1 or args.trials < 1:
        why = f"no checkpoint {', '.join(missing)}" if missing else "--frames and --trials must be >= 1"
        print(f"error: {why}", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    models, outputs = {}, {}
    for m in MODELS:
        cfg = load_experiment(ROOT / "detector" / "configs" / f"mpchair_{m}.yaml")
        model = models[m] = load_model(cfg, ckpts[m], torch.device("cpu"))
        outputs[m] = []
        with torch.no_grad():
            for f in load_eval_frames(cfg, args.work / "dataset", "test", args.frames):
                voxels = model.voxelize([torch.from_numpy(f.points)])
                features, coords = model.pillar_net(voxels)
                x, active = model.backbone_neck(model.feature_net(features, coords, voxels.batch_size))
                outputs[m].append(model.head(x, active))
    result: dict = {"candidates": {}, "postprocess_ms": {}}
    for m in MODELS:  # what NMS gets: top-nms_pre anchors above the score threshold, per frame
        n = [int((torch.topk(torch.sigmoid(o.cls).reshape(-1), models[m].nms_pre).values > models[m].score_thr).sum())
             for o in outputs[m]]
        result["candidates"][m] = statistics.mean(n)
    ms: dict[str, list[float]] = {f"{pm} on {om}": [] for pm in MODELS for om in MODELS}
    for _ in range(args.trials):
        for key in ms:  # interleaved: every pairing once per trial
            pm, om = key.split(" on ")
            t0 = time.perf_counter()
            with torch.no_grad():
                for o in outputs[om]:
                    models[pm].postprocess(o.cls, o.reg, o.dir)
            ms[key].append((time.perf_counter() - t0) / len(outputs[om]) * 1e3)
    result["postprocess_ms"] = {k: statistics.median(v) for k, v in ms.items()}
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    for m, c in result["candidates"].items():
        print(f"{m}: {c:.1f} candidates above the score threshold in the top {models[m].nms_pre} per frame")
    for k, v in result["postprocess_ms"].items():
        print(f"postprocess of {k}'s outputs: {v:.2f} ms per frame (median of {args.trials} trials)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
