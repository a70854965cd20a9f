"""``detector eval``: KITTI-protocol evaluation of result files (any detector's) or of a trained checkpoint."""

from __future__ import annotations

from pathlib import Path

import click

from detector.commands import PRETRAINED_HELP, config_help
from mpchair.core import limits
from mpchair.core.atomic import check_writable
from mpchair.core.errors import InputError


def _parse_min_overlaps(values: tuple[str, ...]) -> dict[str, tuple[float, float, float]]:
    """``CLASS=T`` or ``CLASS=BBOX,BEV,3D`` options → ``{class: (bbox, bev, 3d)}``."""
    out: dict[str, tuple[float, float, float]] = {}
    for v in values:
        name, sep, rest = v.partition("=")
        try:
            nums = tuple(float(x) for x in rest.split(","))
        except ValueError:
            nums = ()
        if not sep or not name or len(nums) not in (1, 3) or not all(0.0 <= x < 1.0 for x in nums):
            raise InputError(f"--min-overlap {v!r}: expected CLASS=T or CLASS=BBOX,BEV,3D with values in [0, 1)")
        out[name] = nums * 3 if len(nums) == 1 else nums
    return out


def _ids_for(labels: Path, split: str | None) -> list[str]:
    from mpchair.kitti import read_imageset

    if split is not None:
        return read_imageset(split)
    if not labels.is_dir():
        raise InputError("label folder not found", labels)
    return sorted(p.stem for p in labels.glob("*.txt"))


@click.command("eval")
@click.option("--labels", type=click.Path(path_type=Path), help="Ground-truth label folder (label_2 layout).")
@click.option("--results", type=click.Path(path_type=Path),
              help="Result folder: one 16-column <id>.txt per frame id (empty if nothing was detected).")
@click.option("--split", help="With --labels: an ImageSets file of frame ids (default: every label file). "
              "With --config: the split name under DATA/ImageSets (default: val).")
@click.option("--classes", help="Comma-separated classes to evaluate, case-insensitive (default: Chair). "
              "Checkpoint mode uses the config's eval classes.")
@click.option("--min-overlap", "min_overlap", multiple=True, metavar="CLASS=T|CLASS=BBOX,BEV,3D",
              help="IoU threshold(s) for a class (repeatable); defaults: Car/Van/Truck 0.7, others 0.5.")
@click.option("--protocol", type=click.Choice(["kitti", "open3d-ml"]), default="kitti", show_default=True,
              help="kitti: the KITTI protocol (Easy / Moderate / Hard / Overall, R40 and R11). open3d-ml: the "
              "reference's own metric, Open3D-ML's mAP (BEV and 3D, every box difficulty 0; needs Open3D-ML).")
@click.option("--json", "as_json", is_flag=True, help="Print the JSON summary instead of the table.")
@click.option("--config", type=click.Path(path_type=Path), metavar="NAME|YAML",
              help=config_help("Experiment config (checkpoint mode)"))
@click.option("--data", type=click.Path(path_type=Path), help="KITTI-format dataset root (checkpoint mode).")
@click.option("--checkpoint", type=click.Path(path_type=Path),
              help=f"Trained checkpoint ({PRETRAINED_HELP}; checkpoint mode).")
@click.option("--out", type=click.Path(path_type=Path),
              help="Checkpoint mode: folder for result files and metrics.json (metrics_open3d_ml.json with "
              "--protocol open3d-ml; default: beside the checkpoint).")
@click.option("--device", default="cpu", show_default=True, help="Checkpoint mode: cpu or cuda.")
@click.option("--threads", type=limits.parallel_range(), help="Checkpoint mode: torch CPU threads.")
@click.option("--runtime", type=click.Choice(["torch", "onnxruntime", "openvino"]), default="torch", show_default=True,
              help="Checkpoint mode: run the network exported, in this runtime (detector export; the deploy extra).")
@click.option("--precision", type=click.Choice(["fp32", "bf16", "int8"]), default="fp32", show_default=True,
              help="Checkpoint mode: bf16 (eager torch autocast or OpenVINO) or int8 (post-training quantization over "
              "--calibration-frames of the train split).")
