"""The clone of the repository the experiment runs in: found from this package's own location, never from a
caller's ``__file__``.

The experiment is the one package that works on a clone only: it writes the clone's ``docs/`` and ``README.md``, runs
its ``tools/`` scripts and reads its vendored ``tests/data/kitti`` frames. Everything a command of the two stacks
reads ships as package data (``detector.config.CONFIG_DIR``, ...), so an installed wheel works without a clone; an
installed ``reproduction`` finds none and says so in one line (:func:`require_checkout`).
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

from mpchair.core.errors import InputError


def _package_parent() -> Path:
    """The folder that holds the ``reproduction`` package: a clone's root in a clone (run in place or installed in
    editable mode), ``site-packages`` in an installed wheel (a zip import gives a path inside the archive, which is no
    clone either)."""
    return Path(str(importlib.resources.files(__package__))).resolve().parent


#: The checkout: every command of the experiment runs in it, and its reports name paths relative to it. In an
#: installed wheel it is ``site-packages`` and :func:`require_checkout` refuses.
ROOT: Path = _package_parent()


def checkout_problem(root: Path | None = None) -> str | None:
    """Why ``root`` (default :data:`ROOT`) is not a clone of the repository (it lacks the project's
    ``pyproject.toml``, ``tools/`` or ``docs/``), or None when it is one."""
    root = ROOT if root is None else root
    if (root / "pyproject.toml").is_file() and (root / "tools").is_dir() and (root / "docs").is_dir():
        return None
    return (f"the reproduction runs in a clone of the repository (it writes its docs/ and README.md); {root} is not "
            "one (this is an installed package): clone the repository and run make reproduce there")


def require_checkout(root: Path | None = None) -> Path:
    """``root`` (default :data:`ROOT`) when it is a clone of the repository, else an :class:`InputError` saying so
    (the experiment's commands call it before any work)."""
    root = ROOT if root is None else root
    problem = checkout_problem(root)
    if problem is not None:
        raise InputError(problem)
    return root
