"""``detector ops``: parse arguments, call :func:`detector.opcount.count_dataset`, print the comparison."""

from __future__ import annotations

import json

import click

from detector.commands import config_help


@click.command("ops")
@click.option("--config", "config_path", required=True, type=click.Path(dir_okay=False), metavar="NAME|YAML",
              help=config_help("Experiment config (dense or sparse: the other variant is the same config with another "
                             "backbone)"))
@click.option("--data", "data_dir", required=True, type=click.Path(file_okay=False),
              help="KITTI-format dataset folder (training/ + ImageSets/).")
@click.option("--split", default="test", show_default=True, help="ImageSets split.")
@click.option("--frames", type=int, default=20, show_default=True, help="Frames counted (the first of the split).")
@click.option("--start", type=int, default=0, show_default=True, help="Index of the first frame in the split.")
@click.option("--json", "as_json", is_flag=True, help="Print the full JSON (per frame, per layer) instead of tables.")
@click.option("--out", "json_out", type=click.Path(dir_okay=False), default=None, help="Also write the JSON here.")
@click.option("--markdown", is_flag=True, help="Print the tables as Markdown.")
@click.option("--no-progress", is_flag=True,
              help="No progress bars (shown on stderr by default when it is a terminal and --json is not given).")
def ops(config_path: str, data_dir: str, split: str, frames: int, start: int, as_json: bool, json_out: str | None,
        markdown: bool, no_progress: bool) -> None:
    """Exact multiply-accumulate counts of the dense and sparse backbone + neck per frame, beside Table I's bound.

    \b
    Per conv type (3x3, 2x2, 1x1/2x2/4x4 transposed) and per block: the dense count, the exact sparse count (active
    (input, output, tap) triples x C_in x C_out, from the sparse backbone's own index tables on the frame's real
    pillars), the paper's Table I upper bound at that frame's density D, and what detector.sparse computes with its
    zero taps. Example:
      detector ops --config mpchair_sparse --data dataset/ --frames 50
    """
    from detector.opcount import count_dataset, format_counts
    from mpchair.core.atomic import check_writable, write_text
    from mpchair.core.errors import InputError

    if frames < 1 or start < 0:
        raise InputError(f"need --frames >= 1 and --start >= 0 (got {frames}, {start})")
    if json_out:
        check_writable(json_out)
    result = count_dataset(config_path, data_dir, split, frames, start, progress=not (no_progress or as_json))
    text = json.dumps(result, indent=2)
    if json_out:
        write_text(json_out, text + "\n")
    click.echo(text if as_json else format_counts(result, markdown=markdown))
