"""The optional ``deploy`` extra (onnx, onnxruntime, openvino, nncf): import one of its packages, or stop with one line
that names the install command."""

from __future__ import annotations

import importlib
from types import ModuleType

from mpchair.core.errors import InputError

#: What to run when a deploy package is missing (the extra in pyproject.toml).
INSTALL_HINT = "pip install '.[deploy]'"


def require(module: str, purpose: str) -> ModuleType:
    """``import module`` (e.g. ``"onnxruntime"``), or an :class:`InputError` naming ``purpose`` and the extra."""
    try:
        return importlib.import_module(module)
    except ImportError:
        # a missing wheel, or one that fails to load its shared libraries: either way the fix is the extra
        raise InputError(f"{purpose} needs {module.split('.')[0]}, which is not installed: {INSTALL_HINT}") from None
