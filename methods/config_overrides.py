"""``--set KEY=VALUE``: change any typed field of a method's config dataclass from the command line.

``KEY`` is a dotted path through nested config dataclasses (``photometric.lambda_depth``,
``priors.epi.threshold_px``); ``VALUE`` is parsed by the field's annotated type:

===========================  ==========================================================================
annotation                   accepted ``VALUE``
===========================  ==========================================================================
``int`` / ``float``          a Python number (``3``, ``30_000``, ``1e-3``); NaN is refused
``bool``                     ``true/false``, ``1/0``, ``yes/no``, ``on/off`` (any case)
``str`` / ``Path``           the text as given
``X | None``                 ``none`` or ``null`` (any case) for None, otherwise as ``X``
``Literal[...]``             one of the choices
``tuple[X, ...]``            comma-separated ``X`` values (empty: the empty tuple)
``tuple[X, Y, Z]``           exactly that many comma-separated values
===========================  ==========================================================================

A nested dataclass is never replaced as a whole: name one of its fields. A setting the configured run never
reads is refused, so that a ``--set`` either changes the run or is an error: the config's
``ignored_settings()`` lists them for the final config (e.g. ``photometric.steps``, which the method fills in
from ``steps``; ``budget.*`` while the budget is off; the tree's settings under ``--ablate tpt``). The config
is rebuilt with :func:`dataclasses.replace` from the innermost dataclass outwards (frozen dataclasses are not
mutated), so every ``__post_init__`` on the path validates the new values again. The walk over the types is
:mod:`worldtree.infra.typed_config`'s; this module reads the text.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from worldtree.infra import typed_config as tc
from worldtree.infra.errors import SettingError, UserError
from worldtree.infra.typed_config import Mismatch, Surface, convert, field_types, setting_paths, shape_of

_BOOLS = {**dict.fromkeys(("true", "1", "yes", "on"), True), **dict.fromkeys(("false", "0", "no", "off"), False)}
_NONE = ("none", "null")


def split_assignment(item: str) -> tuple[str, str]:
    """``"a.b = 1"`` -> ``("a.b", "1")``: the key without spaces and the value with surrounding spaces
    stripped; a missing ``=`` or an empty key is a :class:`UserError`."""
    key, sep, value = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise UserError(f"--set {item!r}: expected KEY=VALUE, e.g. --set photometric.lambda_depth=0.1")
    if any(not part.isidentifier() for part in key.split(".")):
        raise UserError(f"--set {item!r}: KEY must be dotted field names, e.g. priors.epi.threshold_px")
    return key, value.strip()


def canonical_sets(items: Sequence[str]) -> list[str]:
    """The assignments as sorted ``KEY=VALUE`` strings (spaces around key and value dropped); the same
    settings given in any order give the same list. A key given twice is a :class:`UserError` (with sorting,
    "the last one wins" would depend on the order)."""
    pairs = [split_assignment(s) for s in items]
    seen: set[str] = set()
    for key, _ in pairs:
        if key in seen:
            raise UserError(f"--set {key}=...: given more than once; keep one")
        seen.add(key)
    return sorted(f"{k}={v}" for k, v in pairs)


def sets_digest(items: Sequence[str]) -> str:
    """8 hex digits of the sha256 of :func:`canonical_sets` joined by newlines (names the run folder)."""
    text = "\n".join(canonical_sets(items))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:8]


def apply_overrides(cfg: Any, items: Sequence[str]) -> Any:
    """A copy of the config dataclass ``cfg`` with every ``KEY=VALUE`` of ``items`` applied, in order.

    Each assignment replaces the field through :func:`dataclasses.replace` at every level of its dotted path,
    so frozen dataclasses work and ``__post_init__`` checks run again; their :class:`UserError`,
    ``ValueError`` or ``TypeError`` comes back as a :class:`UserError` naming the assignment. An unknown key,
    a value that does not parse as the field's type, or a key naming a whole nested dataclass is a
    :class:`UserError` naming the key.
    """
    canonical_sets(items)  # refuses malformed items and keys given twice, before any work
    for item in items:
        key, raw = split_assignment(item)
        try:
            cfg = _replace_path(cfg, key.split("."), key, raw)
        except SettingError as e:  # the key's own field is named by the key; another field by its name
            own = setting_paths(type(cfg)).get(e.setting) == key
            raise UserError(f"--set {key}={raw}: {e.why if own else e}") from e
        except UserError as e:
            if str(e).startswith("--set "):
                raise
            raise UserError(f"--set {key}={raw}: {e}") from e
        except (ValueError, TypeError) as e:
            raise UserError(f"--set {key}={raw}: rejected: {e}") from e
    ignored = cfg.ignored_settings() if hasattr(cfg, "ignored_settings") else {}
    for item in items:  # against the final config: `--set budget.enabled=true` may come after a budget key
        key, raw = split_assignment(item)
        if key in ignored:
            raise UserError(f"--set {key}={raw}: this run never reads {key} ({ignored[key]})")
    return cfg


def _replace_path(obj: Any, path: list[str], key: str, raw: str, done: tuple[str, ...] = ()) -> Any:
    """``obj`` with the field at ``path`` (below the already walked ``done``) set to ``raw`` parsed."""
    types_ = field_types(type(obj))
    name = path[0]
    here = ".".join((*done, name))
    if name not in types_:
        where = ".".join(done) or type(obj).__name__
        derived = {f.name: f.metadata.get("derived_from") for f in dataclasses.fields(obj)}
        if name in derived:  # a field the config derives (init=False)
            source = ".".join((*done, derived[name])) if derived[name] else "other settings"
            raise UserError(f"--set {key}: {here} follows from {source}; set that instead")
        raise UserError(f"--set {key}: {where} has no field {name!r}{_suggest(name, types_)}")
    current = getattr(obj, name)
    if len(path) > 1:
        if not dataclasses.is_dataclass(current):
            raise UserError(
                f"--set {key}: {here} is a single value ({describe_type(types_[name])}), not a group of settings"
            )
        return dataclasses.replace(obj, **{name: _replace_path(current, path[1:], key, raw, (*done, name))})
    if dataclasses.is_dataclass(current):
        sub = sorted(field_types(type(current)))
        raise UserError(
            f"--set {key}: {here} is a group of settings ({type(current).__name__}), not one value; "
            f"set one of its fields, e.g. {here}.{sub[0]}=VALUE (fields: {', '.join(sub)})"
        )
    return dataclasses.replace(obj, **{name: parse_value(types_[name], raw, key)})


def _suggest(name: str, types_: dict[str, Any]) -> str:
    close = difflib.get_close_matches(name, list(types_), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"{hint}; fields: {', '.join(sorted(types_))}"


def parse_value(tp: Any, raw: str, key: str = "value", flag: str | None = None) -> Any:
    """``raw`` parsed as annotation ``tp`` (see the module doc); a :class:`UserError` naming ``key`` (or the
    option ``flag`` it was given with), the expected type and ``raw`` when it does not parse."""
    try:
        return convert(tp, raw, _TEXT)
    except Mismatch:
        given = f"{flag} {raw}" if flag else f"--set {key}={raw}"
        raise UserError(f"{given}: expected {describe_type(tp)}, got {raw!r}") from None


def _text_leaf(tp: Any, raw: str) -> Any:
    kind, choices, _ = shape_of(tp)
    if kind == tc.LITERAL:
        for choice in choices:
            if str(choice) == raw or (isinstance(choice, bool) and raw.lower() == str(choice).lower()):
                return choice
        raise Mismatch(raw)
    if tp not in _SCALARS:
        _text_record(tp, raw)
    try:
        return _SCALARS[tp](raw)
    except (KeyError, ValueError):
        raise Mismatch(raw) from None


def _text_record(tp: Any, raw: str) -> Any:
    raise UserError(f"fields of type {describe_type(tp)} cannot be set from the command line")


def _float(raw: str) -> float:
    out = float(raw)
    if math.isnan(out):
        raise ValueError("NaN")
    return out


def _path(raw: str) -> Path:
    if not raw:
        raise ValueError("empty path")
    return Path(raw)


#: How the text of a scalar annotation reads; a KeyError or ValueError where it does not.
_SCALARS: dict[Any, Any] = {
    bool: lambda raw: _BOOLS[raw.lower()],
    type(None): lambda raw: dict.fromkeys(_NONE)[raw.lower()],
    int: int,
    float: _float,
    str: str,
    Any: str,
    Path: _path,
}
#: The command line's side of the walk: text, a tuple's items comma-separated.
_TEXT = Surface(
    is_none=lambda raw: raw.lower() in _NONE,
    items=lambda raw: [s.strip() for s in raw.split(",")] if raw.strip() else [],
    leaf=_text_leaf,
    record=_text_record,
)


def describe_type(tp: Any) -> str:
    """The annotation ``tp`` as the user writes its values: ``float``, ``int or none``, ``one of depth,
    disparity``, ``int or one of auto``."""
    kind, args, optional = shape_of(tp)
    if kind == tc.UNION:
        return " or ".join([*map(describe_type, args), *(["none"] if optional else [])])
    if kind == tc.LITERAL:
        return "one of " + ", ".join(str(c) for c in args)
    if kind == tc.VARIADIC:
        return f"comma-separated {describe_type(args[0])} values"
    if kind == tc.FIXED:
        return f"{len(args)} comma-separated values ({', '.join(map(describe_type, args))})"
    if tp is bool:
        return "true/false (also 1/0, yes/no)"
    return "a path" if tp is Path else getattr(tp, "__name__", str(tp))
