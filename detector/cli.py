"""``detector`` command line. Each subcommand is a thin module under ``detector/commands/`` (parse, call, print)."""

from __future__ import annotations

from detector import __version__
from mpchair.core.clitools import lazy_group, run_cli

COMMANDS = {
    "train": "detector.commands.train:train",
    "eval": "detector.commands.eval:eval_cmd",
    "stream-eval": "detector.commands.stream_eval:stream_eval",
    "bench": "detector.commands.bench:bench",
    "export": "detector.commands.export:export",
    "ops": "detector.commands.ops:ops",
    "viz-sparsity": "detector.commands.viz:viz_sparsity",
}


@lazy_group("detector", __version__, COMMANDS)
def cli() -> None:
    """Train, evaluate and time dense PointPillars vs Sparse PointPillars on KITTI-format datasets.

    \b
    Typical use:
      detector train --config mpchair_dense --data dataset/ --out runs/dense
      detector eval --config mpchair_dense --data dataset/ --checkpoint runs/dense/last.pt
      detector stream-eval --data stream/ --config mpchair_dense --checkpoint runs/dense/last.pt
      detector bench --config mpchair_dense --config mpchair_sparse --data dataset/
      detector export --config mpchair_sparse_exact --format openvino --out exported/
    --config takes a packaged config's name (detector train --help lists them) or a YAML path; --checkpoint
    pretrained:NAME takes packaged weights.
    Distributed: torchrun --nproc-per-node=2 -m detector train ...
    """


def main(args: list[str] | None = None) -> None:
    """Console-script entry point (also ``python -m detector``)."""
    run_cli(cli, args)


if __name__ == "__main__":
    main()
