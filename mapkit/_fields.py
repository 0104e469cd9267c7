"""Type checks of user-given dataclass fields (a recipe's ``planner`` and ``loss`` tables, config.json), so
a wrong value is a one-line error naming the field rather than a TypeError deep inside."""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from typing import Any, Literal, Union


def _matches(value: Any, hint: Any) -> bool:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True
    if origin in (Union, types.UnionType):
        return any(_matches(value, a) for a in args)
    if hint is type(None):
        return value is None
    if origin is Literal:
        return value in args
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_matches(v, args[0]) for v in value)
        return len(value) == len(args) and all(_matches(v, a) for v, a in zip(value, args, strict=True))
    if hint is dict or origin is dict:
        return isinstance(value, dict)
    return True  # a type this check does not know: the dataclass's own validation decides


def _describe(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join("null" if a is type(None) else _describe(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(json.dumps(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of ({_describe(args[0])})"
        return f"a list of {len(args)} ({', '.join(_describe(a) for a in args)})"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(hint, str(hint))


def check_fields(values: dict[str, Any], cls: type, option: str, error: type[Exception]) -> None:
    """Raise ``error`` when ``values`` names a field ``cls`` does not have, or gives one a value of
    the wrong type (JSON types: lists stand for tuples, integers for floats)."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    for name, value in values.items():
        if name not in names:
            raise error(f"{option} {name}=…: {cls.__name__} has no field {name!r}; known: {', '.join(names)}")
        if not _matches(value, hints[name]):
            raise error(f"{option} {name}={json.dumps(value)}: expected {_describe(hints[name])} "
                        f"(VALUE is JSON, e.g. {name}={json.dumps(_example(cls, name))})")


def _example(cls: type, name: str) -> Any:
    field = next(f for f in dataclasses.fields(cls) if f.name == name)
    if field.default is not dataclasses.MISSING:
        value = field.default
    elif field.default_factory is not dataclasses.MISSING:
        value = field.default_factory()
    else:
        raise TypeError(f"{cls.__name__}.{name} has no default")
    return list(value) if isinstance(value, tuple) else value
