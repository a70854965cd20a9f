"""The reproduction's steps before the report: each one's ``mpchair`` / ``detector`` command lines, run through a
:class:`~reproduction.runner.Runner`, and the files that mark it done (:func:`step_outputs`).

A step whose outputs exist is skipped unless ``force``; paths are those of the work folder (``houses/``,
``dataset/``, ``runs/<model>/``, ``results/``).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from detector.config import CONFIG_DIR
from mpchair.core.atomic import write_text
from reproduction import deploy
from reproduction.checkout import ROOT
from reproduction.committed import install_text
from reproduction.results import ABLATIONS, MODELS, OPEN3D_ML_JSON, read_density, read_run_config
from reproduction.runner import BIN, REUSE_ENV, Runner
from reproduction.scales import Scale, bench_run_args, model_epochs

STEPS = ("synth", "generate", "stats", "train", "eval", "bench", "refhead", "ops", "viz", "curve", "deploy",
         "ablation-bench", "report", "record")
#: Steps that run only when asked for (``--steps``): the ablations' trainings (``make reproduce-ablations``).
OPT_IN_STEPS = ("ablations",)
#: The experiment configs the commands name: the packaged ones (read when a command line is built, so a test may
#: point it elsewhere).
CONFIGS = CONFIG_DIR


def house_ids(houses_dir: Path) -> list[str]:
    """Ids of the synthetic houses under ``houses_dir`` (``v1/scans/<id>``)."""
    scans = houses_dir / "v1" / "scans"
    return sorted(p.name for p in scans.iterdir() if p.is_dir()) if scans.is_dir() else []


def step_outputs(out: Path) -> dict[str, dict[str, Path]]:
    """The files that mark each step done in work folder ``out`` (the runner skips a step that has them, ``--status``
    lists them), by step, then by what each file is for (a model, an allocator, a protocol)."""
    res, runs = out / "results", out / "runs"
    return {
        "synth": {"houses": out / "houses" / "v1" / "scans"},
        "generate": {"dataset": out / "dataset" / "manifest.json"},
        "stats": {"density": res / "density.json"},
        "train": {m: runs / m / "done" for m in MODELS},
        "eval": {f"{m} {protocol}": res / f"eval_{m}" / name for m in MODELS
                 for protocol, name in (("kitti", "metrics.json"), ("open3d-ml", OPEN3D_ML_JSON))},
        "bench": {alloc: res / f"bench_{alloc}.json" for alloc in ("default", "reuse")},
        "ops": {"ops": res / "ops.json"},
        "viz": {"panel": res / "viz" / "panel.png"},
        "deploy": deploy.deploy_outputs(res),
        **extra_step_outputs(out),
    }


def extra_step_outputs(out: Path, ablations: tuple[str, ...] = ABLATIONS) -> dict[str, dict[str, Path]]:
    """The outputs of the steps issue 30 added: the reference-head bench, the density curve, the ablations' benches
    (``ablation-bench``) and their trainings and evals (``ablations``, of ``ablations``)."""
    res, runs = out / "results", out / "runs"
    trained = {f"{a} train": runs / a / "done" for a in ablations}
    evals = {f"{a} {protocol}": res / f"eval_{a}" / name for a in ablations
             for protocol, name in (("kitti", "metrics.json"), ("open3d-ml", OPEN3D_ML_JSON))}
    return {"refhead": {"bench": res / "bench_reference_head.json"},
            "curve": {"curve": res / "density_curve.json", "plot": res / "density_curve.png"},
            "ablation-bench": {g: res / f"bench_ablations_{g}.json" for g in ("kitti", "mpchair")},
            "ablations": {**trained, **evals}}


@dataclass(frozen=True)
class Plan:
    """One invocation's choices: the work folder, the scale (with the command line's overrides applied), the steps
    asked for, torch threads, generate workers, seed, and whether to redo done steps or only print the commands."""

    out: Path
    scale: Scale
    steps: tuple[str, ...]
    threads: int = 2
    workers: int = 2
    seed: int = 0
    force: bool = False
    dry_run: bool = False
    #: the opt-in ablations step: which ablations to train, and their epochs (None: the sparse model's)
    ablations: tuple[str, ...] = ABLATIONS
    ablation_epochs: int | None = None
    #: ``--weights``: ``train`` the models here, or take the accuracy study's ``committed`` ones
    #: (reproduction.committed)
    weights: str = "train"
    #: the folder of the committed weights and their index.json (None: the package's detector/pretrained)
    pretrained: Path | None = None
    #: a dry run of ``--from-record``: the work folder's paths the real run restores from the record before any step
    #: (a dry run copies nothing), which count as there, so that it lists the steps the real run would run
    restored: frozenset[Path] = frozenset()

    @property
    def houses(self) -> Path:
        return self.out / "houses"

    @property
    def data(self) -> Path:
        return self.out / "dataset"

    @property
    def runs(self) -> Path:
        return self.out / "runs"

    @property
    def res(self) -> Path:
        return self.out / "results"

    def has(self, path: Path) -> bool:
        """Whether ``path`` is there for the steps: in the work folder, or among (or a folder of) :attr:`restored`."""
        return path.exists() or path in self.restored or any(path in r.parents for r in self.restored)

    def todo(self, step: str, *outputs: Path) -> bool:
        """Whether ``step`` runs now (asked for, and not all of its ``outputs`` there unless forced); says which."""
        if step not in self.steps:
            return False
        if not self.force and outputs and all(self.has(o) for o in outputs):
            print(f"[{step}] outputs exist, skipped ({', '.join(str(o) for o in outputs)})")
            return False
        print(f"[{step}]", flush=True)
        return True


def _tool(name: str) -> str:
    return str(BIN / name)


def _config(name: str) -> str:
    """Path of ``detector/configs/<name>.yaml`` (``mpchair_dense_cpu``, ...)."""
    return str(CONFIGS / f"{name}.yaml")


def _threads(plan: Plan) -> list[str]:
    return ["--threads", str(plan.threads)]


def _checkpoints(plan: Plan) -> list[str]:
    """The trained weights of the dense and the sparse model (which need not exist yet)."""
    return [str(plan.runs / m / "last.pt") for m in MODELS]


def run_synth(plan: Plan, r: Runner) -> None:
    """``mpchair synth``: the scale's synthetic houses (Matterport3D release format)."""
    if plan.todo("synth", step_outputs(plan.out)["synth"]["houses"]):
        r.run([_tool("mpchair"), "synth", "--out", str(plan.houses), "--houses", str(plan.scale.houses), "--seed",
               str(plan.seed)])


