"""``tools/device_check.py``: the GPU check's subcommands (:mod:`reproduction.device_check`), run by
``tools/device_check.sh``."""

from __future__ import annotations

import argparse
import importlib
import sys

from mpchair.core.clitools import run_script
from mpchair.core.errors import InputError

#: Subcommand → the job that runs it, imported when chosen: ``step`` wraps every step of the check, and loads no torch.
JOBS: dict[str, str] = {"step": "step:cmd_step", "machine": "jobs:cmd_machine", "configs": "jobs:cmd_configs",
                        "tests": "jobs:cmd_tests", "train": "jobs:cmd_train", "ddp": "jobs:cmd_ddp",
                        "report": "report:cmd_report"}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0].replace("``", ""))
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("step")
    s.add_argument("name")
    s.add_argument("--results", required=True)
    s.add_argument("--stdout")
    s.add_argument("--timeout", type=float, default=600.0)
    s = sub.add_parser("machine")
    s.add_argument("--device", required=True)
    s.add_argument("--dry-run", action="store_true")
    s.add_argument("--out", required=True)
    s = sub.add_parser("configs")
    s.add_argument("--out", required=True)
    s.add_argument("--tiny", action="store_true")
    s = sub.add_parser("tests")
    s.add_argument("--junit", required=True)
    s.add_argument("--out", required=True)
    for name in ("train", "ddp"):
        s = sub.add_parser(name)
        for opt in ("--config", "--data", "--run", "--device", "--out"):
            s.add_argument(opt, required=True)
        s.add_argument("--steps", type=int, required=True)
        if name == "train":
            s.add_argument("--name", required=True)
            s.add_argument("--precision", choices=["fp32", "autocast"], required=True)
    s = sub.add_parser("report")
    s.add_argument("--results", required=True)
    s.add_argument("--out", required=True)
    return p


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand; its exit status (2 with one ``error:`` line on bad input: the console scripts' error
    path)."""
    return run_script(lambda: _main(sys.argv[1:] if argv is None else list(argv)))


def _main(argv: list[str]) -> int:
    # ``step``'s command follows ``--`` verbatim (its own options must not be parsed as the step's)
    cut = argv.index("--") if "--" in argv else len(argv)
    args = parser().parse_args(argv[:cut])
    args.cmd = argv[cut + 1 :]
    if args.command == "step" and not args.cmd:
        raise InputError("step needs a command after --")
    module, func = JOBS[args.command].split(":")
    return getattr(importlib.import_module(f"reproduction.device_check.{module}"), func)(args)
