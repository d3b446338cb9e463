"""Frozen-dataclass configs built from plain dicts / YAML with errors that name the field.

Every config in rl-scan is a frozen dataclass. ``build_config(Cls, mapping)`` turns a
(possibly nested) mapping into one, rejecting unknown keys (with a "did you mean"
hint) and wrong types, and runs each class's ``validate()`` so that out-of-range
values fail before anything else starts.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import re
import tempfile
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A config value is invalid. The message names the field, the value and what is allowed."""


class RunInterrupted(RuntimeError):
    """A training run stopped before its budget (Ctrl+C); its last checkpoint can be resumed."""


def fail(field: str, value: Any, allowed: str) -> typing.NoReturn:
    """Raise a ConfigError in the one format used everywhere."""
    raise ConfigError(f"{field}={value!r} is invalid: allowed {allowed}")


def check_range(field: str, value: float, lo: float | None = None, hi: float | None = None,
                lo_open: bool = False) -> None:
    """Raise unless lo <= value <= hi (lo < value if lo_open)."""
    bad = (lo is not None and (value <= lo if lo_open else value < lo)) or (
        hi is not None and value > hi)
    if bad:
        left = "(" if lo_open else "["
        fail(field, value, f"a value in {left}{lo if lo is not None else '-inf'}, "
                           f"{hi if hi is not None else 'inf'}]")


def _coerce(field: str, tp: Any, value: Any) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            fail(field, value, f"a mapping for {tp.__name__}")
        return build_config(tp, value, prefix=field + ".")
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(field, arg, value)
            except ConfigError:
                continue
        fail(field, value, " or ".join(getattr(a, "__name__", str(a)) for a in args))
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            fail(field, value, f"one of {list(typing.get_args(tp))}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            fail(field, value, "a list")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(f"{field}[{i}]", args[0], v) for i, v in enumerate(value))
        if len(value) != len(args):
            fail(field, value, f"a list of {len(args)} values")
        return tuple(_coerce(f"{field}[{i}]", a, v) for i, (a, v) in enumerate(zip(args, value)))
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            fail(field, value, "a number")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            fail(field, value, "an integer")
        return int(value)
    if tp is bool:
        if not isinstance(value, bool):
            fail(field, value, "true or false")
        return value
    if tp is str:
        if not isinstance(value, str):
            fail(field, value, "a string")
        return value
    return value


def build_config(cls: type[T], mapping: dict[str, Any] | None = None, prefix: str = "") -> T:
    """Build dataclass ``cls`` from ``mapping``; unknown keys and bad values raise ConfigError."""
    mapping = dict(mapping or {})
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    hints = typing.get_type_hints(cls)
    unknown = [k for k in mapping if k not in fields]
    if unknown:
        key = unknown[0]
        close = difflib.get_close_matches(str(key), list(fields), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(
            f"unknown config key {prefix + str(key)!r}{hint}: allowed keys are {sorted(fields)}")
    for k, v in mapping.items():  # a partial nested mapping overrides the field's default
        default = _field_default(fields[k])
        if isinstance(v, dict) and dataclasses.is_dataclass(default):
            mapping[k] = deep_merge(to_dict(default), v)
    kwargs = {k: _coerce(prefix + k, hints[k], v) for k, v in mapping.items()}
    obj = cls(**kwargs)
    validate = getattr(obj, "validate", None)
    if validate is not None:
        validate(prefix)
    return obj


def _field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def to_dict(obj: Any) -> Any:
    """Convert a (nested) dataclass config into plain dicts/lists for YAML/JSON."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    return obj


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """Merge ``override`` into a copy of ``base``, recursing into nested mappings."""
    out = dict(base)
    for k, v in override.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def check_writable(field: str, path: str | Path, *, folder: bool) -> None:
    """Refuse an output path that cannot be written, before any work starts.

    The nearest existing folder on the way to ``path`` (its parent for a file) must take
    a new sub-folder: a probe folder is made there and removed at once, which catches
    read-only and virtual file systems (/proc, /sys) where permission bits alone do not.
    """
    target = Path(path).expanduser().absolute()
    where = target if folder else target.parent
    if folder and target.exists() and not target.is_dir():
        fail(field, str(path), "a folder (a file of that name exists)")
    base = where
    while not base.exists():
        base = base.parent
    if not base.is_dir():
        fail(field, str(path), f"a path under a folder ({str(base)!r} is a file)")
    try:
        probe = tempfile.mkdtemp(prefix=".rl-scan-probe-", dir=base)
    except OSError as e:
        fail(field, str(path), f"a writable location (no folder can be made in "
                               f"{str(base)!r}: {e.strerror})")
    os.rmdir(probe)


class _Loader(yaml.SafeLoader):
    """YAML's safe loader, with YAML 1.2's floats: PyYAML follows YAML 1.1, where ``1e-6``
    (no dot) is the string '1e-6', so ``--meta inner_lr=1e-6`` was refused as not a number."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load`` that also reads exponent floats without a dot (``1e-6``, ``3E2``)."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; a missing or malformed file raises ConfigError naming it."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"file {str(path)!r} does not exist")
    try:
        data = parse_yaml(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"file {str(path)!r} is not valid YAML: {e}") from e
    if not isinstance(data, dict):
        raise ConfigError(f"file {str(path)!r} must hold a mapping, got {type(data).__name__}")
    return data
