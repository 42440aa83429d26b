"""The one walk over a config dataclass's field types, for each surface that reads one: JSON
(:mod:`worldtree.infra.config_json`) and command-line text (``--set``, the generated options). The walk owns
``None`` unions (arms tried in order), tuples and nested dataclasses; a :class:`Surface` owns its leaves.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Callable
from typing import Any, NamedTuple

from worldtree.infra.errors import UserError

UNION, LITERAL, VARIADIC, FIXED, DATACLASS, SCALAR = "union", "literal", "variadic", "fixed", "dataclass", "scalar"


class Shape(NamedTuple):
    kind: str  # one of the kinds above; SCALAR is anything else (NoneType included)
    args: tuple[Any, ...] = ()  # union: its arms but None; literal: the choices; tuples: the item types
    optional: bool = False  # a union with None among its arms


class Surface(NamedTuple):
    """What one surface's values look like: none, a tuple's items, a leaf and a nested dataclass."""

    is_none: Callable[[Any], bool]
    items: Callable[[Any], list[Any]]  # a tuple's items
    leaf: Callable[[Any, Any], Any]  # (SCALAR or LITERAL annotation, value); Mismatch where it does not fit
    record: Callable[[type, Any], Any]  # (dataclass, value)


class Mismatch(ValueError):
    """A value that does not fit its annotation (a union tries its next arm)."""


def shape_of(tp: Any) -> Shape:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return Shape(UNION, tuple(a for a in args if a is not type(None)), type(None) in args)
    if origin is typing.Literal:
        return Shape(LITERAL, args)
    if origin is tuple:
        return Shape(VARIADIC, args[:1]) if len(args) == 2 and args[1] is Ellipsis else Shape(FIXED, args)
    return Shape(DATACLASS) if dataclasses.is_dataclass(tp) else Shape(SCALAR)


def optional_of(tp: Any) -> tuple[Any, bool]:
    """``X | None`` -> ``(X, True)``; anything else -> ``(tp, False)``."""
    kind, args, optional = shape_of(tp)
    return (args[0], True) if kind == UNION and optional and len(args) == 1 else (tp, False)


def field_types(cls: type) -> dict[str, Any]:
    """Resolved annotations of the init fields of dataclass ``cls`` (string annotations included)."""
    try:
        hints = typing.get_type_hints(cls)
    except Exception as e:  # an annotation naming something not importable at run time
        raise UserError(f"{cls.__name__}: field types do not resolve ({e})") from e
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def convert(tp: Any, value: Any, surface: Surface) -> Any:
    """``value`` (in ``surface``'s form) as annotation ``tp``; :class:`Mismatch` where it does not fit."""
    kind, args, optional = shape_of(tp)
    if kind == UNION:
        if optional and surface.is_none(value):
            return None
        for arm in args:
            try:
                return convert(arm, value, surface)
            except Mismatch:
                continue
        raise Mismatch(f"{value!r} fits none of {tp}")
    if kind == DATACLASS:
        return surface.record(tp, value)
    if kind in (VARIADIC, FIXED):
        items = surface.items(value)
        item_types = args * len(items) if kind == VARIADIC else args
        if len(items) != len(item_types):
            raise Mismatch(f"{len(item_types)} values expected, got {len(items)}")
        return tuple(convert(a, x, surface) for a, x in zip(item_types, items, strict=True))
    return surface.leaf(tp, value)


def setting_paths(cls: type) -> dict[str, str]:
    """``{"Class.field": "dotted.path"}`` of the fields of dataclass ``cls``, nested (and optional nested)
    dataclasses' fields included: where the setting a :class:`~worldtree.infra.errors.SettingError` names
    sits in ``cls``. A ``Class.field`` found at two paths is left out (it would be ambiguous)."""
    found: dict[str, list[str]] = {}

    def walk(c: type, prefix: str) -> None:
        for name, tp in field_types(c).items():
            inner, _ = optional_of(tp)
            if dataclasses.is_dataclass(inner):
                walk(inner, f"{prefix}{name}.")
            else:
                found.setdefault(f"{c.__name__}.{name}", []).append(prefix + name)

    walk(cls, "")
    return {setting: paths[0] for setting, paths in found.items() if len(paths) == 1}