def run_generate(plan: Plan, r: Runner) -> None:
    """``mpchair generate``: the dataset of every house (mp3d-depth90 sensor, the scale's seeded split: whole houses
    per split, or per frame)."""
    if plan.todo("generate", step_outputs(plan.out)["generate"]["dataset"]):
        ids = house_ids(plan.houses) or [f"<house ids from {plan.houses}>"]
        cmd = [_tool("mpchair"), "generate", "--root", str(plan.houses), "--frames", str(plan.scale.frames_per_house),
               "--out", str(plan.data), "--sensor", "mp3d-depth90", "--seed", str(plan.seed), "--workers",
               str(plan.workers), "--quiet"]
        if plan.scale.split_mode != "frame":  # the default, left out so that older records' commands stay as logged
            cmd += ["--split-mode", plan.scale.split_mode]
        for h in ids:
            cmd += ["--house", h]
        r.run(cmd)


def run_stats(plan: Plan, r: Runner) -> None:
    """``mpchair stats --density``: D per test frame at the paper's 768 x 512 geometry, its plot and its JSON."""
    density = step_outputs(plan.out)["stats"]["density"]
    if plan.todo("stats", density):
        cmd = [_tool("mpchair"), "stats", "--density", str(plan.data), "--config", _config("mpchair_dense"), "--split",
               "test"]
        r.run([*cmd, "--plot", str(plan.res / "density.png")])
        r.run([*cmd, "--json"], stdout=density)


