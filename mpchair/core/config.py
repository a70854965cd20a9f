"""Plain YAML → frozen dataclasses, validated once at the edge (unknown key or wrong type is an error).

Both packages describe their configs as frozen dataclasses (sensor profiles, model/training configs) and load them
with :func:`load_config`. Supported field types: ``int``, ``float``, ``str``, ``bool``, ``Literal[...]``,
``tuple[T, ...]``, ``tuple[T1, T2]``, ``X | None``, and nested dataclasses. Lists in YAML become tuples, so configs stay
hashable and immutable.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from mpchair.core.errors import InputError

T = TypeVar("T")


def load_yaml(path: str | Path) -> dict:
    """Read a YAML mapping from ``path``; a missing file, a syntax error or a non-mapping is an :class:`InputError`."""
    path = Path(path)
    if not path.is_file():
        raise InputError("config file not found", path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = None if mark is None else mark.line + 1
        raise InputError(f"invalid YAML: {getattr(e, 'problem', e)}", path, line) from None
    if not isinstance(data, dict):
        raise InputError("expected a YAML mapping at the top level", path)
    return data


def load_config(cls: type[T], path: str | Path) -> T:
    """Load the YAML file ``path`` into the frozen dataclass ``cls``, validating every key and type."""
    return from_dict(cls, load_yaml(path), source=str(path))


def from_dict(cls: type[T], data: dict, source: str = "<config>", prefix: str = "") -> T:
    """Build dataclass ``cls`` from a mapping; raise :class:`InputError` naming ``source`` and the dotted key."""
    if not isinstance(data, dict):
        raise InputError(f"{prefix.rstrip('.') or 'config'}: expected a mapping, got {type(data).__name__}", source)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise InputError(f"unknown key {prefix + unknown[0]!r} (allowed: {', '.join(sorted(fields))})", source)
    kwargs = {}
    for name, f in fields.items():
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], source, prefix + name)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise InputError(f"missing required key {prefix + name!r}", source)
    return cls(**kwargs)


def to_dict(obj: Any) -> Any:
    """Dataclass (possibly nested, with tuples) → plain YAML/JSON-able data."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_dict(v) for v in obj]
    return obj


def _convert(tp: Any, value: Any, source: str, key: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(a, value, source, key)
            except InputError as e:
                errors.append(e)
        raise errors[0]
    if origin is typing.Literal:
        if value not in args:
            raise InputError(f"{key}: {value!r} is not one of {', '.join(map(repr, args))}", source)
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise InputError(f"{key}: expected a list, got {value!r}", source)
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, source, f"{key}[{i}]") for i, v in enumerate(value))
        if origin is tuple and args:
            if len(value) != len(args):
                raise InputError(f"{key}: expected {len(args)} values, got {len(value)}", source)
            return tuple(_convert(a, v, source, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        inner = args[0] if args else Any
        return tuple(_convert(inner, v, source, f"{key}[{i}]") for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, source, prefix=key + ".")
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise InputError(f"{key}: expected true/false, got {value!r}", source)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{key}: expected an integer, got {value!r}", source)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{key}: expected a number, got {value!r}", source)
        if not math.isfinite(value):
            raise InputError(f"{key}: expected a finite number, got {value!r}", source)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise InputError(f"{key}: expected a string, got {value!r}", source)
        return value
    raise TypeError(f"config field {key}: unsupported type {tp!r}")
