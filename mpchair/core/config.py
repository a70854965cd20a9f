"""Plain YAML → frozen dataclasses, validated once at the edge (unknown key or wrong type is an error).

Both packages describe their configs as frozen dataclasses (sensor profiles, model/training configs) and load them
with :func:`load_config`. Supported field types: ``int``, ``float``, ``str``, ``bool``, ``Literal[...]``,
``tuple[T, ...]``, ``tuple[T1, T2]``, ``X | None``, and nested dataclasses. Lists in YAML become tuples, so configs stay
hashable and immutable.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import math
import re
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml

from mpchair.core.errors import InputError
from mpchair.core.text import decode_utf8

T = TypeVar("T")


#: Largest config file read (a config is a few KB; a bigger file is not one).
MAX_CONFIG_BYTES = 1 << 20
#: Deepest nesting of mappings / lists accepted (real configs nest three levels).
MAX_CONFIG_DEPTH = 32

# YAML 1.2 numbers: PyYAML follows YAML 1.1, where ``1e-9`` (no dot) is a string; a config author means a number.
_FLOAT_12 = r"""^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?(?:[eE][-+]?[0-9]+)?|\.[0-9_]+(?:[eE][-+]?[0-9]+)?)$"""


class _ConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate keys and reads YAML 1.2 floats (``1e-9``)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.setdefault(key, key_node.start_mark.line + 1)
            except TypeError:  # an unhashable key: SafeLoader's own error says so
                continue
            if first != key_node.start_mark.line + 1:
                raise InputError(f"duplicate key {key!r} (first on line {first})", self.name,
                                 key_node.start_mark.line + 1)
        return super().construct_mapping(node, deep=deep)

    def compose_node(self, parent, index):  # PyYAML calls it for every node: count the depth
        self._depth = getattr(self, "_depth", 0) + 1
        try:
            if self._depth > MAX_CONFIG_DEPTH:
                mark = self.peek_event().start_mark
                raise InputError(f"nested deeper than {MAX_CONFIG_DEPTH} levels", self.name, mark.line + 1)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


_ConfigLoader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(_FLOAT_12, re.X),
                                    list("-+0123456789."))


def load_yaml(path: str | Path) -> dict:
    """Read a YAML mapping from ``path``; a missing file, a non-UTF-8 or oversized file, a syntax error, a duplicate
    key, nesting deeper than :data:`MAX_CONFIG_DEPTH` or a non-mapping is an :class:`InputError` (file and line)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("config file not found", path)
    if path.stat().st_size > MAX_CONFIG_BYTES:
        raise InputError(f"larger than {MAX_CONFIG_BYTES >> 20} MiB: not a config file", path)
    text = decode_utf8(path.read_bytes(), path)
    loader = _ConfigLoader(text)
    loader.name = str(path)
    try:
        data = loader.get_single_data()
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = None if mark is None else mark.line + 1
        raise InputError(f"invalid YAML: {getattr(e, 'problem', None) or e}", path, line) from None
    finally:
        loader.dispose()
    if not isinstance(data, dict):
        raise InputError("expected a YAML mapping at the top level", path)
    return data


def key_lines(path: str | Path) -> dict[str, int]:
    """Dotted key (``model.backbone``) -> the 1-based line it is on, for every mapping key of the YAML file ``path``
    (already read by :func:`load_yaml`, so it parses); {} when it cannot be read."""
    try:
        loader = _ConfigLoader(decode_utf8(Path(path).read_bytes(), path))
        try:
            root = loader.get_single_node()
        finally:
            loader.dispose()
    except (OSError, InputError, yaml.YAMLError):
        return {}
    lines: dict[str, int] = {}

    def walk(node: yaml.Node, prefix: str) -> None:
        if isinstance(node, yaml.MappingNode):
            for key_node, value_node in node.value:
                key = f"{prefix}{key_node.value}"
                lines.setdefault(key, key_node.start_mark.line + 1)
                if isinstance(value_node, yaml.MappingNode):
                    lines.setdefault(key + ".", key_node.start_mark.line + 1)  # marks a section
                walk(value_node, key + ".")

    if root is not None:
        walk(root, "")
    return lines


_KEYISH = re.compile(r"'([A-Za-z_][\w.]*)'|\b([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+)\b|^([A-Za-z_]\w*)(?:\[\d+\])*:")


def at_key_line(e: InputError, path: str | Path) -> InputError:
    """``e`` with the line of the config key its message names (``model.backbone: ...``, ``unknown key 'x.y'``; for
    a missing key, its section's line), when ``e`` names ``path`` and no line yet; else ``e`` itself. A message about
    a whole section (``model: needs at least ... GiB``) gets no line: no one line is at fault."""
    if e.line is not None or e.path != str(path):
        return e
    lines = key_lines(path)
    best: tuple[int, int] | None = None  # (parts, line) of the most specific key named
    for match in _KEYISH.finditer(e.message):
        if match.group(3) and match.group(3) + "." in lines:
            continue  # "section: ..." speaks of the whole section
        parts = next(g for g in match.groups() if g).split(".")
        for n in range(len(parts), 0, -1):
            line = lines.get(".".join(parts[:n]))
            if line is not None:
                if best is None or n > best[0]:
                    best = (n, line)
                break
    return e if best is None else InputError(e.message, e.path, best[1])