def train_command(plan: Plan, model: str, config: Path | None = None, epochs: int | None = None) -> list[str]:
    """``detector train`` of one model's CPU config (``config``, default ``mpchair_<model>_cpu.yaml``) into
    ``runs/<model>``: the scale's epochs (or ``epochs``) and precision, ``--resume`` for a cut run (in the precision
    it started with: a session on another CPU may resolve ``auto`` to the other one, and detector train refuses a
    changed config)."""
    # no bars (they would fill a log), but detector train still prints its estimate and one line per epoch, which
    # pass through (the Runner leaves the child's stdout alone)
    config_path = str(config) if config is not None else _config(f"mpchair_{model}_cpu")
    cmd = [_tool("detector"), "train", "--config", config_path, "--data", str(plan.data),
           "--out", str(plan.runs / model), *_threads(plan), "--no-progress"]
    if epochs is None and plan.scale.epochs is not None:
        epochs = model_epochs(plan.scale.epochs)[model]
    if epochs is not None:
        cmd += ["--epochs", str(epochs)]
    precision = plan.scale.precision
    if (plan.runs / model / "last.pt").exists() and not plan.force:
        cmd.append("--resume")
        cfg = read_run_config(plan.runs / model)
        started = cfg.train.precision if cfg else None
        if started and precision and started != precision:
            print(f"[train] {model}: resuming in {started}, the precision this run started with (not {precision})")
            precision = started
    if precision is not None:
        cmd += ["--precision", precision]
    return cmd


def committed_command(plan: Plan, model: str) -> list[str]:
    """``python -m reproduction.committed``: ``--weights committed``'s train step for one model, which trains nothing
    but puts the accuracy study's committed weights into ``runs/<model>`` (last.pt, config.yaml, done)."""
    cmd = [sys.executable, "-m", "reproduction.committed", "--model", model, "--out", str(plan.runs / model)]
    return cmd + (["--pretrained", str(plan.pretrained)] if plan.pretrained is not None else [])


def run_train(plan: Plan, r: Runner) -> None:
    """``detector train``: the dense, then the sparse model; ``RUN/done`` marks a training that returned. With
    committed weights, :func:`committed_command` instead (a record restored without its weights gets them again)."""
    for m in MODELS:
        done = step_outputs(plan.out)["train"][m]
        if plan.weights == "committed":
            if plan.todo("train", done, plan.runs / m / "last.pt"):
                if plan.dry_run:  # the command line alone hides that it trains nothing and what it copies
                    print(install_text(m, plan.runs / m, plan.pretrained), flush=True)
                r.run(committed_command(plan, m))
            continue
        # ``done`` is written only after training returned; a cut run (last.pt, no done) resumes exactly
        if plan.todo("train", done):
            # glibc otherwise returns every large freed tensor to the OS and page-faults it back in on the next step
            # (measured 0.45 -> 0.33 s per CPU step of mpchair_dense_cpu.yaml); results are unaffected.
            r.run(train_command(plan, m), env=REUSE_ENV)
            if not plan.dry_run:
                write_text(done, "trained\n")


def run_eval(plan: Plan, r: Runner) -> None:
    """``detector eval`` of each model on the val split: the KITTI protocol, then the reference's own metric
    (Open3D-ML's mAP, as its reference computed it) on the same result files."""
    outputs = step_outputs(plan.out)["eval"]
    for m in MODELS:
        eval_model(plan, r, "eval", m, Path(_config(f"mpchair_{m}_cpu")), outputs[f"{m} kitti"],
                   outputs[f"{m} open3d-ml"])


