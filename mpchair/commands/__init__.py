"""Thin CLI modules for ``mpchair``: one file per subcommand (parse arguments, call the library, print)."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

import click

from mpchair.core.config import package_folder, packaged_names


def sensor_help() -> str:
    """``--sensor`` help with the packaged profiles' names (the folder of :data:`mpchair.scan.sensors.SENSOR_DIR`,
    listed without importing the scan stack, which takes a second)."""
    names = ", ".join(packaged_names(package_folder("mpchair", "scan/profiles")))
    return f"Sensor profile: a YAML file's path, or a packaged profile's name ({names}); a path wins."


def echo_summary(summary: Any, as_json: bool) -> None:
    """Print a job's summary (a frozen dataclass with a ``line()``): one JSON object with ``--json``, else its line."""
    click.echo(json.dumps(dataclasses.asdict(summary), sort_keys=True) if as_json else summary.line())
