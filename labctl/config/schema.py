"""Typed loading of YAML configuration into frozen dataclasses.

Safe YAML only. Every problem raises :class:`ConfigError` naming the file, the key path and
what was expected; unknown keys are errors, never silently ignored.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Protocol, Union, get_args, get_origin, runtime_checkable

import yaml


class ConfigError(Exception):
    """A configuration file is missing, unparsable or invalid. ``str()`` is one line."""

    def __init__(self, file: Path | str, key: str | None, message: str):
        self.file, self.key, self.message = str(file), key, message
        where = f"{self.file}: {key}: " if key else f"{self.file}: "
        super().__init__(where + message)



@runtime_checkable
class Validated(Protocol):
    """A config section with cross-field rules: ``validate()`` returns ``(key, message)`` for the first
    problem, or None."""

    def validate(self) -> tuple[str, str] | None:
        """The first problem as ``(key, message)``, or None."""
        ...

def read_yaml(path: Path) -> Any:
    """Read a YAML file with ``yaml.safe_load``; errors become one-line ConfigErrors."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(path, None, "file not found")
    try:
        with path.open(encoding="utf-8") as fh:
            return yaml.safe_load(fh)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(path, None, f"YAML does not parse: {where}{problem}") from None


@dataclasses.dataclass(frozen=True)
class Range:
    """A numeric field's bounds, as ``Annotated[float, Range(gt=0)]``; checked at load time."""

    gt: float | None = None
    ge: float | None = None
    le: float | None = None
    lt: float | None = None

    def problem(self, value: float) -> str | None:
        """What ``value`` violates (e.g. ``"> 0"``), or None when it is in range."""
        for bound, ok, word in ((self.gt, lambda b: value > b, ">"), (self.ge, lambda b: value >= b, "≥"),
                                (self.le, lambda b: value <= b, "≤"), (self.lt, lambda b: value < b, "<")):
            if bound is not None and not ok(bound):
                return f"{word} {bound:g}"
        return None


Positive = Annotated[float, Range(gt=0)]
PositiveInt = Annotated[int, Range(gt=0)]
NonNegative = Annotated[float, Range(ge=0)]
Fraction = Annotated[float, Range(ge=0, le=1)]

# YAML 1.2 numbers that PyYAML (YAML 1.1) leaves as strings: 1e9, 1E-3, +2.5e3
_YAML12_FLOAT = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+$")


def _type_name(tp) -> str:
    origin = get_origin(tp)
    if origin is Annotated:
        base, *meta = get_args(tp)
        rng = next((m for m in meta if isinstance(m, Range)), None)
        bounds = [f"{w} {b:g}" for b, w in ((rng.gt, ">"), (rng.ge, "≥"), (rng.le, "≤"), (rng.lt, "<"))
                  if b is not None] if rng else []
        return _type_name(base) + (f" {' and '.join(bounds)}" if bounds else "")
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if origin in (list, tuple):
        args = get_args(tp)
        inner = _type_name(args[0]) if args else "value"
        if origin is tuple and args and args[-1] is not Ellipsis:
            return f"a list of {len(args)} {inner}s"
        return f"a list of {inner}s"
    if origin is dict:
        return "a mapping"
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return {float: "a number", int: "an integer", str: "a string", bool: "true or false",
            type(None): "null"}.get(tp, getattr(tp, "__name__", str(tp)))


def convert(tp, value, file, key: str):
    """Convert ``value`` to type ``tp`` or raise ConfigError at ``file``/``key``."""
    origin = get_origin(tp)
    fail = lambda: ConfigError(file, key, f"expected {_type_name(tp)}, got {value!r}")  # noqa: E731
    if tp is Any:
        return value
    if origin is Annotated:
        base, *meta = get_args(tp)
        out = convert(base, value, file, key)
        for m in meta:
            problem = m.problem(out) if isinstance(m, Range) else None
            if problem:
                raise ConfigError(file, key, f"expected {_type_name(tp)}, got {value!r}")
        return out
    if isinstance(value, str) and tp in (float, int) and _YAML12_FLOAT.match(value.strip()):
        value = float(value)
        if tp is int and value.is_integer():
            value = int(value)
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return convert(a, value, file, key)
            except ConfigError:
                continue
        raise fail()
    if origin is Literal:
        if value in get_args(tp):
            return value
        raise fail()
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise fail()
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise fail()
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise ConfigError(file, key, f"expected a finite number, got {value!r}")
            return float(value)
        raise fail()
    if tp is str:
        if isinstance(value, str):
            return value
        raise fail()
    if origin in (list, tuple):
        if not isinstance(value, list):
            raise fail()
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise fail()
            return tuple(convert(a, v, file, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        inner = args[0] if args else Any
        items = [convert(inner, v, file, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise fail()
        kt, vt = get_args(tp) or (Any, Any)
        return {convert(kt, k, file, key): convert(vt, v, file, f"{key}.{k}") for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        return from_mapping(tp, value, file, key)
    raise TypeError(f"unsupported config type {tp!r}")


def from_mapping(cls, data, file, key: str = ""):
    """Build dataclass ``cls`` from a mapping, checking types, required and unknown keys."""
    prefix = f"{key}." if key else ""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(file, key or None, f"expected a mapping, got {data!r}")
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(map(str, data)) - set(fields))
    if unknown:
        raise ConfigError(file, prefix + unknown[0], f"unknown key (expected one of: {', '.join(fields)})")
    kwargs = {}
    for name, fld in fields.items():
        if name in data:
            kwargs[name] = convert(hints[name], data[name], file, prefix + name)
        elif fld.default is dataclasses.MISSING and fld.default_factory is dataclasses.MISSING:
            raise ConfigError(file, prefix + name, f"missing required key ({_type_name(hints[name])})")
    obj = cls(**kwargs)
    if isinstance(obj, Validated):
        problem = obj.validate()
        if problem:
            bad_key, message = problem
            raise ConfigError(file, prefix + bad_key, message)
    return obj


def _dataclass_in(tp):
    """The dataclass a field of type ``tp`` holds (through Annotated and Optional), or None."""
    if get_origin(tp) is Annotated:
        tp = get_args(tp)[0]
    if get_origin(tp) in (Union, types.UnionType):
        inner = [a for a in get_args(tp) if a is not type(None)]
        tp = inner[0] if len(inner) == 1 else None
    return tp if tp is not None and dataclasses.is_dataclass(tp) else None


def defaulted_keys(cls, data, prefix: str = "") -> list[str]:
    """The keys of dataclass ``cls`` (dotted, as in the file) whose value comes from the code's default
    because ``data`` (the file's mapping, as :func:`from_mapping` read it) does not set them."""
    data = data if isinstance(data, dict) else {}
    hints = typing.get_type_hints(cls, include_extras=True)
    out: list[str] = []
    for fld in dataclasses.fields(cls):
        if not fld.init:
            continue
        key, sub = prefix + fld.name, _dataclass_in(hints[fld.name])
        given = fld.name in data
        if sub is not None and (not given or data[fld.name] is None or isinstance(data[fld.name], dict)):
            default = fld.default_factory() if fld.default_factory is not dataclasses.MISSING else fld.default
            if given or default is not None:  # a nested section: which of its keys the file left out
                out += defaulted_keys(sub, data.get(fld.name), key + ".")
                continue
        if not given:
            out.append(key)
    return out


def to_plain(obj):
    """Dataclass → plain dict/list/scalars, suitable for YAML or JSON."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, list | tuple):
        return [to_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_plain(v) for k, v in obj.items()}
    if isinstance(obj, Path):
        return str(obj)
    return obj
