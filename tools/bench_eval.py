"""Time the KITTI evaluator (``detector.eval.evaluate``) on a synthetic KITTI-val-sized set, in memory.

Builds ``--frames`` frames (default 3769, KITTI val) of about ``--objects`` GT objects each with a KITTI-like mix
(Car / Pedestrian / Cyclist / Van / DontCare; 2D heights from 15 to 200 px; occlusion 0-3; truncation 0-0.6; camera
locations up to 70 m, any ry), and detections that perturb the GT (a fifth missed, centre / size / ry / 2D noise) plus
a few false positives per frame, scored so TPs tend to outrank FPs. Prints the wall time of one ``evaluate`` call
(after a small warm-up call that loads the numba kernels), its CPU time, and the Moderate AP_R40 per class.

With ``--cli`` it also writes the frames as a ``label_2`` folder and a 16-column result folder and times the whole
user-facing command in a fresh process, ``python -m detector eval --labels ... --results ... --json`` (interpreter
start, imports, numba cache load, reading 2 x frames files, the evaluation and the report).

    python tools/bench_eval.py [--frames 3769] [--objects 10] [--seed 0] [--repeat 3] [--cli]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from detector.eval import evaluate
from mpchair.kitti import Labels, write_labels

CLASSES = ("Car", "Pedestrian", "Cyclist", "Van", "DontCare")
CLASS_P = (0.55, 0.15, 0.07, 0.08, 0.15)
DIMS_HWL = {"Car": (1.53, 1.63, 3.88), "Pedestrian": (1.76, 0.66, 0.84), "Cyclist": (1.74, 0.60, 1.76),
            "Van": (2.2, 1.9, 5.1), "DontCare": (-1.0, -1.0, -1.0)}


def synth_frame(rng: np.random.Generator, n: int) -> tuple[Labels, Labels]:
    """One frame: (ground truth, detections) in the KITTI file frame (rectified camera, image_2 pixels)."""
    names = rng.choice(CLASSES, size=n, p=CLASS_P)
    order = np.argsort(names == "DontCare", kind="stable")  # DontCare rows last, as in the files
    names = names[order]
    dims = np.array([DIMS_HWL[c] for c in names]) * rng.uniform(0.9, 1.1, (n, 1))
    z = rng.uniform(5, 70, n)
    loc = np.c_[rng.uniform(-20, 20, n), rng.normal(1.65, 0.1, n), z]
    ry = rng.uniform(-np.pi, np.pi, n)
    height = np.clip(720 * dims[:, 0] / z * rng.uniform(0.9, 1.1, n), 12, 250)  # ~f * h / z pixels
    u = rng.uniform(0, 1200, n)
    bbox = np.c_[u, 180 - height / 2, u + height * rng.uniform(0.5, 2.5, n), 180 + height / 2]
    dc = names == "DontCare"
    dims[dc], loc[dc], ry[dc] = -1.0, -1000.0, -10.0
    gt = Labels(names=names, truncated=np.where(dc, -1, rng.choice([0.0, 0.0, 0.1, 0.2, 0.4, 0.6], n)),
                occluded=np.where(dc, -1, rng.choice([0, 0, 1, 2, 3], n)), alpha=np.where(dc, -10, ry - 0.1),
                bbox=bbox, dims_hwl=dims, location=loc, rotation_y=ry)

    keep = ~dc & (rng.uniform(size=n) > 0.2)
    k = int(keep.sum())
    n_fp = int(rng.integers(0, 5))
    fp_names = rng.choice(CLASSES[:4], size=n_fp)
    fp_z = rng.uniform(5, 70, n_fp)
    fp_h = np.clip(720 * 1.6 / fp_z, 12, 250)
    fp_u = rng.uniform(0, 1200, n_fp)
    det = Labels(
        names=np.concatenate([names[keep], fp_names]),
        truncated=np.full(k + n_fp, -1.0), occluded=np.full(k + n_fp, -1),
        alpha=np.concatenate([gt.alpha[keep] + rng.normal(0, 0.2, k), rng.uniform(-np.pi, np.pi, n_fp)]),
        bbox=np.concatenate([bbox[keep] + rng.normal(0, 3, (k, 4)),
                             np.c_[fp_u, 180 - fp_h / 2, fp_u + fp_h, 180 + fp_h / 2]]),
        dims_hwl=np.concatenate([dims[keep] * rng.normal(1, 0.05, (k, 3)),
                                 np.array([DIMS_HWL[c] for c in fp_names]).reshape(-1, 3)]),
        location=np.concatenate([loc[keep] + rng.normal(0, 0.2, (k, 3)),
                                 np.c_[rng.uniform(-20, 20, n_fp), np.full(n_fp, 1.65), fp_z]]),
        rotation_y=np.concatenate([ry[keep] + rng.normal(0, 0.1, k), rng.uniform(-np.pi, np.pi, n_fp)]),
        score=np.concatenate([rng.beta(5, 2, k), rng.beta(2, 5, n_fp)]),
    )
    return gt, det


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3769)
    ap.add_argument("--objects", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cli", action="store_true", help="also time `python -m detector eval` on files, cold process")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    frames = [synth_frame(rng, int(rng.integers(args.objects // 2, args.objects * 3 // 2 + 1)))
              for _ in range(args.frames)]
    gt = [f[0] for f in frames]
    dt = [f[1] for f in frames]
    classes = ["Car", "Pedestrian", "Cyclist"]
    evaluate(gt[:5], dt[:5], classes)  # loads (or compiles) the numba kernels
    times, cpu = [], []
    for _ in range(args.repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        result = evaluate(gt, dt, classes)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    n_gt = sum(len(g) for g in gt)
    n_dt = sum(len(d) for d in dt)
    print(f"frames {args.frames}, GT rows {n_gt}, detections {n_dt}, classes {','.join(classes)}")
    # CPU time is printed too: on a shared machine the wall time mostly measures the other jobs.
    print(f"evaluate: wall best {min(times):.2f} s, median {float(np.median(times)):.2f} s; "
          f"CPU best {min(cpu):.2f} s over {args.repeat} runs")
    for c in classes:
        r = result.ap[c]
        print(f"  {c:<11} num_gt(mod) {result.num_gt[c][1]:>6}  moderate AP_R40 bbox {r['bbox']['R40'][1]:6.2f} "
              f"bev {r['bev']['R40'][1]:6.2f} 3d {r['3d']['R40'][1]:6.2f} aos {r['aos']['R40'][1]:6.2f}")
    if args.cli:
        time_cli(gt, dt, classes, args.repeat)


def time_cli(gt: list[Labels], dt: list[Labels], classes: list[str], repeat: int) -> None:
    """Write the frames as KITTI folders and time ``python -m detector eval`` on them in fresh processes."""
    with tempfile.TemporaryDirectory() as tmp:
        labels, results = Path(tmp, "label_2"), Path(tmp, "results")
        labels.mkdir()
        results.mkdir()
        for i, (g, d) in enumerate(zip(gt, dt)):
            write_labels(labels / f"{i:06d}.txt", g)
            write_labels(results / f"{i:06d}.txt", d)
        cmd = [sys.executable, "-m", "detector", "eval", "--labels", str(labels), "--results", str(results),
               "--classes", ",".join(classes), "--json"]
        repo = str(Path(__file__).resolve().parents[1])
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [repo, os.environ.get("PYTHONPATH")]))}
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=True)
            times.append(time.perf_counter() - t0)
        res = json.loads(out.stdout)
        print(f"python -m detector eval on {len(gt)} label + {len(dt)} result files, fresh process: wall best "
              f"{min(times):.2f} s, median {float(np.median(times)):.2f} s over {repeat} runs")
        print("  moderate AP_R40 3d from the files: "
              + ", ".join(f"{c} {res[c]['3d']['R40'][1]:.2f}" for c in classes))


if __name__ == "__main__":
    main()