def eval_model(plan: Plan, r: Runner, step: str, model: str, config: Path, kitti_out: Path, o3d_out: Path) -> None:
    """``detector eval`` of ``runs/<model>/last.pt`` (experiment ``config``) on the val split into
    ``results/eval_<model>/`` (``kitti_out``: its metrics.json), then the reference's metric on the same result
    files (``o3d_out``), each unless step ``step`` finds its output."""
    ev = plan.res / f"eval_{model}"
    kitti_ran = plan.todo(step, kitti_out)
    if kitti_ran:
        r.run([_tool("detector"), "eval", "--config", str(config), "--data", str(plan.data),
               "--checkpoint", str(plan.runs / model / "last.pt"), "--split", "val", "--out", str(ev),
               *_threads(plan)])
    if kitti_ran or plan.todo(step, o3d_out):
        r.run([_tool("detector"), "eval", "--labels", str(plan.data / "training" / "label_2"), "--results",
               str(ev / "data"), "--split", str(plan.data / "ImageSets" / "val.txt"), "--classes", "Chair",
               "--protocol", "open3d-ml", "--json"], stdout=o3d_out)


def peer_available(dry_run: bool) -> bool:
    """Whether ``detector bench --peer open3d-ml`` can run here (Open3D-ML importable); says so when it cannot.

    A dry run only looks for the ``open3d`` package (importing Open3D-ML takes seconds)."""
    import importlib.util

    if dry_run:
        return importlib.util.find_spec("open3d") is not None
    from detector.bench.peer import open3d_ml_pointpillars
    from mpchair.core.errors import InputError

    try:
        open3d_ml_pointpillars()
    except InputError as e:
        print(f"[bench] no Open3D-ML peer row: {e}", flush=True)
        return False
    return True


def bench_command(plan: Plan, json_out: Path, peer: bool) -> list[str]:
    """``detector bench`` at the paper's 768 x 512 of dense, sparse and sparse with the exact sparse head (the
    trained weights once both exist), with Open3D-ML's own PointPillars as the peer row if ``peer``."""
    # mpchair_sparse_exact.yaml = the sparse model with the exact sparse head (same weights, same output)
    cmd = [_tool("detector"), "bench", "--config", _config("mpchair_dense"), "--config", _config("mpchair_sparse"),
           "--config", _config("mpchair_sparse_exact"), "--data", str(plan.data), "--split", "test", "--frames",
           str(plan.scale.bench_frames), "--trials", str(plan.scale.bench_trials), *bench_run_args(plan.scale),
           *_threads(plan), "--json-out", str(json_out), "--markdown"]
    # the peer row: Open3D-ML's own PointPillars with the dense model's architecture, grid and weights
    if peer:
        cmd += ["--peer", "open3d-ml"]
    ckpts = _checkpoints(plan)
    if all(Path(c).exists() for c in ckpts):
        for c in (*ckpts, ckpts[1]):
            cmd += ["--checkpoint", c]
    return cmd


def run_bench(plan: Plan, r: Runner) -> None:
    """``detector bench`` under the default allocator and the reuse setting (its table to ``bench_<alloc>.md``)."""
    outputs = step_outputs(plan.out)["bench"]
    peer = None
    for alloc, env in (("default", {}), ("reuse", REUSE_ENV)):
        if plan.todo("bench", outputs[alloc]):
            peer = peer_available(plan.dry_run) if peer is None else peer
            r.run(bench_command(plan, outputs[alloc], peer), env=env or None, stdout=plan.res / f"bench_{alloc}.md")


def run_ops(plan: Plan, r: Runner) -> None:
    """``detector ops``: exact MACs of the sparse config against Table I's bound at 768 x 512."""
    ops = step_outputs(plan.out)["ops"]["ops"]
    if plan.todo("ops", ops):
        r.run([_tool("detector"), "ops", "--config", _config("mpchair_sparse"), "--data", str(plan.data), "--split",
               "test", "--frames", str(plan.scale.ops_frames), "--out", str(ops), "--markdown"],
              stdout=plan.res / "ops.md")