@click.option("--calibration-frames", type=int, default=8, show_default=True, help="int8 calibration frames.")
def eval_cmd(labels, results, split, classes, min_overlap, protocol, as_json, config, data, checkpoint, out, device,
             threads, runtime, precision, calibration_frames) -> None:
    """Evaluate with the KITTI protocol (AP of bbox / BEV / 3D / AOS, R40 and R11, Easy / Moderate / Hard and
    Overall, where every box of the class counts) or with the reference's Open3D-ML mAP (--protocol open3d-ml).

    \b
    Result files (any detector's):
      detector eval --labels DATA/training/label_2 --results runs/dense/data --split DATA/ImageSets/val.txt \\
                    --classes Car,Chair [--json]
    A trained checkpoint (inference, result files, then the same evaluation; prints where it wrote them, and
    what an all-zero AP means):
      detector eval --config CONFIG.yaml --data DATA --checkpoint runs/dense/last.pt [--split val]
    The same network deployed (exported, run in ONNX Runtime or OpenVINO; docs/deployment.md):
      detector eval ... --runtime openvino --precision int8
    The reference's metric (Open3D-ML's mAP) on the same files: add --protocol open3d-ml.

    BEV and 3D overlaps use an exact float64 rotated IoU (identical boxes score 1; see docs/evaluation.md).
    Buckets with fewer than 41 valid GT cannot reach 100 and are flagged.
    """
    from detector.eval import all_ap_zero, evaluate_folders, format_table, to_json

    folder_mode = labels is not None or results is not None
    checkpoint_mode = config is not None or data is not None or checkpoint is not None
    if folder_mode and checkpoint_mode:
        raise InputError("use either --labels/--results or --config/--data/--checkpoint, not both")
    if checkpoint_mode:
        if classes is not None or min_overlap:
            raise InputError("--classes / --min-overlap apply to --labels/--results; a checkpoint is evaluated with "
                             "its config's eval classes and thresholds")
        result, written = _checkpoint_mode(config, data, checkpoint, split, out, device, threads, protocol,
                                           (runtime, precision, calibration_frames))
    elif folder_mode:
        if (runtime, precision) != ("torch", "fp32"):
            raise InputError("--runtime / --precision apply to a checkpoint (--config/--data/--checkpoint)")
        if labels is None or results is None:
            raise InputError("--labels and --results go together")
        class_list = [c.strip() for c in (classes or "Chair").split(",") if c.strip()]
        if not class_list:
            raise InputError("--classes is empty")
        result = evaluate_folders(labels, results, _ids_for(labels, split), class_list,
                                  _parse_min_overlaps(min_overlap), protocol=protocol)
    else:
        raise InputError("nothing to evaluate: give --labels and --results, or --config, --data and --checkpoint")
    if as_json:
        click.echo(to_json(result))
    else:
        click.echo(format_table(result))
    notes = [f"warning: {w}" for w in result.warnings] if as_json else []  # the table lists them itself
    if checkpoint_mode:
        notes.append(f"wrote {written[0]}/ ({result.num_frames} result files, one per frame of the split) and "
                     f"{written[1]}")
        if all_ap_zero(result):
            notes.append(_zero_ap_note(checkpoint))
    for line in notes:  # beside --json's document on stdout, not in it
        click.echo(line, err=as_json)


def _zero_ap_note(checkpoint: Path) -> str:
    """What an all-zero AP means, with the checkpoint's training length (most often: trained too briefly)."""
    from detector.checkpoint import load_checkpoint

    saved = load_checkpoint(checkpoint)
    step, epoch = saved.step, saved.epoch
    trained = (f"{checkpoint} holds {step} optimiser step(s) ({epoch} completed epoch(s))" if step is not None
               else f"{checkpoint} records no step count")
    return (f"note: every AP is 0. That is expected of an under-trained model: {trained}, and a briefly trained "
            "model scores few or no boxes above the config's score threshold. Train longer (the config's "
            "train.epochs) before reading AP; if it was trained that long, check the data and the config.")


def _checkpoint_mode(config, data, checkpoint, split, out, device, threads, protocol, deployed):
    """Inference + evaluation (:func:`detector.infer.evaluate_checkpoint`, or :func:`_deployed_mode` for another
    runtime or precision); returns the result and the paths written (the result folder and the metrics file)."""
    if config is None or data is None or checkpoint is None:
        raise InputError("checkpoint mode needs --config, --data and --checkpoint")
    try:
        from detector.infer import (
            METRICS_FILES,
            RESULTS_SUBDIR,
            check_results_dir,
            default_results_dir,
            evaluate_checkpoint,
        )
    except ImportError as e:
        if e.name == "detector.infer":  # the module or the function is missing (not one of its own imports)
            raise InputError("checkpoint evaluation is not available in this build (detector.infer."
                             "evaluate_checkpoint is missing); evaluate result files with --labels/--results") from None
        raise
    split = split or "val"
    out = out if out is not None else default_results_dir(checkpoint, split)
    check_writable(out, folder=True)  # before the inference, not after it
    check_results_dir(out)  # and OUT/data is new or this command's own, before a deployed runtime's export too
    if deployed[:2] != ("torch", "fp32"):
        result = _deployed_mode(config, data, checkpoint, split, out, device, threads, protocol, *deployed)
    else:
        result = evaluate_checkpoint(config, data, checkpoint, split=split, out_dir=out, device=device,
                                     threads=threads, protocol=protocol)
    return result, (out / RESULTS_SUBDIR, out / METRICS_FILES[protocol])


def _deployed_mode(config, data, checkpoint, split, out, device, threads, protocol, runtime, precision,
                   calibration_frames):
    """The checkpoint deployed (:func:`detector.deploy.deployed.deploy_checkpoint`: exported, int8 calibrated on the
    train split) and evaluated like the eager one (:func:`detector.infer.evaluate_model`)."""
    from detector.config import load_experiment
    from detector.data.experiment import open_split
    from detector.deploy.deployed import deploy_checkpoint, graph_work_dir
    from detector.device import use_device
    from detector.eval.protocols import check_protocol
    from detector.infer import evaluate_model

    if device != "cpu":
        raise InputError(f"--runtime {runtime} / --precision {precision} run on the CPU; drop --device {device}")
    check_protocol(protocol)
    use_device("cpu", threads)
    cfg = load_experiment(config)
    open_split(cfg, data, split).check()
    if runtime == "torch":  # eager bf16: the model's stages under bfloat16 autocast, as `detector bench` times it
        from detector.checkpoint import load_model
        from detector.deploy.cpu import cpu_flags, skip_reason

        why = skip_reason(runtime, precision, cpu_flags())
        if why is not None:
            raise InputError(f"cannot run {runtime} {precision} here: {why}")
        model = load_model(cfg, checkpoint, "cpu")
        model.precision = precision
        return evaluate_model(model, cfg, data, split, out, device="cpu", protocol=protocol)
    with graph_work_dir("detector-eval-") as work:
        model = deploy_checkpoint(cfg, checkpoint, runtime, precision, work, threads=torch_threads(), data=data,
                                  calibration_frames=calibration_frames)
        return evaluate_model(model, cfg, data, split, out, device="cpu", protocol=protocol)


def torch_threads() -> int:
    """The torch intra-op threads set now (the deployed runtimes use as many)."""
    import torch

    return torch.get_num_threads()
