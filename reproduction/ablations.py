"""The paper's ablations (section V-B, Tables III / IV) in the reproduction: their runtime beside dense and sparse at
the KITTI and the Matterport geometry (step ``ablation-bench``, part of ``make reproduce``), and, opt in, their
training and AP on Matterport-Chair (step ``ablations``, ``make reproduce-ablations``: four more trainings do not fit
the session of the main run).

The paper trained its ablations on KITTI Car; there is no KITTI training set here, so they are trained on this run's
Matterport-Chair data with the sparse model's CPU schedule (``detector/configs/mpchair_<ablation>_cpu.yaml``:
``mpchair_sparse_cpu.yaml`` with another ``backbone``), and their AP is compared with this run's dense model as the
paper's Table III compares its own (delta to dense). Their KITTI-geometry runtime uses random weights on the vendored
KITTI frames (``tests/data/kitti``); at the Matterport geometry the trained weights of all six models once every
ablation is trained, random weights for all six before (never a mix: BBox Extract's time depends on the boxes a model
scores above its threshold).
"""

from __future__ import annotations

from pathlib import Path

from mpchair.core.atomic import write_text
from reproduction.checkout import ROOT
from reproduction.results import ABLATIONS, bench_weights
from reproduction.runner import BIN, REUSE_ENV, Runner
from reproduction.scales import model_epochs
from reproduction.steps import CONFIGS, Plan, eval_model, extra_step_outputs, train_command

#: The vendored KITTI frames (six frames of the KITTI object training set, cropped to the camera's view as the KITTI
#: configs' ``fov_crop`` crops them; tests/data/kitti/README.md) and the split that lists them all.
KITTI_DATA, KITTI_SPLIT = ROOT / "tests" / "data" / "kitti", "val"
#: The models of the ablation benches, in table order.
BENCH_MODELS = ("dense", "sparse", *ABLATIONS)


def ablation_epochs(plan: Plan) -> int | None:
    """Epochs of every ablation: ``--ablation-epochs``, else the sparse model's of the scale (None: the config's)."""
    return plan.ablation_epochs or model_epochs(plan.scale.epochs)["sparse"]


def _checkpoint(plan: Plan, model: str) -> Path:
    return plan.runs / model / "last.pt"


def weights_are_random(bench_json: Path) -> bool:
    """Whether a bench JSON's models were timed with random weights (True for a file that is not there)."""
    weights = bench_weights(bench_json)
    return not weights or any(w.startswith("random") for w in weights)


def ablation_bench_command(plan: Plan, geometry: str, json_out: Path) -> list[str]:
    """``detector bench`` of dense, sparse and every ablation at one geometry (``kitti``: the vendored KITTI frames,
    random weights; ``mpchair``: the test split at 768 x 512, the trained weights when all six models have them)."""
    if geometry == "kitti":
        configs = [CONFIGS / f"kitti_car_{m}.yaml" for m in BENCH_MODELS]
        data, split, frames = KITTI_DATA, KITTI_SPLIT, "6"
    else:
        configs = [CONFIGS / f"mpchair_{m}.yaml" for m in BENCH_MODELS]
        data, split, frames = plan.data, "test", str(plan.scale.bench_frames)
    cmd = [str(BIN / "detector"), "bench"]
    for c in configs:
        cmd += ["--config", str(c)]
    cmd += ["--data", str(data), "--split", split, "--frames", frames, "--trials", str(plan.scale.bench_trials),
            "--threads", str(plan.threads), "--json-out", str(json_out), "--markdown", "--no-progress"]
    ckpts = [_checkpoint(plan, m) for m in BENCH_MODELS]
    if geometry == "mpchair" and all(c.exists() for c in ckpts):
        for c in ckpts:
            cmd += ["--checkpoint", str(c)]
    return cmd


def run_ablation_bench(plan: Plan, r: Runner) -> None:
    """``detector bench`` of the ablations beside dense and sparse at both geometries (allocator reuse)."""
    outputs = extra_step_outputs(plan.out)["ablation-bench"]
    for geometry, json_out in outputs.items():
        if plan.todo("ablation-bench", json_out):
            r.run(ablation_bench_command(plan, geometry, json_out), env=REUSE_ENV,
                  stdout=json_out.with_suffix(".md"))


def run_ablations(plan: Plan, r: Runner) -> None:
    """Opt in: train each ablation of ``plan.ablations`` on this run's data, evaluate it as the eval step evaluates
    dense and sparse, and, once every ablation is trained, time all six models at 768 x 512 with their weights."""
    outputs = extra_step_outputs(plan.out, plan.ablations)["ablations"]
    for a in plan.ablations:
        config = CONFIGS / f"mpchair_{a}_cpu.yaml"
        done = outputs[f"{a} train"]
        if plan.todo("ablations", done):
            r.run(train_command(plan, a, config=config, epochs=ablation_epochs(plan)), env=REUSE_ENV)
            if not plan.dry_run:
                write_text(done, "trained\n")
        eval_model(plan, r, "ablations", a, config, outputs[f"{a} kitti"], outputs[f"{a} open3d-ml"])
    bench = extra_step_outputs(plan.out)["ablation-bench"]["mpchair"]
    trained = all(_checkpoint(plan, m).exists() for m in BENCH_MODELS)
    if "ablations" in plan.steps and trained and (plan.force or weights_are_random(bench)):
        print("[ablations] every ablation is trained: the 768 x 512 ablation bench again, with the trained weights")
        r.run(ablation_bench_command(plan, "mpchair", bench), env=REUSE_ENV, stdout=bench.with_suffix(".md"))
