"""``detector viz-sparsity``: parse arguments, call :func:`detector.viz.viz_sparsity`, print what was written."""

from __future__ import annotations

import json

import click

from detector.commands import config_help
from mpchair.core import limits
from mpchair.core.clitools import FRAME_ID


@click.command("viz-sparsity")
@click.option("--config", "config_path", required=True, type=click.Path(dir_okay=False), metavar="NAME|YAML",
              help=config_help("Experiment config: its geometry is used for both the dense and the sparse backbone"))
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False),
              help="KITTI-format dataset folder (training/ + ImageSets/).")
@click.option("--frame", "frame_id", type=FRAME_ID, default=None,
              help="Frame id (123 or 000123, as mpchair view); it must be in --split.")
@click.option("--index", type=click.IntRange(min=0), default=None,
              help="Instead of --frame: the frame's position in --split (0 = its first frame). With neither: the "
                   "frame of median density D among the split's first 50 (a typical frame, not a near-empty one).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Folder for the PNGs.")
@click.option("--split", default="test", show_default=True, help="ImageSets split.")
@click.option("--dense-checkpoint", default=None, help="Trained dense weights (default: random, seeded).")
@click.option("--sparse-checkpoint", default=None, help="Trained sparse weights (default: random, seeded).")
@click.option("--seed", type=limits.SEED, default=0, show_default=True, help="Seed of the random weights.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def viz_sparsity(config_path: str, data_dir: str, frame_id: str | None, index: int | None, out_dir: str, split: str,
                 dense_checkpoint: str | None, sparse_checkpoint: str | None, seed: int, as_json: bool) -> None:
    """The paper's Figs. 3-4: non-zero cells of the pseudo-image before and after Conv blocks 1-3.

    \b
    Writes OUT/{dense,sparse}_{input,block1,block2,block3}.png (ny x nx, white = any non-zero channel, +x right,
    +y up; the dense backbone runs without BatchNorm, as in the paper) and OUT/panel.png (both rows together).
    Example:
      detector viz-sparsity --config mpchair_sparse --data dataset/ --out figs/
      detector viz-sparsity --config mpchair_sparse --data dataset/ --frame 12 --out figs/
    """
    from detector.viz import STAGES
    from detector.viz import viz_sparsity as run
    from mpchair.core.atomic import check_writable

    check_writable(out_dir, folder=True)
    result = run(config_path, data_dir, out_dir, frame_id=frame_id, index=index, split=split,
                 dense_checkpoint=dense_checkpoint, sparse_checkpoint=sparse_checkpoint, seed=seed)
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    click.echo(f"frame {result['frame_id']}: non-zero fraction of the pseudo-image per stage")
    for name, fr in result["nonzero_fraction"].items():
        click.echo(f"  {name:<6} " + "  ".join(f"{s} {100 * f:.3f}%" for s, f in zip(STAGES, fr)))
    for f in result["files"]:
        click.echo(f)
