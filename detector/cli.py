"""``detector`` command line. Each subcommand is a thin module under ``detector/commands/`` (parse, call, print)."""

from __future__ import annotations

import os

import click

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
    Typical use on a CPU (the *_cpu configs: the paper's pillars on a 288 x 144 grid, sized for 2 cores):
      detector train --config mpchair_sparse_cpu --data dataset/ --out runs/sparse
      detector eval --config mpchair_sparse_cpu --data dataset/ --checkpoint runs/sparse/last.pt
      detector stream-eval --data stream/ --config mpchair_sparse_cpu --checkpoint runs/sparse/last.pt
      detector bench --config mpchair_dense --config mpchair_sparse --data dataset/
      detector export --config mpchair_sparse_exact --format openvino --out exported/
    --config takes a packaged config's name (detector train --help lists them) or a YAML path; --checkpoint
    pretrained:NAME takes packaged weights. The paper's configs (mpchair_dense, mpchair_sparse: 768 x 512, 200 / 250
    epochs) are a GPU's job to train: about 70 days of dense training on 2 CPU cores (train says so after its first
    step). bench times them on a CPU in minutes, with the CPU configs' weights or random ones.
    Distributed: torchrun --nproc-per-node=2 -m detector train ...

    \b
    Environment: DETECTOR_GEMM=auto|mkl, the library of the eager fp32 CPU GEMMs (auto: oneDNN; docs/sparse.md).
    """
    choice = os.environ.get("DETECTOR_GEMM")
    if choice is not None:  # read once, here; the command runs inside the library choice (detector.ops.gemm)
        from detector.ops.gemm import gemm_backend, parse_backend

        click.get_current_context().with_resource(gemm_backend(parse_backend(choice)))


def main(args: list[str] | None = None) -> None:
    """Console-script entry point (also ``python -m detector``)."""
    run_cli(cli, args)


if __name__ == "__main__":
    main()
