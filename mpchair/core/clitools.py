"""Shared command-line plumbing for the ``mpchair`` and ``detector`` console scripts.

* :class:`LazyGroup` registers subcommands by ``"module:attribute"`` so a command imports only what it needs
  (``mpchair houses`` never imports torch). ``--help`` lists every registered command.
* :func:`run_cli` turns :class:`mpchair.core.errors.InputError`, ``OSError`` (``error: PATH: reason``) and click's usage
  errors into one ``error: ...`` line and exit status 2, :class:`mpchair.core.errors.RunError` into one line and exit 1.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable

import click

from mpchair.core.errors import InputError, RunError


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use from ``{name: "package.module:attr"}``."""

    def __init__(self, *args, lazy_commands: dict[str, str] | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.lazy_commands = dict(lazy_commands or {})

    def _available(self) -> dict[str, str]:
        # A registered command whose module is absent (e.g. a partial install) is left out rather than crashing --help.
        return {
            name: target
            for name, target in self.lazy_commands.items()
            if importlib.util.find_spec(target.split(":")[0]) is not None
        }

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(self._available()))

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        target = self._available().get(cmd_name)
        if target is not None:
            module_name, attr = target.split(":")
            return getattr(importlib.import_module(module_name), attr)
        return super().get_command(ctx, cmd_name)


def lazy_group(prog: str, version: str, commands: dict[str, str]) -> Callable[[Callable[[], None]], click.Group]:
    """Decorator: the top-level click group of a CLI (``mpchair``, ``detector``) whose subcommands load lazily from
    ``commands`` (``{name: "package.module:attr"}``), with ``-h/--help`` and ``--version``."""

    def make(func: Callable[[], None]) -> click.Group:
        settings = {"help_option_names": ["-h", "--help"], "max_content_width": 110}
        group = click.group(cls=LazyGroup, lazy_commands=commands, context_settings=settings)
        return group(click.version_option(version, prog_name=prog)(func))

    return make


class FrameIdType(click.ParamType):
    """A KITTI frame id typed as up to 6 digits (``3`` or ``000003``), converted to its file name form ``000003``.

    ``--frame`` means the frame id in every command (``mpchair view``, ``detector viz-sparsity``), never a position in
    a split."""

    name = "ID"

    def convert(self, value: object, param: click.Parameter | None, ctx: click.Context | None) -> str:
        text = str(value).strip()
        if not text.isdigit() or len(text) > 6:
            self.fail(f"{value!r} is not a frame id (up to 6 digits)", param, ctx)
        return f"{int(text):06d}"


#: The ``type=`` of every ``--frame ID`` option.
FRAME_ID = FrameIdType()


def os_error_line(e: OSError) -> str:
    """``PATH: reason`` of an OS error (``reason`` alone when the error names no file)."""
    reason = e.strerror or str(e)
    return reason if e.filename is None else f"{e.filename}: {reason}"


def run_cli(group: click.Group, args: list[str] | None = None) -> None:
    """Run ``group`` as a console script; every failure a user can act on is one ``error: ...`` line on stderr.

    :class:`InputError`, an ``OSError`` (``error: PATH: reason``: a full disk, a missing permission, ``--out`` under
    a file) and click's usage errors (with the command's ``--help`` hint on the same line) exit with status 2,
    :class:`RunError` with 1; Ctrl-C exits 130 without a traceback.
    """
    try:
        rv = group.main(args=args, standalone_mode=False)
    except InputError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    except RunError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(1)
    except (click.exceptions.Abort, KeyboardInterrupt):
        click.echo("interrupted", err=True)
        sys.exit(130)
    except click.UsageError as e:
        hint = f" (see '{e.ctx.command_path} --help')" if e.ctx is not None else ""
        click.echo(f"error: {' '.join(e.format_message().split())}{hint}", err=True)
        sys.exit(e.exit_code)
    except click.ClickException as e:
        click.echo(f"error: {e.format_message()}", err=True)
        sys.exit(e.exit_code)
    except OSError as e:
        click.echo(f"error: {os_error_line(e)}", err=True)
        sys.exit(2)
    except click.exceptions.Exit as e:
        sys.exit(e.exit_code)
    sys.exit(rv if isinstance(rv, int) else 0)
