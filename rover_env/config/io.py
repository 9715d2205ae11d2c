"""Strict construction of frozen configuration dataclasses from plain data (YAML, dicts).

Every error names the key path (and the file when loading from one) so the user can fix it:
unknown keys, missing required keys, wrong types and out-of-range values are all rejected.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

from perception.models.validation import ConfigError, check_range, read_yaml, real_number

__all__ = ["ConfigError", "check_range", "from_dict", "to_dict", "load_yaml_dataclass", "replace"]

T = TypeVar("T")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, key: str, allow_inf: bool = False) -> Any:
    """Convert ``value`` to type ``tp`` or raise ConfigError naming ``key``.

    ``allow_inf``: a float may be infinite (a field whose metadata says ``allow_inf``).
    """
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key, allow_inf)
            except ConfigError as exc:
                errors.append(exc)
        if len(errors) == 1:  # X | None: X's own error names the key inside
            raise errors[0]
        raise ConfigError(f"{key}: {value!r} does not match {_type_name(tp)}")
    if origin is Literal:
        allowed = get_args(tp)
        if value not in allowed:
            raise ConfigError(f"{key}: {value!r} is not one of {list(allowed)}")
        return value
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a mapping for {tp.__name__}, got {value!r}")
        return from_dict(tp, value, key)
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{key}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        return real_number(key, value, allow_inf=allow_inf)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{key}: unsupported field type {_type_name(tp)}")


def from_dict(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build the frozen dataclass ``cls`` from ``data``, strictly.

    Args:
        cls: A dataclass type whose fields have type hints.
        data: Mapping of field name to value; nested dataclasses are mappings.
        prefix: Key path of ``data`` for error messages (e.g. ``"terrain"``).

    Returns:
        The constructed instance (its ``__post_init__`` validation has run).

    Raises:
        ConfigError: On unknown keys, missing keys, wrong types or invalid values.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix or cls.__name__}: expected a mapping, got {data!r}")
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    dot = f"{prefix}." if prefix else ""
    unknown = sorted(set(data) - set(fields), key=str)  # keys may mix numbers and strings
    if unknown:
        raise ConfigError(f"unknown key '{dot}{unknown[0]}' (allowed keys: {', '.join(sorted(fields))})")
    kwargs = {}
    for name, field in fields.items():
        key = f"{dot}{name}"
        if name not in data:
            no_default = field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING
            if no_default:
                raise ConfigError(f"missing required key '{key}'")
            continue
        kwargs[name] = _coerce(data[name], hints[name], key, bool(field.metadata.get("allow_inf", False)))
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        msg = str(exc)
        if prefix and not msg.startswith(prefix):
            for lead in ("unknown key '", "missing required key '"):  # the key path inside the quotes
                if msg.startswith(lead):
                    msg = f"{lead}{dot}{msg[len(lead) :]}"
                    break
            else:
                msg = f"{dot}{msg}"
        raise ConfigError(msg) from None


def to_dict(obj: Any) -> Any:
    """Plain-data (YAML-safe) form of a configuration dataclass, inverse of :func:`from_dict`."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init}
    if isinstance(obj, tuple | list):
        return [to_dict(v) for v in obj]
    return obj


def load_yaml_dataclass(cls: type[T], path: str | Path) -> T:
    """Load a YAML file into the dataclass ``cls``; errors name the file and the key.

    Raises:
        ConfigError: If the file is missing, is not valid YAML, or does not fit ``cls``.
    """
    path = Path(path)
    data = read_yaml(path)
    if data is None:
        data = {}
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def replace(obj: T, **changes: Any) -> T:
    """``dataclasses.replace`` re-exported with a type-preserving signature."""
    return typing.cast(T, dataclasses.replace(obj, **changes))  # type: ignore[type-var]
