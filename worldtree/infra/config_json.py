"""Typed settings as plain JSON: a dataclass written with its values and read back into the same types.

For settings one process writes and another reads (the tree's node settings for its worker processes): JSON
that a person can read, instead of a pickle, which runs code when loaded and breaks when a class moves.
Supported field types: the JSON scalars, ``None`` unions, ``Literal``, tuples (``tuple[X, ...]`` and fixed),
lists, dicts of scalars and nested dataclasses; :mod:`worldtree.infra.typed_config` walks the types.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.typed_config import Surface, convert, field_types


def write_config(path: str | Path, obj: Any) -> None:
    """Write the dataclass ``obj`` as JSON (atomically)."""
    atomic_write_json(path, dataclasses.asdict(obj))


def read_config(path: str | Path, cls: type) -> Any:
    """The ``cls`` instance written by :func:`write_config` at ``path``."""
    return from_dict(cls, json.loads(Path(path).read_text()))


def from_dict(cls: type, data: dict[str, Any]) -> Any:
    """``cls(**data)`` with every value converted to its field's type (nested dataclasses, tuples); a key
    ``cls`` does not have is a ``ValueError``, a missing one takes the field's default, one of a field ``cls``
    derives itself (``init=False``, written with the rest) is skipped."""
    if not isinstance(data, dict):
        raise ValueError(f"{cls.__name__}: expected a JSON object, got {type(data).__name__}")
    hints = field_types(cls)
    unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown settings {unknown}")
    return cls(**{k: convert(hints[k], v, _JSON) for k, v in data.items() if k in hints})


#: JSON's side of the walk: a leaf as it is (an integer made a float for a float field), a dataclass an object.
_JSON = Surface(
    is_none=lambda v: v is None,
    items=list,
    leaf=lambda tp, v: float(v) if tp is float and isinstance(v, int) and not isinstance(v, bool) else v,
    record=from_dict,
)
