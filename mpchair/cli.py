"""``mpchair`` command line. Each subcommand is a thin module under ``mpchair/commands/`` (parse, call, print)."""

from __future__ import annotations

from mpchair import __version__
from mpchair.core.clitools import lazy_group, run_cli

COMMANDS = {
    "synth": "mpchair.commands.synth:synth",
    "houses": "mpchair.commands.houses:houses",
    "generate": "mpchair.commands.generate:generate",
    "stream": "mpchair.commands.stream:stream",
    "stats": "mpchair.commands.stats:stats",
    "view": "mpchair.commands.view:view",
    "view-house": "mpchair.commands.view:view_house",
}


@lazy_group("mpchair", __version__, COMMANDS)
def cli() -> None:
    """Build the Matterport-Chair 3D detection dataset (KITTI format) from Matterport3D houses.

    \b
    Typical use:
      mpchair synth --out houses/               # synthetic houses in the Matterport3D release format
      mpchair houses --root houses/             # what the reader finds
      mpchair generate --root houses/ --house X --frames 200 --out dataset/
      mpchair stream --root houses/ --house X --episodes 2 --out stream/   # a moving robot's frames
      mpchair stats --density dataset/
    """


def main(args: list[str] | None = None) -> None:
    """Console-script entry point."""
    run_cli(cli, args)


if __name__ == "__main__":
    main()
