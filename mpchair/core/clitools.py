"""Shared command-line plumbing for the ``mpchair`` and ``detector`` console scripts.

* :class:`LazyGroup` registers subcommands by ``"module:attribute"`` so a command imports only what it needs
  (``mpchair houses`` never imports torch). ``--help`` lists every registered command.
* :func:`run_cli` turns :class:`mpchair.core.errors.InputError`, ``OSError`` (``error: PATH: reason``) and click's usage
  errors into one ``error: ...`` line and exit status 2, :class:`mpchair.core.errors.RunError` into one line and exit 1;
  :func:`run_script` is the same path for an argparse command line (``tools/``, the experiment's commands).
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import warnings
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
    :class:`RunError` with 1; Ctrl-C exits 130 without a traceback (``interrupted: ...`` with what a command's
    ``KeyboardInterrupt`` says was kept). Python warnings raised on the way (a house's
    oddities, numpy's floating-point notes) are held and printed after a successful run as one ``warning: ...`` line
    each (repeats once); a failed run prints its error line alone, so the error is never buried.
    """
    sys.exit(run_script(lambda: group.main(args=args, standalone_mode=False)))


def run_script(work: Callable[[], int | None]) -> int:
    """The console scripts' error path (:func:`run_cli`) around ``work`` (its exit status; None counts as 0), for the
    argparse command lines of ``tools/`` and the experiment: :class:`InputError` and ``OSError`` are one ``error:``
    line and status 2, :class:`RunError` status 1, Ctrl-C 130; warnings are held and printed after a success only.
    Returns the exit status (argparse's own ``--help`` and usage errors exit as argparse does)."""
    held: list[str] = []

    def hold(message, category, filename, lineno, file=None, line=None) -> None:  # warnings.showwarning's signature
        text = " ".join(str(message).split())
        if text not in held:
            held.append(text)

    with warnings.catch_warnings():
        warnings.showwarning = hold
        code, error = _exit_status(work)
    if error is not None:
        click.echo(f"error: {error}", err=True)
    elif code == 0:
        for text in held:
            click.echo(f"warning: {text}", err=True)
    return code


def _exit_status(work: Callable[[], int | None]) -> tuple[int, str | None]:
    """``(exit status, error line or None)`` of one run of ``work``."""
    try:
        from mpchair.core.limits import check_environment

        check_environment()  # a variable a command reads, with a value it cannot use: one line, before any work
        rv = work()
    except InputError as e:
        return 2, str(e)
    except RunError as e:
        return 1, str(e)
    except (click.exceptions.Abort, KeyboardInterrupt) as e:
        # a command that knows what its interrupted work left raises KeyboardInterrupt(what is kept, how to resume);
        # click turns a KeyboardInterrupt into Abort, keeping it as the cause
        cause = e if isinstance(e, KeyboardInterrupt) else (e.__cause__ or e.__context__)
        said = str(cause) if isinstance(cause, KeyboardInterrupt) else ""
        click.echo(f"interrupted: {said}" if said else "interrupted", err=True)
        return 130, None
    except click.UsageError as e:
        hint = f" (see '{e.ctx.command_path} --help')" if e.ctx is not None else ""
        return e.exit_code, f"{' '.join(e.format_message().split())}{hint}"
    except click.ClickException as e:
        return e.exit_code, e.format_message()
    except OSError as e:
        return 2, os_error_line(e)
    except click.exceptions.Exit as e:
        return e.exit_code, None
    return (rv if isinstance(rv, int) else 0), None
