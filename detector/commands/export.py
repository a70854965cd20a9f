"""``detector export``: parse arguments, call :func:`detector.deploy.folder.export_folder`, say what was written."""

from __future__ import annotations

import click

from detector.commands import PRETRAINED_HELP, config_help
from mpchair.core import limits


@click.command("export")
@click.option("--config", required=True, type=click.Path(dir_okay=False), metavar="NAME|YAML",
              help=config_help("Experiment config of the model"))
@click.option("--checkpoint", default=None, type=click.Path(dir_okay=False),
              help=f"Trained weights ({PRETRAINED_HELP}; default: seeded random weights, said so in deploy.json).")
@click.option("--format", "fmt", type=click.Choice(["onnx", "openvino"]), required=True,
              help="onnx: model.onnx; openvino: model.xml + model.bin (OpenVINO IR, converted from the ONNX graph).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Output folder (created; an older export there, with nothing added, is replaced; any other "
                   "non-empty folder is refused).")
@click.option("--precision", type=click.Choice(["fp32", "int8"]), default="fp32", show_default=True,
              help="int8: post-training quantization over calibration frames (NNCF for openvino, ONNX Runtime's "
                   "quantizer for onnx); needs --data.")
@click.option("--data", "data_dir", default=None, type=click.Path(file_okay=False),
              help="KITTI-format dataset whose frames calibrate int8.")
@click.option("--calibration-split", default="train", show_default=True, help="Split of the calibration frames.")
@click.option("--calibration-frames", type=int, default=8, show_default=True, help="Calibration frames (int8).")
@click.option("--seed", type=limits.SEED, default=0, show_default=True, help="Seed of the random weights.")
def export(config: str, checkpoint: str | None, fmt: str, out_dir: str, precision: str, data_dir: str | None,
           calibration_split: str, calibration_frames: int, seed: int) -> None:
    """Export the network (backbone + neck + head, BatchNorm folded) to ONNX or OpenVINO IR.

    \b
    Dense model: from the pseudo-image canvas (1, 64, ny, nx) to the head output (1, O, H, W).
    Sparse model: from the pillar features and the rulebook tables (built outside the graph by
    detector.sparse.indices, as voxelization is) to the exact sparse head's rows (N_1, O), or the dense head's
    map; the graph holds only Gather + MatMul (+ bias, ReLU) with a dynamic number of sites.
    Voxelization, the pillar net, the scatter and box decoding + NMS stay outside (docs/deployment.md).
    Needs the deploy extra: pip install '.[deploy]'.
    Example:
      detector export --config mpchair_sparse_exact --checkpoint runs/sparse/last.pt \\
        --format openvino --out exported/sparse
    """
    from detector.deploy.folder import MANIFEST, export_folder

    record = export_folder(config, checkpoint, fmt, out_dir, precision=precision, data=data_dir,
                           calibration_split=calibration_split, calibration_frames=calibration_frames, seed=seed)
    names = ", ".join(i["name"] for i in record.inputs)
    click.echo(f"wrote {out_dir}/: {', '.join(record.files)} and {MANIFEST} ({record.format} {record.precision}, "
               f"{record.backbone} backbone, {record.head} head; inputs {names}; output {record.output['name']})")