#: Suffixes that make a ``--config`` / ``--sensor`` value a file name rather than a packaged name.
YAML_SUFFIXES = (".yaml", ".yml")


def package_folder(package: str, name: str) -> Path:
    """The folder ``name`` shipped inside ``package`` as package data (found through :mod:`importlib.resources`, so
    the same in a checkout, an editable install and an installed wheel)."""
    folder = importlib.resources.files(package) / name
    # pip unpacks wheels, so the package data are real files; a zip import would need as_file() for every read.
    if not isinstance(folder, Path):
        raise RuntimeError(f"{package} is installed as a zip archive; install it unpacked (pip does) to read {name}/")
    return folder


def packaged_names(folder: Path) -> list[str]:
    """Names (file stems) of the YAML files shipped in the package folder ``folder``, sorted."""
    return sorted(p.stem for p in Path(folder).iterdir() if p.suffix in YAML_SUFFIXES and p.is_file())


def resolve_named_file(name_or_path: str | Path, folder: Path, what: str) -> Path:
    """The YAML file meant by ``name_or_path``: an existing file (a path wins), else a name packaged in ``folder``.

    ``what`` names the kind in errors (``sensor``, ``config``). A value that looks like a path (a folder separator or
    a ``.yaml`` suffix) but names no file, or an unknown name, is an :class:`InputError` listing the packaged names.
    """
    p = Path(name_or_path)
    if p.is_file():
        return p
    text = str(name_or_path)
    names = packaged_names(folder)
    looks_like_path = p.suffix in YAML_SUFFIXES or "/" in text or "\\" in text
    if not looks_like_path and text in names:
        return Path(folder) / f"{text}.yaml"
    listed = ", ".join(names) or "none"
    if looks_like_path:
        raise InputError(f"{what} file not found (packaged {what}s, available by name: {listed})", p)
    # the name of neither a file nor a packaged one (the wording docs/generate.md lists for --sensor)
    raise InputError(f"unknown {what} {text!r} (available: {listed})")


#: The key with which a YAML file names the file it derives from (OpenPCDet's spelling).
BASE_KEY = "_BASE_CONFIG_"


def load_derived_yaml(
    path: str | Path,
    *,
    named_base: Callable[[str], Path | None] | None = None,
    check_base: Callable[[dict, Path], None] | None = None,
    _chain: tuple[Path, ...] = (),
) -> dict:
    """:func:`load_yaml` of ``path`` with the file it derives from merged underneath: a top-level ``_BASE_CONFIG_``
    names one base, either a YAML path (relative to ``path``'s folder) or a name that ``named_base`` turns into a file
    (the detector's packaged configs); the file's own keys go on top (:func:`merge_config`). Bases may derive in turn.

    ``check_base(data, base_path)`` validates each base's merged mapping on its own, so that a bad key is reported
    against the file that holds it. A missing base, a base value of the wrong type or a cycle of bases is an
    :class:`InputError` naming ``path``.
    """
    path = Path(path)
    data = load_yaml(path)
    if BASE_KEY not in data:
        return data
    base = _base_file(data.pop(BASE_KEY), path, named_base)
    chain = (*_chain, path.resolve())
    if base.resolve() in chain:
        loop = " -> ".join(p.name for p in (*chain, base))
        raise InputError(f"{BASE_KEY} cycle: {loop}", path)
    base_data = load_derived_yaml(base, named_base=named_base, check_base=check_base, _chain=chain)
    if check_base is not None:
        check_base(base_data, base)
    return merge_config(base_data, data)


def _base_file(value: object, path: Path, named_base: Callable[[str], Path | None] | None) -> Path:
    """The file named by ``path``'s ``_BASE_CONFIG_`` value: a YAML path relative to ``path``'s folder, or a name."""
    if not isinstance(value, str) or not value:
        raise InputError(f"{BASE_KEY}: expected a YAML path or a config name, got {value!r}", path)
    if Path(value).suffix in YAML_SUFFIXES or "/" in value:
        base = path.parent / value
        if not base.is_file():
            raise InputError(f"{BASE_KEY}: base file {value!r} not found (looked for {base})", path)
        return base
    base = named_base(value) if named_base is not None else None
    if base is None:
        raise InputError(f"{BASE_KEY}: {value!r} is not a known config name (give a YAML path, relative to this "
                         "file's folder)", path)
    return base


def merge_config(base: Mapping, changes: Mapping) -> dict:
    """``base`` with ``changes`` on top: nested mappings merge key by key, any other value (a list included) replaces
    the base's."""
    out = dict(base)
    for key, value in changes.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge_config(out[key], value)
        else:
            out[key] = value
    return out


def load_config(cls: type[T], path: str | Path) -> T:
    """Load the YAML file ``path`` into the frozen dataclass ``cls``, validating every key and type (an error names
    the file and the line of the key at fault)."""
    data = load_yaml(path)
    try:
        return from_dict(cls, data, source=str(path))
    except InputError as e:
        raise at_key_line(e, path) from None


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