def run_viz(plan: Plan, r: Runner) -> None:
    """``detector viz-sparsity``: the paper's Figs. 3-4 at 768 x 512 (trained weights once both exist)."""
    if plan.todo("viz", step_outputs(plan.out)["viz"]["panel"]):
        # the test split's first frame (its ids are a seeded sample, so frame 000000 need not be in it)
        cmd = [_tool("detector"), "viz-sparsity", "--config", _config("mpchair_sparse"), "--data", str(plan.data),
               "--index", "0", "--split", "test", "--out", str(plan.res / "viz"), "--json"]
        ckpts = _checkpoints(plan)
        if all(Path(c).exists() for c in ckpts):
            cmd += ["--dense-checkpoint", ckpts[0], "--sparse-checkpoint", ckpts[1]]
        r.run(cmd, stdout=plan.res / "viz.json")


def reference_head_command(plan: Plan, json_out: Path) -> list[str]:
    """``tools/bench_reference_head.py`` at 768 x 512: dense and sparse with our fused head and the reference's three
    NCHW 1x1 convs, interleaved per frame (the trained weights once both exist)."""
    cmd = [sys.executable, str(ROOT / "tools" / "bench_reference_head.py"), "--config", _config("mpchair_dense"),
           "--config", _config("mpchair_sparse"), "--data", str(plan.data), "--split", "test", "--frames",
           str(plan.scale.bench_frames), "--trials", str(plan.scale.bench_trials), *_threads(plan), "--json-out",
           str(json_out)]
    ckpts = _checkpoints(plan)
    if all(Path(c).exists() for c in ckpts):
        for c in ckpts:
            cmd += ["--checkpoint", c]
    return cmd


def run_refhead(plan: Plan, r: Runner) -> None:
    """The total-time ratio with the reference's head layout (allocator reuse), its table to
    ``bench_reference_head.md``."""
    json_out = step_outputs(plan.out)["refhead"]["bench"]
    if plan.todo("refhead", json_out):
        r.run(reference_head_command(plan, json_out), env=REUSE_ENV, stdout=json_out.with_suffix(".md"))


def curve_command(plan: Plan, json_out: Path, png: Path) -> list[str]:
    """``tools/bench_density.py``: the dense / sparse backbone ratio against D (clustered synthetic sites, random
    weights) at 768 x 512, the test split's first real frames at their own D, the dataset's median D marked."""
    sc = plan.scale
    cmd = [sys.executable, str(ROOT / "tools" / "bench_density.py"), "--dense-config", _config("mpchair_dense"),
           "--sparse-config", _config("mpchair_sparse"), "--frames", str(sc.curve_frames), "--trials",
           str(sc.curve_trials), *_threads(plan), "--data", str(plan.data), "--split", "test", "--real-frames",
           str(sc.curve_real_frames), "--json-out", str(json_out), "--plot", str(png)]
    if sc.curve_densities:
        cmd += ["--densities", ",".join(f"{d:g}" for d in sc.curve_densities)]
    density = read_density(step_outputs(plan.out)["stats"]["density"])
    median = density.values.get("median") if density else None
    if median:
        cmd += ["--mark", f"this dataset (median)={median:.5f}"]
    return cmd


def run_curve(plan: Plan, r: Runner) -> None:
    """The density curve: its JSON, its PNG and its table (``density_curve.md``)."""
    files = step_outputs(plan.out)["curve"]
    if plan.todo("curve", *files.values()):
        r.run(curve_command(plan, files["curve"], files["plot"]), env=REUSE_ENV,
              stdout=files["curve"].with_suffix(".md"))


def run_deploy(plan: Plan, r: Runner) -> None:
    """The trained models deployed in ONNX Runtime / OpenVINO: AP, runtime and CPU budget
    (:func:`reproduction.deploy.run_deploy`)."""
    deploy.run_deploy(plan, r, _config)


#: The steps before the report, in the order they run (the ablation steps: reproduction.ablations).
COMMAND_STEPS = (run_synth, run_generate, run_stats, run_train, run_eval, run_bench, run_refhead, run_ops, run_viz,
                 run_curve, run_deploy)
