"""Field checks shared by the typed messages of bgt_core.messages and
bgt_core.control_messages: each reads one key of a decoded JSON object, or raises
``wire.InvalidField`` with a one-line error naming the message and the field."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeGuard

from bgt_core.wire import InvalidField

REQUIRED: Any = object()  # the default that makes a field mandatory


def is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def is_num(v: object) -> TypeGuard[int | float]:
    return isinstance(v, int | float) and not isinstance(v, bool)


def get_field(d: Mapping[str, Any], key: str, what: str, default: Any) -> Any:
    if key in d and d[key] is not None:
        return d[key]
    if default is REQUIRED:
        raise InvalidField(f"{what}: {key} is missing")
    return default


def int_field(d: Mapping[str, Any], key: str, what: str, default: Any = REQUIRED) -> Any:
    v = get_field(d, key, what, default)
    if v is not default and not is_int(v):
        raise InvalidField(f"{what}: {key} must be an integer, got {v!r}")
    return v


def num_field(d: Mapping[str, Any], key: str, what: str, default: Any = REQUIRED) -> Any:
    v = get_field(d, key, what, default)
    if v is not default and not is_num(v):
        raise InvalidField(f"{what}: {key} must be a number, got {v!r}")
    return v if v is default or v is None else float(v)


def str_field(d: Mapping[str, Any], key: str, what: str, default: Any = REQUIRED) -> Any:
    v = get_field(d, key, what, default)
    if v is not default and not isinstance(v, str):
        raise InvalidField(f"{what}: {key} must be a string, got {v!r}")
    return v


def obj_field(d: Mapping[str, Any], key: str, what: str, default: Any = REQUIRED) -> Any:
    v = get_field(d, key, what, default)
    if v is not default and not isinstance(v, dict):
        raise InvalidField(f"{what}: {key} must be an object, got {type(v).__name__}")
    return v


def mapping(d: object, what: str) -> Mapping[str, Any]:
    if not isinstance(d, Mapping):
        raise InvalidField(f"{what} must be a JSON object, got {type(d).__name__}")
    return d
