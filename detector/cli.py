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
      detector train --config detector/configs/mpchair_dense.yaml --data dataset/ --out runs/dense
      detector eval --config detector/configs/mpchair_dense.yaml --data dataset/ --checkpoint runs/dense/last.pt
      detector stream-eval --data stream/ --config detector/configs/mpchair_dense.yaml --checkpoint runs/dense/last.pt
      detector bench --config detector/configs/mpchair_dense.yaml \\
        --config detector/configs/mpchair_sparse.yaml --data dataset/
      detector export --config detector/configs/mpchair_sparse_exact.yaml --format openvino --out exported/
    Distributed: torchrun --nproc-per-node=2 -m detector train ...
    """


def main(args: list[str] | None = None) -> None:
    """Console-script entry point (also ``python -m detector``)."""
    run_cli(cli, args)


if __name__ == "__main__":
    main()
