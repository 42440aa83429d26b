"""Typed settings as plain JSON: a dataclass written with its values and read back into the same types.

For settings one process writes and another reads (the tree's node settings for its worker processes): JSON
that a person can read, instead of a pickle, which runs code when loaded and breaks when a class moves.
Supported field types: the JSON scalars, ``None`` unions, ``Literal``, tuples (``tuple[X, ...]`` and fixed),
lists, dicts of scalars and nested dataclasses.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any

from worldtree.infra.atomic import atomic_write_json


def write_config(path: str | Path, obj: Any) -> None:
    """Write the dataclass ``obj`` as JSON (atomically)."""
    atomic_write_json(path, dataclasses.asdict(obj))


def read_config(path: str | Path, cls: type) -> Any:
    """The ``cls`` instance written by :func:`write_config` at ``path``."""
    return from_dict(cls, json.loads(Path(path).read_text()))


def from_dict(cls: type, data: dict[str, Any]) -> Any:
    """``cls(**data)`` with every value converted to its field's type (nested dataclasses, tuples); a key
    ``cls`` does not have is a ``ValueError``, a missing one takes the field's default."""
    if not isinstance(data, dict):
        raise ValueError(f"{cls.__name__}: expected a JSON object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown settings {unknown}")
    return cls(**{k: _value(hints[k], v) for k, v in data.items()})


def _value(tp: Any, v: Any) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        if v is None:
            return None
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        for a in args:  # a dataclass member takes a JSON object; anything else is converted by its own type
            if dataclasses.is_dataclass(a) and isinstance(v, dict):
                return from_dict(a, v)
        return _value(args[0], v) if len(args) == 1 else v
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, v)
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_value(args[0], x) for x in v)
        return tuple(_value(a, x) for a, x in zip(args, v, strict=True))
    if tp is float and isinstance(v, int) and not isinstance(v, bool):
        return float(v)
    return v
